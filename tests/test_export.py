"""iris-export: the two ONNX graphs, their validation, the manifest, and every failure path.

The random ``tiny`` model of conftest's ``torch_export`` (exported once per session by
``export_model``) is also saved as a checkpoint and run through the CLI (``--quick`` probes,
``--quantize int8``, one thread: the machine is shared). What is checked:

* the files: manifest fields, sha256 of every graph, self-contained graphs (no ``.data`` file),
  I/O spec as ONNX Runtime sees it, validation report within tolerance;
* round trip like the runtime does it: ORT encoder -> numpy geometry (``iris_runtime.geometry``)
  -> ORT renderer, against torch ``IrisModel.encode`` + ``render_rays`` on fresh random rays,
  within 1e-4, for V' in {1, 2, 5} and several (R, S) (dynamic axes, exported once);
* masking: points masked in every view and rays with every sample masked stay finite and match;
* isolated references: the encoder graph's ``is_reference`` input; the references' field maps and
  cameras equal up to the encoder's float32 rounding (tests/tolerances.py; measured: bitwise)
  whether queries are present, changed or absent,
  and the queries' poses match ``IrisModel.locate``; validation reports probes with queries and
  the isolation check;
* the wrappers compute exactly what the model computes;
* explicit colour (``preset("tiny-rgb")``, conftest ``torch_export_rgb``): the renderer takes
  ``colours`` [V', R, S, 3] as its last input (only such models do), the manifest says so
  (``config.explicit_rgb``, I/O spec 3), its validation covers the same probes, and the round
  trip and masking tests above run on it too (``model_and_sessions``);
* failures: existing OUT_DIR without --force (and --force replacing it), corrupt / truncated /
  foreign checkpoints, tolerance exceeded -> ``ValidationError``; OUT_DIR untouched each time, no
  temporary directory left behind; ``iris-export --help``.

Everything after the session's one real export reuses its graphs (``export_graph`` patched to
copy them): a dynamo export costs 15 s on an idle machine and 1-2 min on a busy one.
"""
from __future__ import annotations

import dataclasses
import json
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
F = torch.nn.functional
onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from iris_runtime import geometry as RG                                    # noqa: E402
from . import np_geometry as NPG                                           # noqa: E402
from iris_train.config import preset                                        # noqa: E402
from iris_train.model import CheckpointError, save_checkpoint              # noqa: E402

from export import io_spec, pipeline                                        # noqa: E402
from export.cli import main as cli_main                                     # noqa: E402
from export.errors import ExportArgumentError, OutputExistsError, ValidationError  # noqa: E402
from export.graphs import EncoderGraph, RendererGraph                       # noqa: E402
from export.manifest import FORMAT, MANIFEST_NAME, VERSION, read_manifest, sha256_file  # noqa: E402
from export.pipeline import export_model                                    # noqa: E402
from export.validate import renderer_inputs, scene_images, scene_rays      # noqa: E402
from iris_train.geometry import sample_bilinear_dense as sample_dense        # noqa: E402

from .conftest import copy_graphs_from                                       # noqa: E402
from .tolerances import encoder_terms, encoder_tol, f32_tol, render_tol, renderer_terms     # noqa: E402

pytestmark = pytest.mark.torch

ROOT = Path(__file__).resolve().parents[1]
CFG = preset("tiny")
H, W = CFG.image_height, CFG.image_width


# -- fixtures ------------------------------------------------------------------------------------
@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Torch eager at 2 threads on 2 busy cores is 10-50x slower than at 1 (spin-waiting)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def model(torch_export):
    """The random tiny model (``torch.manual_seed(0)``) that conftest exported once per session."""
    return torch_export[1]


@pytest.fixture(scope="module")
def checkpoint(model, tmp_path_factory):
    path = tmp_path_factory.mktemp("ckpt") / "tiny.pt"
    save_checkpoint(path, model, step=0)
    return path


@pytest.fixture(scope="module")
def exported(torch_export, checkpoint, tmp_path_factory):
    """``iris-export CKPT OUT --quantize int8`` on the checkpoint of the session's model.

    The dynamo export itself ran once for the whole session (conftest ``torch_export``:
    ``export_model(model, ...)``, 15-40 s); here the CLI loads the checkpoint, reuses those graphs,
    quantises, validates the checkpoint's weights against them and writes the manifest.
    """
    out = tmp_path_factory.mktemp("export") / "model"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pipeline, "export_graph", copy_graphs_from(torch_export[0]))
        rc = cli_main([str(checkpoint), str(out), "--quick", "--quantize", "int8", "--threads", "1", "-q"])
    assert rc == 0
    return out


def _session(path):
    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


@pytest.fixture(scope="module")
def sessions(exported):
    return {"encoder": _session(exported / "encoder.onnx"),
            "renderer": _session(exported / "renderer.onnx")}


@pytest.fixture(scope="module")
def rgb_sessions(torch_export_rgb):
    d = torch_export_rgb[0]
    return {"encoder": _session(d / "encoder.onnx"), "renderer": _session(d / "renderer.onnx")}


@pytest.fixture(scope="module", params=["tiny", "tiny-rgb"])
def model_and_sessions(request):
    """(IrisModel, ORT sessions) of the session's random tiny model and of its explicit-colour
    twin."""
    if request.param == "tiny":
        return request.getfixturevalue("model"), request.getfixturevalue("sessions")
    return request.getfixturevalue("torch_export_rgb")[1], request.getfixturevalue("rgb_sessions")


@pytest.fixture
def copy_graphs(monkeypatch, exported):
    """Make ``export_model`` reuse the module's graphs instead of exporting again."""
    monkeypatch.setattr(pipeline, "export_graph", copy_graphs_from(exported))


def _siblings(path: Path) -> list[str]:
    return sorted(p.name for p in path.parent.iterdir())


# -- files and manifest --------------------------------------------------------------------------
def test_output_files_are_exactly_the_graphs_and_manifest(exported, torch_export):
    assert sorted(p.name for p in exported.iterdir()) == \
        ["encoder.onnx", "iris.json", "renderer.int8.onnx", "renderer.onnx", "renderer_views.onnx"]
    assert _siblings(exported) == ["model"]           # no temporary directory left behind
    plain = torch_export[0]                           # the real export_model(model) output
    assert sorted(p.name for p in plain.iterdir()) == ["encoder.onnx", "iris.json", "renderer.onnx",
                                                       "renderer_views.onnx"]
    assert not list(exported.rglob("*.data")) and not list(plain.rglob("*.data"))
    assert read_manifest(plain)["source"] == {"checkpoint": None}


def test_manifest_content(exported, model, checkpoint):
    m = read_manifest(exported)
    assert (m["format"], m["version"], m["io_spec_version"]) == (FORMAT, VERSION, io_spec.IO_SPEC_VERSION)
    assert m["config"] == model.cfg.to_dict()
    assert m["image_size"] == [H, W] and m["patch_size"] == CFG.patch_size
    assert m["feature_grid"] == list(CFG.field_grid) and m["field_channels"] == CFG.field_channels
    assert (m["near"], m["far"], m["samples"]) == (CFG.near, CFG.far, CFG.samples)
    assert m["median_depth"] == CFG.median_depth
    assert m["export"]["opset"] == io_spec.DEFAULT_OPSET and m["export"]["renderer_sampler"] == "dense"
    assert set(m["export"]["versions"]) >= {"torch", "onnx", "onnxruntime"}
    assert m["source"] == {"checkpoint": checkpoint.name, "sha256": sha256_file(checkpoint)}
    for name, spec in io_spec.GRAPHS.items():
        entry = m["graphs"][name]
        assert entry["file"] == spec["file"]
        # The spec travels through JSON (integer axis keys become strings).
        assert entry["inputs"] == json.loads(json.dumps(spec["inputs"]))
        assert entry["outputs"] == json.loads(json.dumps(spec["outputs"]))
        assert entry["dynamic_axes"] == json.loads(json.dumps(spec["dynamic_axes"]))
        report = m["validation"][name]
        assert report["passed"] and report["enforced"]
        for out, tol in spec["tolerance"].items():
            assert 0 <= report["max_abs_error"][out] <= tol
        assert report["time"]["onnxruntime_median_s"] > 0 and report["time"]["torch_median_s"] > 0
    # Encoder probes: all references and with queries; isolation checked and recorded.
    enc = m["validation"]["encoder"]
    assert {p["queries"] for p in enc["probes"]} >= {0, 1, 2, 3}
    assert enc["isolation"]["passed"] and enc["isolation"]["tolerance"] == 1e-6
    assert all(0 <= e <= enc["isolation"]["tolerance"]
               for e in enc["isolation"]["max_abs_error"].values())
    # Probes covered the edge cases and the view counts.
    probes = m["validation"]["renderer"]["probes"]
    assert {p["V"] for p in probes} == {1, 3, 8} and 1 in {p["R"] for p in probes}
    assert any(p["rays_with_every_sample_masked"] for p in probes)
    assert any(p["points_masked_in_every_view"] for p in probes)
    # int8: its own file, hash and recorded error, not enforced.
    int8 = m["graphs"]["renderer_int8"]
    assert int8["file"] == "renderer.int8.onnx" and int8["variant_of"] == "renderer"
    rep8 = m["validation"]["renderer_int8"]
    assert rep8["enforced"] is False and 0 < rep8["max_abs_error"]["rgb"] < 0.05


def test_sha256_in_manifest_matches_files(exported):
    m = read_manifest(exported / MANIFEST_NAME)
    assert sorted(m["graphs"]) == ["encoder", "renderer", "renderer_int8", "renderer_views"]
    for entry in m["graphs"].values():
        path = exported / entry["file"]
        assert entry["sha256"] == sha256_file(path) and entry["bytes"] == path.stat().st_size


def test_graph_files_are_self_contained_and_valid(exported):
    max_ir = onnx.helper.find_min_ir_version_for([onnx.helper.make_opsetid("", io_spec.DEFAULT_OPSET)])
    for name in ("encoder.onnx", "renderer.onnx", "renderer.int8.onnx", "renderer_views.onnx"):
        proto = onnx.load(str(exported / name), load_external_data=False)
        assert all(t.data_location != onnx.TensorProto.EXTERNAL for t in proto.graph.initializer)
        assert proto.ir_version <= max_ir
        onnx.checker.check_model(proto, full_check=True)


def test_io_names_match_spec(sessions):
    for graph, sess in sessions.items():
        spec = io_spec.GRAPHS[graph]
        assert [i.name for i in sess.get_inputs()] == list(spec["inputs"])
        assert [o.name for o in sess.get_outputs()] == list(spec["outputs"])
        for arg in sess.get_inputs():
            for axis, name in spec["dynamic_axes"].get(arg.name, {}).items():
                assert arg.shape[axis] == name
    mask = next(i for i in sessions["renderer"].get_inputs() if i.name == "mask")
    assert mask.type == "tensor(float)"                   # validity weights (I/O spec 4)
    is_reference = next(i for i in sessions["encoder"].get_inputs() if i.name == "is_reference")
    assert is_reference.type == "tensor(bool)" and is_reference.shape == ["V"]


# -- numbers -------------------------------------------------------------------------------------
def _runtime_render(sessions, images, pose, uv, depths, reverse=0):
    """What the runtime does: ORT encoder, numpy geometry in float32, ORT renderer."""
    maps, world_from_cam, focal = sessions["encoder"].run(
        None, {"images": images, "is_reference": np.ones(len(images), bool)})
    K = RG.intrinsics_from_focal(focal, H, W)
    origins, directions = RG.rays_from_pixels(uv, K, pose)
    if reverse:
        directions[-reverse:] *= -1
    points = origins[:, None, :] + depths[..., None] * directions[:, None, :]          # [R, S, 3]
    uvp, zp, _ = RG.project_points(points, K, RG.invert_pose(world_from_cam), H, W)    # [V, R, S, .]
    valid = RG.validity(uvp, zp, H, W).astype(np.float32)
    cues = RG.geometric_cue(points, origins[:, None, :], world_from_cam[:, :3, 3])     # [R, S, V, 4]
    feed = {"field_maps": maps, "grid": RG.pixels_to_grid(uvp, H, W).astype(np.float32),
            "cues": np.ascontiguousarray(np.moveaxis(cues, 2, 0), dtype=np.float32),
            "mask": valid, "positions": points.astype(np.float32),
            "directions": directions.astype(np.float32)}
    if "colours" in {i.name for i in sessions["renderer"].get_inputs()}:
        feed["colours"] = RG.sample_bilinear_views(images, feed["grid"])   # full-resolution RGB
    rgb, weights = sessions["renderer"].run(None, feed)
    return rgb, weights, origins, directions, valid, (world_from_cam, focal)


@pytest.mark.parametrize("V,R,S", [(1, 1, 64), (2, 37, 64), (5, 50, 23), (2, 8, 1)])
def test_round_trip_against_torch_render_rays(model_and_sessions, V, R, S):
    model, sessions = model_and_sessions
    rng = np.random.default_rng(100 * V + R + S)
    images = scene_images(V, H, W, torch.Generator().manual_seed(V)).numpy()
    # A fresh random target pose near view 0 and random pixels; some rays point backwards.
    angle = rng.uniform(-0.1, 0.1, 3)
    rot = NPG.rotation_from_6d(np.concatenate([[1, angle[2], -angle[1]], [-angle[2], 1, angle[0]]]))
    pose = np.eye(4, dtype=np.float32)
    pose[:3, :3], pose[:3, 3] = rot, rng.uniform(-0.05, 0.05, 3)
    uv = NPG.pixel_centres(H, W, dtype=np.float32)[rng.choice(H * W, R, replace=False)]
    depths = RG.sample_depths(CFG.near, CFG.far, S, R, stratified=True, rng=rng, dtype=np.float32)
    reverse = R // 8
    rgb, weights, origins, directions, valid, (world_from_cam, focal) = _runtime_render(
        sessions, images, pose, uv, depths, reverse)

    with torch.no_grad():
        # torch's field maps, the graph's cameras: the cameras' own rounding would move the
        # projected pixels by an amount that depends on how ill-conditioned the random scene's
        # projection is, which no rounding model bounds (the cameras are compared on their own in
        # test_encoder_graph_isolates_references).
        scene = dataclasses.replace(model.encode(torch.from_numpy(images)),
                                    world_from_cam=torch.from_numpy(world_from_cam),
                                    focal=torch.from_numpy(focal))
        rgb_ref, w_ref = model.render_rays(scene, torch.tensor(origins), torch.tensor(directions),
                                           torch.tensor(depths))
    assert rgb.shape == (R, 3) and weights.shape == (R, S)
    assert np.isfinite(rgb).all() and np.isfinite(weights).all()
    # Two roundings of the encoder's field maps and of the renderer, plus the projection's
    # (pixel coordinates of magnitude <= 2 max(H, W), 3 roundings each) carried through the
    # bilinear sample with a gain of order one. A wrong mask, cue or blend moves rgb by > 1e-2.
    tol = f32_tol(encoder_terms(CFG, V, "field_maps") + renderer_terms(CFG, V) + 6 * max(H, W) + 8)
    np.testing.assert_allclose(rgb, rgb_ref.numpy(), rtol=0, atol=tol)
    np.testing.assert_allclose(weights, w_ref.numpy(), rtol=0, atol=tol)
    if reverse:       # backward rays: every sample masked in every view -> zero weights
        assert not valid[:, -reverse:].any() and np.all(weights[-reverse:] == 0)


def test_encoder_graph_isolates_references(model, sessions):
    """ONNX Runtime: the references' field maps and cameras do not change (up to the encoder's
    float32 rounding: other batches may take other kernels; tests/tolerances.py, ~3e-5 for poses,
    ~6e-5 for field maps of magnitude ~2; measured bitwise) when queries are added, changed or
    removed, and the queries' poses match torch's ``IrisModel.locate``. A query leaking into the
    references moves them by 1e-2 to 1e-1 (tests/test_model.py)."""
    enc = sessions["encoder"]
    g = torch.Generator().manual_seed(11)
    refs, queries = scene_images(4, H, W, g).numpy(), scene_images(3, H, W, g).numpy()

    def run(q):
        images = np.concatenate([refs, q]) if len(q) else refs
        return enc.run(None, {"images": images, "is_reference": np.arange(len(images)) < len(refs)})

    alone = run(queries[:0])
    present, changed, fewer = run(queries), run(1.0 - queries), run(queries[:1])
    views = len(refs) + len(queries)
    for out in (present, changed, fewer):
        for name, a, b in zip(("field_maps", "world_from_cam", "focal"), out, alone):
            rows = slice(None) if name == "focal" else slice(0, len(refs))
            output = {"world_from_cam": "cameras"}.get(name, name)
            tol = encoder_tol(CFG, views, output, max(1.0, float(np.abs(b).max())))
            assert np.abs(a[rows] - b).max() <= tol, name
    with torch.no_grad():
        located = model.locate(torch.from_numpy(refs), torch.from_numpy(queries)).numpy()
    assert np.abs(present[1][len(refs):] - located).max() <= 1e-5
    assert np.abs(present[1][len(refs):] - changed[1][len(refs):]).max() > 0   # queries' own poses
    # Queries independent: a query's pose with the other queries present or absent.
    assert np.abs(fewer[1][len(refs)] - present[1][len(refs)]).max() <= encoder_tol(CFG, views)


def test_encoder_cross_view_mask_is_an_additive_bias(exported):
    """The encoder's cross-view attention adds its mask to the scores as a float bias: the graph
    has no NaN guard behind a softmax (IsNaN), which a bool attention mask exports with
    (docs/PERFORMANCE.md)."""
    ops = [n.op_type for n in onnx.load(str(exported / "encoder.onnx")).graph.node]
    assert "IsNaN" not in ops
    assert ops.count("Softmax") >= 2


def _random_feed(V, R, S, seed, explicit_rgb=False):
    g = torch.Generator().manual_seed(seed)
    h, w = CFG.field_grid
    feed = {"field_maps": torch.randn(V, CFG.field_channels, h, w, generator=g),
            "grid": torch.rand(V, R, S, 2, generator=g) * 2.4 - 1.2,
            "cues": torch.randn(V, R, S, 4, generator=g),
            "mask": (torch.rand(V, R, S, generator=g) * 2 - 0.5).clamp(0, 1),   # 0, edge, 1
            "positions": torch.randn(R, S, 3, generator=g),
            "directions": torch.randn(R, 3, generator=g)}
    if explicit_rgb:
        feed["colours"] = torch.rand(V, R, S, 3, generator=g)
    return feed


@pytest.mark.parametrize("case", ["all", "point", "ray"])
def test_fully_masked_points_and_rays_stay_finite(model_and_sessions, case):
    model, sessions = model_and_sessions
    V, R, S = 3, 4, 9
    feed = _random_feed(V, R, S, seed=7, explicit_rgb=model.cfg.explicit_rgb)
    if case == "all":
        feed["mask"][:] = 0.0
    elif case == "point":
        feed["mask"][:, :, 2] = 0.0            # sample 2 of every ray masked in every view
    else:
        feed["mask"][:, 1] = 0.0               # ray 1: every sample masked
    rgb, weights = sessions["renderer"].run(None, {k: v.numpy() for k, v in feed.items()})
    with torch.no_grad():
        rgb_ref, w_ref = RendererGraph(model)(**feed)
    assert np.isfinite(rgb).all() and np.isfinite(weights).all()
    np.testing.assert_allclose(rgb, rgb_ref.numpy(), rtol=0, atol=render_tol(CFG, V))
    np.testing.assert_allclose(weights, w_ref.numpy(), rtol=0, atol=render_tol(CFG, V))
    empty = ~(feed["mask"].numpy() > 0).any(0)                             # [R, S]
    assert np.all(weights[empty] == 0)
    if case == "all":
        assert np.allclose(rgb, rgb[0])                                    # rgb = head(0) everywhere
    else:
        live = ~empty.all(-1)
        np.testing.assert_allclose(weights[live].sum(-1), 1.0, atol=1e-5)


def test_wrappers_compute_what_the_model_computes(model):
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        images = scene_images(3, H, W, g)
        scene = model.encode(images)
        maps, world_from_cam, focal = EncoderGraph(model)(images, torch.ones(3, dtype=torch.bool))
        assert torch.equal(maps, scene.field_maps) and torch.equal(world_from_cam, scene.world_from_cam)
        assert torch.equal(focal, scene.focal)
        # With queries after the references: the references' rows are encode's (the encoder's
        # float32 rounding of longer attention rows aside, tests/tolerances.py), the queries'
        # poses are locate's.
        queries = scene_images(2, H, W, g)
        maps_q, poses_q, focal_q = EncoderGraph(model)(torch.cat([images, queries]),
                                                       torch.arange(5) < 3)
        scale = max(1.0, float(scene.field_maps.abs().max()))
        torch.testing.assert_close(maps_q[:3], scene.field_maps, rtol=0,
                                   atol=encoder_tol(CFG, 5, "field_maps", scale))
        torch.testing.assert_close(poses_q[:3], scene.world_from_cam, rtol=0,
                                   atol=encoder_tol(CFG, 5, "cameras"))
        assert torch.equal(poses_q[3:], model.locate(images, queries))
        origins, directions, depths = scene_rays(model, scene, 24, g)
        rgb, weights = RendererGraph(model)(**renderer_inputs(scene, origins, directions, depths))
        rgb_ref, w_ref = model.render_rays(scene, origins, directions, depths)
    # The wrapper is render_samples itself: the same sampler as render_rays; its inputs (grid,
    # cues, mask) are computed by export.validate's helpers, so the two differ by the float32
    # rounding of those inputs and of the renderer (tests/tolerances.py: 1.6e-5; rgb and
    # weights in [0, 1]).
    tol = render_tol(CFG, 3)
    torch.testing.assert_close(rgb, rgb_ref, rtol=0, atol=tol)
    torch.testing.assert_close(weights, w_ref, rtol=0, atol=tol)


def test_explicit_rgb_contract(torch_export_rgb, torch_export, rgb_sessions, sessions):
    """Only an explicit-colour model's renderer takes ``colours`` [V', R, S, 3], as its last
    input; the manifest records it (config, I/O spec 3, the renderer's inputs) and its validation
    covers the probes of every model (V' 1/3/8, R 1, fully masked points and rays) in tolerance."""
    rgb_dir, rgb_model = torch_export_rgb
    m = read_manifest(rgb_dir)
    assert m["config"]["explicit_rgb"] is True and m["io_spec_version"] == io_spec.IO_SPEC_VERSION == 4
    spec = io_spec.spec_for("renderer", True)
    assert list(spec["inputs"])[-1] == "colours" and list(spec["inputs"])[:-1] == list(io_spec.RENDERER["inputs"])
    assert spec["inputs"]["colours"] == {"dtype": "float32", "shape": ["V", "R", "S", 3]}
    assert spec["tolerance"] is io_spec.RENDERER["tolerance"]
    for name in ("renderer", "renderer_int8"):
        assert m["graphs"][name]["inputs"] == json.loads(json.dumps(spec["inputs"]))
        assert m["graphs"][name]["dynamic_axes"] == json.loads(json.dumps(spec["dynamic_axes"]))
    inputs = rgb_sessions["renderer"].get_inputs()
    assert [i.name for i in inputs] == list(spec["inputs"])
    assert inputs[-1].shape == ["V", "R", "S", 3] and inputs[-1].type == "tensor(float)"
    assert "colours" not in {i.name for i in sessions["renderer"].get_inputs()}
    assert "colours" not in read_manifest(torch_export[0])["graphs"]["renderer"]["inputs"]
    assert read_manifest(torch_export[0])["config"]["explicit_rgb"] is False
    rep = m["validation"]["renderer"]
    assert rep["passed"] and rep["enforced"]
    assert all(0 <= rep["max_abs_error"][o] <= t for o, t in rep["tolerance"].items())
    probes = rep["probes"]
    assert {p["V"] for p in probes} == {1, 3, 8} and 1 in {p["R"] for p in probes}
    assert any(p["rays_with_every_sample_masked"] for p in probes)
    assert any(p["points_masked_in_every_view"] for p in probes)
    assert any(p["probe"].startswith("scene") for p in probes)
    assert m["validation"]["renderer_int8"]["enforced"] is False
    assert 0 < m["validation"]["renderer_int8"]["max_abs_error"]["rgb"] < 0.05


def test_explicit_rgb_wrapper_computes_what_the_model_computes(torch_export_rgb):
    """RendererGraph on an explicit-colour model = IrisModel.render_rays (the colours sampled as
    field_at samples them); without colours it refuses to run."""
    model = torch_export_rgb[1]
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():
        scene = model.encode(scene_images(3, H, W, g))
        origins, directions, depths = scene_rays(model, scene, 24, g)
        inputs = renderer_inputs(scene, origins, directions, depths)
        assert inputs["colours"].shape == (3, 24, CFG.samples, 3)
        rgb, weights = RendererGraph(model)(**inputs)
        rgb_ref, w_ref = model.render_rays(scene, origins, directions, depths)
        tol = render_tol(model.cfg, 3)                   # as in the test above
        torch.testing.assert_close(rgb, rgb_ref, rtol=0, atol=tol)
        torch.testing.assert_close(weights, w_ref, rtol=0, atol=tol)
        # the residual head is live (random weights): the colour is not the blend alone
        f, points, mask, colours = model.field_at(scene, origins, directions, depths)
        blend = (w_ref[..., None] * colours).sum(1)
        assert (rgb - blend).abs().max() > 1e-3
        inputs.pop("colours")
        with pytest.raises(ExportArgumentError, match="colours"):
            RendererGraph(model)(**inputs)


@pytest.mark.parametrize("seed", [0, 1])
def test_dense_sampler_equals_grid_sample(model, seed):
    g = torch.Generator().manual_seed(seed)
    maps = torch.randn(3, 5, 4, 7, generator=g)
    grid = torch.rand(3, 200, 2, generator=g) * 3.0 - 1.5           # inside, border band, outside
    grid[0, :4] = torch.tensor([[-1.0, -1.0], [1.0, 1.0], [2.0, -2.0], [0.0, 0.0]])
    ref = F.grid_sample(maps, grid[:, None], mode="bilinear", padding_mode="border",
                        align_corners=False)[:, :, 0].transpose(1, 2)
    # Two float32 bilinear samplers: the sample position ((g + 1) * w - 1) / 2 (3 roundings of
    # values <= 2 max(h, w) cells) times the maps' slope (<= 2 max|maps| per cell), plus the
    # interpolation (8 roundings of values <= max|maps|). A tap off by one cell moves samples
    # by O(max|maps|) = O(3).
    m = float(maps.abs().max())
    tol = f32_tol(3, 2 * max(maps.shape[-2:])) * 2 * m + f32_tol(8, m)
    torch.testing.assert_close(sample_dense(maps, grid), ref, rtol=0, atol=tol)
    feed = _random_feed(2, 5, 6, seed)
    with torch.no_grad():
        dense = RendererGraph(model, "dense")(**feed)
        gs = RendererGraph(model, "grid_sample")(**feed)
    # The renderer's rounding (rgb and weights in [0, 1]) plus the samplers' difference (above)
    # carried through it with a gain of order one relative to the maps' magnitude: 3 position
    # roundings of values <= 2 max(h, w) cells (6 max(h, w) unit terms) and 8 of the
    # interpolation.
    tol = f32_tol(renderer_terms(CFG, 2) + 6 * max(CFG.field_grid) + 8)
    for a, b in zip(dense, gs):
        torch.testing.assert_close(a, b, rtol=0, atol=tol)


# -- failure paths -------------------------------------------------------------------------------
def test_existing_out_dir_is_refused_without_force(checkpoint, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(OutputExistsError, match="already exists"):
        export_model(checkpoint, out, progress=False)
    rc = cli_main([str(checkpoint), str(out), "-q"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "already exists" in err and "Traceback" not in err
    assert [p.name for p in out.iterdir()] == ["keep.txt"] and _siblings(out) == ["out"]


def test_force_replaces_existing_out_dir(checkpoint, tmp_path, copy_graphs):
    out = tmp_path / "out"
    out.mkdir()
    (out / "stale.txt").write_text("old")
    export_model(checkpoint, out, force=True, progress=False, quick=True, threads=1)
    assert sorted(p.name for p in out.iterdir()) == ["encoder.onnx", "iris.json", "renderer.onnx",
                                                     "renderer_views.onnx"]
    assert _siblings(out) == ["out"]


def _truncated(path, src):
    data = src.read_bytes()
    path.write_bytes(data[: len(data) // 2])


class _Foreign:
    pass


BAD_CHECKPOINTS = {
    "random_bytes": lambda p, src: p.write_bytes(np.random.default_rng(0).bytes(4096)),
    "truncated": _truncated,
    "empty": lambda p, src: p.write_bytes(b""),
    "foreign_state_dict": lambda p, src: torch.save({"state_dict": {"w": torch.zeros(2)}}, p),
    "foreign_pickle": lambda p, src: p.write_bytes(pickle.dumps(_Foreign())),
    "wrong_weights": lambda p, src: torch.save({**torch.load(src, weights_only=True),
                                                "model": {"w": torch.zeros(2)}}, p),
    "missing": lambda p, src: None,
}


@pytest.mark.filterwarnings("ignore:Detected pickle protocol")
@pytest.mark.parametrize("kind", sorted(BAD_CHECKPOINTS))
def test_bad_checkpoint_gives_one_line_error(kind, checkpoint, tmp_path, capsys):
    bad = tmp_path / f"{kind}.pt"
    BAD_CHECKPOINTS[kind](bad, checkpoint)
    out = tmp_path / "out"
    with pytest.raises(CheckpointError):
        export_model(bad, out, progress=False)
    rc = cli_main([str(bad), str(out), "-q"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and str(bad) in err and "Traceback" not in err
    assert not out.exists() and not any(n.startswith(".out") for n in _siblings(out))


def test_tolerance_exceeded_raises_and_writes_nothing(checkpoint, tmp_path, monkeypatch, copy_graphs,
                                                      capsys):
    monkeypatch.setitem(io_spec.RENDERER["tolerance"], "rgb", 1e-12)
    out = tmp_path / "out"
    with pytest.raises(ValidationError) as info:
        export_model(checkpoint, out, progress=False, quick=True, threads=1)
    exc = info.value
    assert (exc.graph, exc.output, exc.tolerance) == ("renderer", "rgb", 1e-12)
    assert exc.error > 1e-12 and "'rgb'" in str(exc) and "1e-12" in str(exc)
    assert not out.exists() and _siblings(out) == []
    rc = cli_main([str(checkpoint), str(out), "-q", "--quick", "--threads", "1"])
    err = capsys.readouterr().err
    assert rc == 1 and err.count("\n") == 1 and "validation failed" in err
    assert not out.exists() and _siblings(out) == []


@pytest.mark.parametrize("kwargs", [{"opset": 17}, {"opset": 1000}, {"quantize": "int4"}, {"threads": 0},
                                    {"cameras": "refined"}, {"cameras": "solve"},
                                    {"cameras": "colmap"}])
def test_bad_arguments_are_refused(checkpoint, tmp_path, kwargs):
    with pytest.raises(ExportArgumentError):      # the checkpoint's renderer: "model" cameras
        export_model(checkpoint, tmp_path / "out", progress=False, **kwargs)
    assert not (tmp_path / "out").exists()


def test_default_cameras_are_the_trained_ones_or_refined_over_solved_ones():
    """The manifest's default cameras: the ones the renderer was trained with, or "refined" (the
    camera head's refined by the photos, in the solve's unit) over a renderer trained on the
    solve's cameras, by default where the head was distilled from the solve; nothing else."""
    assert pipeline._default_cameras(None, "solve") == "solve"
    assert pipeline._default_cameras(None, "solve", distilled=True) == "refined"
    assert pipeline._default_cameras(None, "model", distilled=True) == "model"
    assert pipeline._default_cameras("solve", "solve", distilled=True) == "solve"
    assert pipeline._default_cameras("refined", "solve") == "refined"
    assert pipeline._default_cameras("model", "model") == "model"
    for cameras, trained in (("refined", "model"), ("model", "solve"), ("solve", "model")):
        with pytest.raises(ExportArgumentError, match=f"not {cameras!r}"):
            pipeline._default_cameras(cameras, trained)


def test_cli_help():
    res = subprocess.run([sys.executable, "-m", "export.cli", "--help"], cwd=ROOT,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0
    for flag in ("CKPT", "OUT_DIR", "--opset", "--quantize", "--force"):
        assert flag in res.stdout
