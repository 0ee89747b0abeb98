"""Shared fixtures: one exported model per test session.

``model_dir`` is ``IRIS_TEST_MODEL_DIR`` (an ``iris-export`` output directory) when set, which is
how the runtime tests run in the environment without torch; otherwise, when torch is installed, a
random tiny model (``torch.manual_seed(0); build_model(preset("tiny"))``) exported once per
session (``torch_export``). Tests that compare with ``IrisModel`` use ``torch_export`` directly.

``rgb_model_dir`` / ``torch_export_rgb`` are the same for an explicit-colour model
(``preset("tiny-rgb")``, exported once per session with its int8 renderer; its residual rgb head,
which a new model starts at zero, gets random weights so that parity covers it):
``IRIS_TEST_RGB_MODEL_DIR`` when set. ``any_model_dir`` is parametrized over both models for the
runtime tests that are cheap enough to run twice.
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest


def load_script(name: str):
    """``scripts/NAME.py`` as a module (scripts/ is not a package), registered in
    ``sys.modules`` so that its dataclasses can find their module."""
    import importlib.util
    import sys
    spec = importlib.util.spec_from_file_location(name, Path(__file__).resolve().parents[1]
                                                  / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def has_torch() -> bool:
    try:
        import torch  # noqa: F401
    except ImportError:
        return False
    return True


def random_model(preset_name: str = "tiny", **config):
    """``torch.manual_seed(0); build_model(preset(preset_name))`` (with ``config``'s fields
    replaced) in eval mode; for explicit-colour models the residual rgb head (zero at
    initialisation) then gets N(0, 0.2) weights, a fine-feature stem (``map_scale`` > 1) its
    mix (zero at initialisation too) N(0, 0.05), and a colour-deviation map (zero too) N(0,
    0.3): zero layers would hide the paths they gate from every parity test."""
    import dataclasses

    import torch

    import iris_train

    torch.manual_seed(0)
    cfg = dataclasses.replace(iris_train.preset(preset_name), **config)
    model = iris_train.build_model(cfg).eval()
    if model.cfg.explicit_rgb:
        with torch.no_grad():
            for p in model.renderer.rgb_head[-1].parameters():
                p.normal_(0.0, 0.2)
    with torch.no_grad():
        if model.fine_features is not None:
            for p in model.fine_features.mix.parameters():
                p.normal_(0.0, 0.05)
        if model.field.deviation_to_maps is not None:
            model.field.deviation_to_maps.weight.normal_(0.0, 0.3)
    return model


def _export_random_tiny(tmp_path_factory, name: str, quantize=None, preset_name: str = "tiny",
                        **config):
    """(model_dir, IrisModel): a random tiny model (seed 0) exported once (needs torch and onnx)."""
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from export.pipeline import export_model

    model = random_model(preset_name, **config)
    out = tmp_path_factory.mktemp(name) / preset_name
    export_model(model, out, quick=True, progress=False, threads=1, quantize=quantize)
    return out, model


@pytest.fixture(scope="session")
def torch_export(tmp_path_factory):
    """(model_dir, IrisModel): a random tiny model and its export."""
    return _export_random_tiny(tmp_path_factory, "iris_model")


def copy_graphs_from(src_dir, trace=()):
    """An ``export.graphs.export_graph`` stand-in that copies the graphs already exported to
    ``src_dir`` (of a model with the same weights) but those named in ``trace``, which it
    exports: ``export_model`` with it still quantises, validates every graph against the model
    it is given (so a graph of other weights fails) and writes the manifest, without tracing the
    copied graphs again (torch.onnx.export: 15-60 s a graph)."""
    import shutil

    import onnx

    from export import io_spec
    from export.graphs import GraphFile, export_graph

    def fake_export_graph(model, graph, path, opset=io_spec.DEFAULT_OPSET, wrapper=None):
        if graph in trace:
            return export_graph(model, graph, path, opset, wrapper)
        src = Path(src_dir) / io_spec.spec_for(graph)["file"]
        shutil.copyfile(src, path)
        return GraphFile(graph, Path(path), len(onnx.load(str(src)).graph.node), 0.0)
    return fake_export_graph


@pytest.fixture(scope="session")
def torch_export_int8(torch_export, tmp_path_factory):
    """Like ``torch_export``, also with the int8 renderer (``--quantize int8``). The same model
    (a fresh copy: seed 0), so its float graphs are ``torch_export``'s, copied rather than traced
    again (``copy_graphs_from``); the int8 renderer is quantised from them and every graph is
    validated against the model as in any export."""
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    from export import pipeline

    model = random_model("tiny")
    out = tmp_path_factory.mktemp("iris_model_int8") / "tiny"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pipeline, "export_graph", copy_graphs_from(torch_export[0]))
        pipeline.export_model(model, out, quick=True, progress=False, threads=1, quantize="int8")
    return out, model


@pytest.fixture(scope="session")
def torch_export_rgb(tmp_path_factory):
    """(model_dir, IrisModel): a random explicit-colour model (``tiny-rgb``) and its export, with
    the int8 renderer (one export serves the float and the int8 tests). It weights the views of
    its colour blend by angle (``blend_angle`` 0.02), so the torch-free paths that blend colours
    in numpy (two scales, the residual) are held to the graph's weighting; the shipped model,
    which CI's torch-free environment tests, may blend them plainly."""
    return _export_random_tiny(tmp_path_factory, "iris_model_rgb", quantize="int8",
                               preset_name="tiny-rgb", blend_angle=0.02)


@pytest.fixture(scope="session")
def torch_export_fine(tmp_path_factory):
    """(model_dir, IrisModel): a random explicit-colour model with field maps at twice the token
    grid (``map_scale`` 2: 16x16, the fine-feature stem) and the views' colour deviation as a
    field input (``colour_deviation``), and its export."""
    return _export_random_tiny(tmp_path_factory, "iris_model_fine", preset_name="tiny-rgb",
                               blend_angle=0.02, map_scale=2, colour_deviation=True)


#: The shipped, trained model (explicit colour, a camera head on its own encoder, plain blend).
SHIPPED = Path(__file__).resolve().parents[1] / "models" / "iris-tiny-rgb.pt"


@pytest.fixture(scope="session")
def shipped_export(tmp_path_factory):
    """(model_dir, IrisModel): ``SHIPPED`` exported once per session (``export_model`` with its
    defaults, quick probes) and loaded in torch; skips without torch, onnx or the checkpoint."""
    pytest.importorskip("torch")
    pytest.importorskip("onnx")
    if not SHIPPED.is_file():
        pytest.skip("no shipped model")
    from export.pipeline import export_model
    from iris_train import load_model
    out = export_model(SHIPPED, tmp_path_factory.mktemp("shipped") / "model", quick=True,
                       progress=False, threads=1)
    return out, load_model(SHIPPED)


def resolve_model_dir(request, export_fixture: str, env_var: str = "IRIS_TEST_MODEL_DIR") -> Path:
    """``env_var`` if set, else the export made by ``export_fixture`` (needs torch)."""
    env = os.environ.get(env_var)
    if env:
        return Path(env)
    if not has_torch():
        pytest.skip(f"no {env_var} and no torch to export a model")
    return request.getfixturevalue(export_fixture)[0]


@pytest.fixture(scope="session")
def model_dir(request) -> Path:
    return resolve_model_dir(request, "torch_export")


@pytest.fixture(scope="session")
def rgb_model_dir(request) -> Path:
    """An explicit-colour model: ``IRIS_TEST_RGB_MODEL_DIR`` or the random ``tiny-rgb`` export."""
    return resolve_model_dir(request, "torch_export_rgb", "IRIS_TEST_RGB_MODEL_DIR")


@pytest.fixture(scope="session", params=["tiny", "tiny-rgb"])
def any_model_dir(request) -> Path:
    """``model_dir`` and ``rgb_model_dir`` in turn."""
    return request.getfixturevalue("model_dir" if request.param == "tiny" else "rgb_model_dir")
