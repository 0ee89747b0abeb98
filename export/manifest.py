"""The manifest ``iris.json`` that sits beside the exported graphs.

It is everything the torch-free runtime needs to use the graphs without importing ``export``:
format name and version, the model config and the numbers derived from it (image size, patch size,
feature grid, field channels, near/far, samples), the exporter's settings and library versions,
per graph its file name, sha256, size and I/O spec (``iris_runtime.io_spec``), and the validation
report (max abs error of ONNX Runtime vs torch per output, tolerances, median times). Layout::

    {
      "format": "iris-model", "version": 2, "io_spec_version": 4,
      "created": "YYYY-MM-DDThh:mm:ssZ",                 # UTC, when it was written
      "config": {...ModelConfig.to_dict()...},
      "image_size": [H, W], "patch_size": p, "feature_grid": [h, w], "field_channels": C',
      "near": 0.1, "far": 1.0, "samples": 64,
      "dims": {"H": H, "W": W, "h": h, "w": w, "C'": C'},     # values of the spec's fixed axes
      "export": {"exporter": ..., "opset": 20, "ir_version": 9, "renderer_sampler": "dense",
                 "versions": {"torch": ..., "onnx": ..., "onnxruntime": ..., "onnxscript": ...}},
      "source": {"checkpoint": "ckpt.pt", "sha256": ...} | {"checkpoint": null},
      "graphs": {
        "encoder":  {"file": "encoder.onnx", "sha256": ..., "bytes": ..., "nodes": ...,
                     "inputs": {...}, "outputs": {...}, "dynamic_axes": {...}, "tolerance": {...}},
        "renderer": {...},
        "renderer_int8": {..., "variant_of": "renderer", "precision": "int8",  # only with --quantize int8
                          "tolerance": null}     # its error is in "validation", not enforced
      },
      "validation": {"quick": false, "encoder": {..., "isolation": {...}}, "renderer": {...},
                     "renderer_int8": {...}}
    }

Versions: 2 (this one) = the encoder graph takes ``is_reference [V]`` (isolated references,
queries located in their frame) and the encoder validation covers probes with queries and the
isolation check; 1 = the encoder took ``images`` only and every view saw every other. The runtime
refuses version 1 with a ``ModelFormatError`` that says to re-export with iris-export (the
checkpoint's weights are unchanged; only the graph's contract is new).

Explicit colour. Whether the model is an explicit-colour model is ``config.explicit_rgb`` (the
one place it is recorded; absent in configs written before it = False). For such a model the
renderer's ``inputs`` (here and in the graph) end with ``colours`` [V', R, S, 3]
(``io_spec.EXPLICIT_RGB_INPUTS``); other models' renderers have no such input.

``io_spec_version`` is the version of the graphs' I/O (``io_spec.IO_SPEC_VERSION``, 4: the
renderers' ``mask`` is float32 validity weights); the layout of this file is unchanged by it
(still version 2). The runtime reads only the current I/O spec version and refuses older ones
with a re-export hint.

JSON turns the integer axis keys of ``dynamic_axes`` into strings ("0"); non-finite numbers in the
validation report (an int8 error can be ``inf`` if it produced NaN) are written as strings.

The format name, versions and file name are declared once, in ``iris_runtime.io_spec`` (the
runtime's reader checks against the same constants); ``FORMAT`` and ``VERSION`` are their names here.
"""
from __future__ import annotations

import math
import os
from datetime import datetime, timezone
from pathlib import Path

from iris_runtime.fileio import atomic_write_json, read_json, sha256_file
from iris_runtime.io_spec import FORMAT_NAME as FORMAT
from iris_runtime.io_spec import FORMAT_VERSION as VERSION
from iris_runtime.io_spec import IO_SPEC_VERSION, MANIFEST_NAME
from iris_train.config import ModelConfig


def graph_entry(path: str | os.PathLike, spec: dict, nodes: int, **extra) -> dict:
    """One ``graphs`` entry: file name (relative to the manifest), sha256, size, I/O spec."""
    path = Path(path)
    return {"file": path.name, "sha256": sha256_file(path), "bytes": path.stat().st_size,
            "nodes": nodes, **extra,
            "inputs": spec["inputs"], "outputs": spec["outputs"],
            "dynamic_axes": spec["dynamic_axes"], "tolerance": spec["tolerance"]}


def versions() -> dict[str, str]:
    import onnx
    import onnxruntime
    import onnxscript
    import torch
    return {"torch": torch.__version__, "onnx": onnx.__version__,
            "onnxruntime": onnxruntime.__version__, "onnxscript": onnxscript.__version__}


def build_manifest(cfg: ModelConfig, graphs: dict[str, dict], validation: dict, *, opset: int,
                   ir_version: int, exporter: str, source: dict, cameras: str = "model",
                   **export_info) -> dict:
    h, w = cfg.field_grid       # the field maps' grid: the tokens' times config.map_scale
    return {
        "format": FORMAT,
        "version": VERSION,
        "io_spec_version": IO_SPEC_VERSION,
        "created": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "config": cfg.to_dict(),
        "image_size": [cfg.image_height, cfg.image_width],
        "patch_size": cfg.patch_size,
        "feature_grid": [h, w],
        "field_channels": cfg.field_channels,
        "near": cfg.near,
        "far": cfg.far,
        "samples": cfg.samples,
        "median_depth": cfg.median_depth,
        "cameras": cameras,
        "dims": {"H": cfg.image_height, "W": cfg.image_width, "h": h, "w": w,
                 "C'": cfg.field_channels},
        "export": {"exporter": exporter, "opset": opset, "ir_version": ir_version, **export_info,
                   "versions": versions()},
        "source": source,
        "graphs": graphs,
        "validation": validation,
    }


def _json_safe(x):
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    return x


def write_manifest(path: str | os.PathLike, manifest: dict) -> Path:
    """Write ``manifest`` as strict JSON (non-finite numbers as strings), atomically."""
    path = Path(path)
    atomic_write_json(path, _json_safe(manifest))
    return path


def read_manifest(path_or_dir: str | os.PathLike) -> dict:
    """Read ``iris.json`` (given the file or its directory) unchecked, for tests and tools
    (``iris_runtime.manifest.read_manifest`` is the checked reader)."""
    path = Path(path_or_dir)
    if path.is_dir():
        path = path / MANIFEST_NAME
    return read_json(path, what=f"the {MANIFEST_NAME} manifest written by iris-export")


__all__ = ["FORMAT", "VERSION", "MANIFEST_NAME", "sha256_file", "graph_entry", "build_manifest",
           "write_manifest", "read_manifest", "versions"]
