"""The ``--set NAME=VALUE`` settings of the camera studies: a setting of ``iris_runtime.cameras``
changed for one run, kept here for the benchmarks that take it (``encode_cost``, ``refine_cost``;
``witness_quality`` parses its options with ``parse_value``) and for the scripts that study the
camera solve (``scripts/camera_study.py``, ``scripts/refine_signals.py``), so that no benchmark
imports a script.

- ``MODULE.NAME=VALUE``: a constant of ``iris_runtime.cameras.MODULE``, set in every module of
  ``MODULES`` that holds that name (imported names are copies);
- ``refine.STAGE.FIELD=VALUE``: a field of one stage of the refinement's settings
  (``refine.RefineOptions``, e.g. ``refine.adjust.tolerance=1e-6``);
- ``FIELD=VALUE``: a field of ``MapperOptions`` (``apply`` returns them).

Values take the type of the setting they replace (a tuple: comma-separated). Torch-free.
"""
from __future__ import annotations

import dataclasses
import importlib

MODULES = ("features", "two_view", "tracks", "triangulation", "bundle", "locate", "mapper",
           "solve", "replace", "refine")


def parse_value(text: str, like):
    """``text`` as a value of the type of ``like`` (a tuple: comma-separated, of the type of
    its first item)."""
    if isinstance(like, tuple):
        return tuple(type(like[0])(x) for x in text.split(","))
    return type(like)(text)


def apply(settings: list[str]):
    """Apply ``--set`` settings (the module docstring's forms); returns the ``MapperOptions``
    to solve with."""
    from iris_runtime.cameras import MapperOptions
    fields = {}
    for item in settings:
        key, text = item.split("=", 1)
        if key.startswith("refine.") and key.count(".") == 2:
            # A field of one stage of the refinement: refine.STAGE.FIELD (RefineOptions).
            from iris_runtime.cameras.refine import ladder
            _, stage, name = key.split(".")
            group = getattr(ladder.DEFAULTS, stage)
            group = dataclasses.replace(group, **{name: parse_value(text, getattr(group, name))})
            ladder.DEFAULTS = dataclasses.replace(ladder.DEFAULTS, **{stage: group})
        elif "." in key:
            mod, name = key.rsplit(".", 1)
            module = importlib.import_module(f"iris_runtime.cameras.{mod}")
            value = parse_value(text, getattr(module, name))
            for m in MODULES:
                module = importlib.import_module(f"iris_runtime.cameras.{m}")
                if hasattr(module, name):
                    setattr(module, name, value)
        else:
            fields[key] = parse_value(text, getattr(MapperOptions(), key))
    return MapperOptions(**fields)
