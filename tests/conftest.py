"""Shared fixtures: one exported model per test session.

``model_dir`` is ``IRIS_TEST_MODEL_DIR`` (an ``iris-export`` output directory) when set, which is
how the runtime tests run in the environment without torch; otherwise, when torch is installed, a
random tiny model (``torch.manual_seed(0); build_model(preset("tiny"))``) exported once per
session (``torch_export``). Tests that compare with ``IrisModel`` use ``torch_export`` directly.
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest


def has_torch() -> bool:
    try:
        import torch  # noqa: F401
    except ImportError:
        return False
    return True


def _export_random_tiny(tmp_path_factory, name: str, quantize=None):
    """(model_dir, IrisModel): a random tiny model (seed 0) exported once (needs torch and onnx)."""
    torch = pytest.importorskip("torch")
    pytest.importorskip("onnx")
    import iris_train
    from export.pipeline import export_model

    torch.manual_seed(0)
    model = iris_train.build_model(iris_train.preset("tiny")).eval()
    out = tmp_path_factory.mktemp(name) / "tiny"
    export_model(model, out, quick=True, progress=False, threads=1, quantize=quantize)
    return out, model


@pytest.fixture(scope="session")
def torch_export(tmp_path_factory):
    """(model_dir, IrisModel): a random tiny model and its export."""
    return _export_random_tiny(tmp_path_factory, "iris_model")


@pytest.fixture(scope="session")
def torch_export_int8(tmp_path_factory):
    """Like ``torch_export``, also with the int8 renderer (``--quantize int8``)."""
    return _export_random_tiny(tmp_path_factory, "iris_model_int8", quantize="int8")


def resolve_model_dir(request, export_fixture: str) -> Path:
    """``IRIS_TEST_MODEL_DIR`` if set, else the export made by ``export_fixture`` (needs torch)."""
    env = os.environ.get("IRIS_TEST_MODEL_DIR")
    if env:
        return Path(env)
    if not has_torch():
        pytest.skip("no IRIS_TEST_MODEL_DIR and no torch to export a model")
    return request.getfixturevalue(export_fixture)[0]


@pytest.fixture(scope="session")
def model_dir(request) -> Path:
    return resolve_model_dir(request, "torch_export")
