"""The alternative renderer graph (``export.fast_renderer.FastRendererGraph``): same function as the
torch renderer, laid out for ONNX Runtime's CPU kernels.

* torch parity with ``IrisModel.render_samples`` (``RendererGraph``) within 1e-5 on rgb and weights,
  for both renderer kinds (``tiny``: the paper's renderer, weights from the last ray attention;
  ``tiny-rgb``: explicit colour, weights = blend weights), with and without the ``com.microsoft``
  contrib ops, on: random probes whose mask has points seen by no view and rays with no valid
  sample, a call where everything is masked, a single view, per-point top-k masks, a fed subset of
  the views, real scene geometry (``Scene.project_samples``, against ``render_rays``), the
  ``grid_sample`` sampler, and configs with other depths / widths / heads (non-power-of-two
  attention scale);
* the latent field itself (before the ray transformer) equals ``IrisModel.field_from_samples``,
  points seen by no view included (the masked max-pool of nothing is 0, their attention is 0);
* ONNX: each kind exported once (module-scoped; ~15 s each on an idle machine), ONNX Runtime vs
  torch within 1e-5 on several (V', R, S) through the dynamic axes, I/O exactly the spec's, no
  ``Where`` node and, after ONNX Runtime's optimisations, no Transpose but the ray attentions'
  head merges;
* the export option: ``export_model(..., renderer="fast")`` records it in the manifest and
  ``IrisRuntime`` renders that model like torch (the session's export of the shipped model),
  unknown kinds are refused, ``iris-export --renderer`` parses.
"""
from __future__ import annotations

import collections
import json
import tempfile
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from iris_runtime import quality as Q                                       # noqa: E402
from iris_train.config import ModelConfig                                   # noqa: E402
from iris_train.layers import validity_bias                                 # noqa: E402
from iris_train.model import build_model                                    # noqa: E402

from export import io_spec                                                  # noqa: E402
from export.errors import ExportArgumentError                               # noqa: E402
from export.fast_renderer import (FastRendererGraph, SelectedViewsRendererGraph,  # noqa: E402
                                  renderer_wrapper)
from export.graphs import DEFAULT_OPSET, RendererGraph, export_graph        # noqa: E402
from export.validate import (random_renderer_inputs, renderer_inputs,      # noqa: E402
                             scene_images, scene_rays, selected_view_inputs)

from .conftest import random_model                                          # noqa: E402

pytestmark = pytest.mark.torch

TOL = 1e-5
PRESETS = ("tiny", "tiny-rgb")
SHAPES = [(1, 1, 1), (1, 9, 17), (3, 9, 64), (8, 5, 23)]        # (V', R, S)


def export_fast_renderer(model, path, *, contrib: bool = False):
    """``FastRendererGraph(model, contrib=contrib)`` exported to ``path`` by
    ``export.graphs.export_graph`` (the exporter, axis names, IR version and checks of the
    reference renderer) -> ``GraphFile``."""
    return export_graph(model, "renderer", path, DEFAULT_OPSET,
                        wrapper=FastRendererGraph(model, contrib=contrib))


def op_histogram(path, optimized: bool = False) -> collections.Counter:
    """Op-type counts of the ONNX graph at ``path``; ``optimized``: of the graph ONNX Runtime runs
    after its ``ORT_ENABLE_ALL`` optimisations (what ``IrisRuntime`` loads), written to a temporary
    file and read back (contrib ops counted as ``com.microsoft.<op>``)."""
    if optimized:
        with tempfile.TemporaryDirectory() as tmp:
            opts = ort.SessionOptions()
            opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
            opts.optimized_model_filepath = str(Path(tmp) / "optimized.onnx")
            opts.intra_op_num_threads = 1
            opts.log_severity_level = 3
            ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])
            proto = onnx.load_model(opts.optimized_model_filepath)
    else:
        proto = onnx.load_model(str(path))
    return collections.Counter((f"{n.domain}.{n.op_type}" if n.domain not in ("", "ai.onnx")
                                else n.op_type) for n in proto.graph.node)


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)                                # the machine is shared
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module", params=PRESETS)
def model(request):
    return random_model(request.param)


def _errors(a, b) -> list[float]:
    return [float((torch.as_tensor(x) - torch.as_tensor(y)).abs().max()) for x, y in zip(a, b)]


@torch.no_grad()
def _check(model, inputs: dict, contrib: bool, reference=None):
    """FastRendererGraph vs the reference (default ``RendererGraph``) within TOL; both finite."""
    args = tuple(inputs.values())
    want = (reference or RendererGraph(model))(*args)
    got = FastRendererGraph(model, contrib=contrib)(*args)
    assert all(torch.isfinite(g).all() for g in got)
    assert [tuple(g.shape) for g in got] == [tuple(w.shape) for w in want]
    errors = _errors(got, want)
    assert max(errors) <= TOL, errors
    return got


# -- torch parity ---------------------------------------------------------------------------------
@pytest.mark.parametrize("contrib", [False, True])
@pytest.mark.parametrize("V,R,S", SHAPES)
def test_random_probes_match_torch(model, contrib, V, R, S):
    # random_renderer_inputs masks sample 0 of every ray in every view (a point seen by no view)
    # and, for R > 1, every sample of the last ray (a ray with no valid sample).
    inputs = random_renderer_inputs(model, V, R, S, torch.Generator().manual_seed(V * 100 + R + S))
    _, weights = _check(model, inputs, contrib)
    assert torch.equal(weights[:, 0], torch.zeros(R))        # the point seen by no view
    seen = (inputs["mask"] > 0).any(0).any(-1)               # rays with a valid sample
    assert torch.equal(weights[~seen], torch.zeros_like(weights[~seen]))    # exactly zero
    assert torch.allclose(weights[seen].sum(-1), torch.ones(int(seen.sum())), atol=1e-5)


@pytest.mark.parametrize("contrib", [False, True])
def test_everything_masked(model, contrib):
    """No valid (view, sample) at all: rgb = head(0) (+ the blend of nothing), weights 0."""
    inputs = random_renderer_inputs(model, 2, 4, 6, torch.Generator().manual_seed(3))
    inputs["mask"][:] = 0.0
    rgb, weights = _check(model, inputs, contrib)
    assert torch.equal(weights, torch.zeros_like(weights))
    assert torch.allclose(rgb, rgb[:1].expand_as(rgb))      # every ray the same colour


@pytest.mark.parametrize("contrib", [False, True])
def test_every_sample_at_full_weight(model, contrib):
    """All validity weights 1: the ray attentions skip their key-bias Add (``_key_softmax``'s
    other branch), same values; the weights of each ray sum to one."""
    inputs = random_renderer_inputs(model, 3, 5, 17, torch.Generator().manual_seed(4))
    inputs["mask"][:] = 1.0
    _, weights = _check(model, inputs, contrib)
    assert torch.allclose(weights.sum(-1), torch.ones(5), atol=1e-5)


@pytest.mark.parametrize("contrib", [False, True])
@pytest.mark.parametrize("k", [1, 2])
def test_top_k_masks_and_view_subsets(model, contrib, k):
    """Per-point top-k (the runtime's ``quality.top_k_mask`` on the cue's t.s) and a call fed a
    subset of the views (``top_k_by="ray"``) give the reference's values."""
    inputs = random_renderer_inputs(model, 5, 7, 31, torch.Generator().manual_seed(k))
    score = inputs["cues"][..., 3].numpy()
    keep = Q.top_k_mask(inputs["mask"].numpy() > 0, score, k)
    inputs["mask"] = inputs["mask"] * torch.from_numpy(keep)
    _check(model, inputs, contrib)
    views = [4, 1, 2][:k + 1]                                   # a subset, in another order
    sub = {name: (t[views] if t.ndim >= 3 and name != "positions" else t)
           for name, t in inputs.items()}
    _check(model, sub, contrib)


@pytest.mark.parametrize("contrib", [False, True])
def test_scene_geometry_matches_render_rays(model, contrib):
    """Samples projected by ``Scene.project_samples`` (rays backwards included: samples behind
    every camera) against ``IrisModel.render_rays`` itself."""
    g = torch.Generator().manual_seed(5)
    cfg = model.cfg
    with torch.no_grad():
        scene = model.encode(scene_images(3, cfg.image_height, cfg.image_width, g))
        origins, directions, depths = scene_rays(model, scene, 24, g)
        want = model.render_rays(scene, origins, directions, depths)
        inputs = renderer_inputs(scene, origins, directions, depths)
        got = FastRendererGraph(model, contrib=contrib)(*inputs.values())
    errors = _errors(got, want)
    assert max(errors) <= TOL, errors


def test_grid_sample_sampler(model):
    inputs = random_renderer_inputs(model, 3, 5, 9, torch.Generator().manual_seed(6))
    with torch.no_grad():
        want = RendererGraph(model, sampler="grid_sample")(*inputs.values())
        got = FastRendererGraph(model, sampler="grid_sample")(*inputs.values())
    assert max(_errors(got, want)) <= TOL


@pytest.mark.parametrize("explicit_rgb", [False, True])
@pytest.mark.parametrize("shape", [
    {"field_width": 48, "field_heads": 4, "view_blocks": 2, "ray_blocks": 3},
    {"field_width": 32, "field_heads": 2, "view_blocks": 1, "ray_blocks": 1}])
def test_other_configs(shape, explicit_rgb):
    """More view/ray blocks, one ray block, Dh = 12 (attention scale not a power of two)."""
    torch.manual_seed(1)
    model = build_model(ModelConfig(encoder_width=32, encoder_heads=2, encoder_pairs=1,
                                    explicit_rgb=explicit_rgb, **shape)).eval()
    if explicit_rgb:
        with torch.no_grad():
            for p in model.renderer.rgb_head[-1].parameters():
                p.normal_(0.0, 0.2)
    inputs = random_renderer_inputs(model, 3, 6, 19, torch.Generator().manual_seed(7))
    for contrib in (False, True):
        _check(model, inputs, contrib)


@torch.no_grad()
def test_finer_maps_and_colour_deviation():
    """``map_scale`` 2 (16x16 maps through the dense tent matmul) and ``colour_deviation`` (one
    more additive term a slot, from the views' colours and validity): the full renderer and the
    selected-views one against the torch model."""
    model = random_model("tiny-rgb", map_scale=2, colour_deviation=True, blend_angle=0.02)
    inputs = random_renderer_inputs(model, 4, 7, 13, torch.Generator().manual_seed(5))
    assert inputs["field_maps"].shape[-2:] == (16, 16)
    for contrib in (False, True):
        _check(model, inputs, contrib)
    selected, masked = selected_view_inputs(inputs, 2, torch.Generator().manual_seed(2))
    got = SelectedViewsRendererGraph(model)(**selected)
    assert max(_errors(got, RendererGraph(model)(**masked))) <= TOL
    # The deviation term matters: without it the same inputs render otherwise.
    with torch.no_grad():
        model.field.deviation_to_maps.weight.zero_()
    assert max(_errors(RendererGraph(model)(**masked), got)) > 1e-3


@pytest.mark.parametrize("V,R,S,k", [(5, 7, 11, 2), (8, 4, 6, 3), (4, 3, 9, 4), (1, 2, 3, 1)])
@torch.no_grad()
def test_selected_views_match_the_masked_renderer(model, V, R, S, k):
    """SelectedViewsRendererGraph on per-point kept views = the torch model fed every view with
    the views not kept masked (points with no view and rays with no sample included)."""
    inputs = random_renderer_inputs(model, V, R, S, torch.Generator().manual_seed(V * 100 + k))
    selected, masked = selected_view_inputs(inputs, k, torch.Generator().manual_seed(k))
    assert selected["mask"].shape[0] <= k and selected["pairs"].shape == selected["mask"].shape
    want = RendererGraph(model)(**masked)
    got = SelectedViewsRendererGraph(model)(**selected)
    assert max(_errors(got, want)) <= TOL


def _session_graph(request, model, graph: str):
    """The file of ``graph`` in conftest's ``torch_export`` when ``model`` is that model (the
    seed-0 random ``tiny``, exported by ``export_model`` with its default ``renderer="fast"``:
    ``FastRendererGraph(model)`` and ``SelectedViewsRendererGraph(model)`` through
    ``export_graph`` at the default opset, as below), else None: the same graph is not traced
    again (torch.onnx.export: 15-60 s a graph)."""
    if model.cfg.explicit_rgb:               # the session's tiny-rgb blends by angle: not this one
        return None
    model_dir, twin = request.getfixturevalue("torch_export")
    mine, theirs = model.state_dict(), twin.state_dict()
    if (model.cfg != twin.cfg or mine.keys() != theirs.keys()
            or not all(torch.equal(mine[k], theirs[k]) for k in mine)):
        return None
    assert json.loads((model_dir / "iris.json").read_text())["export"]["renderer_graph"] == "fast"
    return model_dir / io_spec.spec_for(graph, model.cfg.explicit_rgb)["file"]


def test_selected_views_graph_in_onnx_runtime(model, tmp_path, request):
    """The exported selected-views graph: I/O of io_spec.RENDERER_VIEWS, ONNX Runtime within TOL of
    torch through its dynamic axes (V, M, K, R, S)."""
    path = _session_graph(request, model, "renderer_views")
    if path is None:
        path = tmp_path / "renderer_views.onnx"
        export_graph(model, "renderer_views", path, wrapper=SelectedViewsRendererGraph(model))
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    spec = io_spec.spec_for("renderer_views", model.cfg.explicit_rgb)
    assert [i.name for i in sess.get_inputs()] == list(spec["inputs"])
    g = torch.Generator().manual_seed(5)
    for V, R, S, k in [(5, 7, 11, 2), (3, 2, 64, 3), (1, 1, 1, 1)]:
        selected, masked = selected_view_inputs(random_renderer_inputs(model, V, R, S, g), k, g)
        got = sess.run(None, {n: x.numpy() for n, x in selected.items()})
        with torch.no_grad():
            want = RendererGraph(model)(**masked)
        assert max(_errors(got, want)) <= TOL


@torch.no_grad()
def test_field_semantics_for_points_seen_by_no_view(model):
    """The field's point features equal ``IrisModel.field_from_samples`` for every point, those
    seen by no view included (max-pool of nothing = 0, zero view attention)."""
    inputs = random_renderer_inputs(model, 4, 6, 11, torch.Generator().manual_seed(8))
    V, R, S = inputs["mask"].shape
    want, _ = model.field_from_samples(inputs["field_maps"], inputs["grid"], inputs["cues"],
                                       inputs["mask"], inputs.get("colours"))
    fast = FastRendererGraph(model)
    m = inputs["mask"].float().reshape(V, R * S)
    bias = validity_bias(m)
    slots = fast._sample_slots(inputs["field_maps"], inputs["grid"], inputs["cues"],
                               inputs.get("colours"), bias)
    _, got = fast._field(slots, bias, (m.amax(0) > 0).float(),
                         model.renderer.ray_transformer.blocks[0].norm1, torch.zeros(1))
    unseen = ~(inputs["mask"] > 0).any(0).reshape(-1)
    assert unseen.sum() >= R                                   # sample 0 of every ray at least
    assert (got - want.reshape(R * S, -1)).abs().max() <= TOL


def test_wrapper_arguments(model):
    with pytest.raises(ExportArgumentError, match="sampler"):
        FastRendererGraph(model, sampler="nearest")
    with pytest.raises(ExportArgumentError, match="renderer"):
        renderer_wrapper(model, "fastest")
    assert isinstance(renderer_wrapper(model, "fast"), FastRendererGraph)
    assert renderer_wrapper(model, "fast-contrib").contrib
    assert isinstance(renderer_wrapper(model, "reference"), RendererGraph)
    if model.cfg.explicit_rgb:
        inputs = random_renderer_inputs(model, 2, 3, 4, torch.Generator().manual_seed(0))
        inputs.pop("colours")
        with pytest.raises(ExportArgumentError, match="colours"):
            FastRendererGraph(model)(*inputs.values())


# -- ONNX export + ONNX Runtime -------------------------------------------------------------------
@pytest.fixture(scope="module")
def exported(tmp_path_factory, model, request):
    """{kind: path} of the fast graphs of ``model`` ("fast", "fast-contrib"); the random tiny
    model's "fast" graph is the session export's renderer (``_session_graph``)."""
    out = tmp_path_factory.mktemp("fast_renderer")
    name = "rgb" if model.cfg.explicit_rgb else "paper"
    paths = {}
    for kind, contrib in (("fast", False), ("fast-contrib", True)):
        paths[kind] = (None if contrib else _session_graph(request, model, "renderer")) or \
            export_fast_renderer(model, out / f"{name}-{kind}.onnx", contrib=contrib).path
    return paths


def _session(path):
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL   # as IrisRuntime
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


@pytest.mark.parametrize("kind", ["fast", "fast-contrib"])
def test_onnx_runtime_matches_torch(model, exported, kind):
    sess = _session(exported[kind])
    spec = io_spec.spec_for("renderer", model.cfg.explicit_rgb)
    assert [i.name for i in sess.get_inputs()] == list(spec["inputs"])
    assert [o.name for o in sess.get_outputs()] == list(spec["outputs"])
    for i in sess.get_inputs():
        assert i.type == ("tensor(bool)" if spec["inputs"][i.name]["dtype"] == "bool"
                          else "tensor(float)")
        assert len(i.shape) == len(spec["inputs"][i.name]["shape"])
    ref = RendererGraph(model)
    g = torch.Generator().manual_seed(11)
    for V, R, S in SHAPES + [(2, 33, 64)]:
        inputs = random_renderer_inputs(model, V, R, S, g)
        with torch.no_grad():
            want = ref(*inputs.values())
        got = sess.run(None, {k: v.numpy() for k, v in inputs.items()})
        assert all(np.isfinite(x).all() for x in got)
        errors = _errors(got, want)
        assert max(errors) <= TOL, (V, R, S, errors)
    # Every sample at full weight: the ray attentions take the If's branch without the key
    # bias (``_key_softmax``); the probes above have masked and fading keys.
    for V, R, S in [(1, 1, 1), (3, 9, 64)]:
        feed = {k: v.numpy() for k, v in random_renderer_inputs(model, V, R, S, g).items()}
        feed["mask"][:] = 1.0
        with torch.no_grad():
            want = ref(*(torch.from_numpy(v) for v in feed.values()))
        assert max(_errors(sess.run(None, feed), want)) <= TOL, (V, R, S)
    # The runtime's empty-ray probe (every size 1, everything masked).
    feed = {k: v.numpy() for k, v in random_renderer_inputs(model, 1, 1, 1, g).items()}
    feed["mask"][:] = 0.0
    with torch.no_grad():
        want = ref(*(torch.from_numpy(v) for v in feed.values()))
    assert max(_errors(sess.run(None, feed), want)) <= TOL


def test_onnx_graph_has_no_where_and_no_per_sample_transpose(model, exported):
    """No ``Where``; after ONNX Runtime's optimisations (Transpose + MatMul -> FusedMatMul) the
    only Transposes left are the head merges of the ray attentions, one per ray block (the
    reference graph: 14 / 16)."""
    blocks = model.cfg.ray_blocks
    for kind in ("fast", "fast-contrib"):
        raw, opt = op_histogram(exported[kind]), op_histogram(exported[kind], optimized=True)
        assert raw["Where"] == 0 and opt["Where"] == 0
        assert opt["Transpose"] == blocks, opt
        onnx.checker.check_model(onnx.load_model(str(exported[kind])), full_check=True)
        assert raw["com.microsoft.MultiHeadAttention"] == 0     # it cannot take fractional masks
        assert opt["If"] == blocks                  # the key-bias Add skipped at full weight


def test_onnx_graph_reduces_over_views_with_scan_and_no_trailing_one_broadcasts(model, exported):
    """No ``ReduceMax`` over the leading (view) axis is left (``views_max_as_scan``), and no
    element-wise op broadcasts an operand over a trailing axis of 1 against a wider one (the
    layouts ONNX Runtime runs several times slower, benchmarks/ort_reductions.py), in the graph
    ONNX Runtime runs."""
    from onnx import shape_inference
    for kind in ("fast", "fast-contrib"):
        proto = onnx.load_model(str(exported[kind]))
        leading = [n for n in proto.graph.node if n.op_type == "ReduceMax"
                   and onnx.numpy_helper.to_array(next(t for t in proto.graph.initializer
                                                       if t.name == n.input[1])).tolist() == [0]]
        assert not leading and op_histogram(exported[kind])["Scan"] >= 2
        inferred = shape_inference.infer_shapes(proto)
        shapes = {v.name: [d.dim_value if d.HasField("dim_value") else d.dim_param
                           for d in v.type.tensor_type.shape.dim]
                  for v in [*inferred.graph.value_info, *inferred.graph.input]}
        for n in inferred.graph.node:
            if n.op_type not in ("Add", "Sub", "Mul", "Div") or len(n.input) != 2:
                continue
            a, b = (shapes.get(i) for i in n.input)
            if not a or not b or (a[-1] == 1) == (b[-1] == 1):
                continue
            wide = a if b[-1] == 1 else b
            # per-sample tensors with a channel axis (a dim of the samples, "S" or "S*R", and a
            # fixed last dim); per-ray and per-view-map ones are small.
            per_sample = isinstance(wide[-1], int) and any("S" in str(d) for d in wide[:-1])
            assert not per_sample, (kind, n.name, a, b)


@pytest.mark.parametrize("keepdims", [0, 1])
def test_views_max_as_scan_keeps_values(keepdims):
    """The rewrite on a one-node graph: the same values as ``ReduceMax`` over axis 0 (and numpy)
    for 1 to 7 views; a ``ReduceMax`` over another axis is left alone."""
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    from export.fast_renderer import views_max_as_scan
    graph = helper.make_graph(
        [helper.make_node("ReduceMax", ["x", "axis0"], ["y"], keepdims=keepdims),
         helper.make_node("ReduceMax", ["x", "axis1"], ["z"], keepdims=keepdims)], "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["V", "N", 4])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, "N", 4][1 - keepdims:]),
         helper.make_tensor_value_info("z", TensorProto.FLOAT, ["V", 1, 4] if keepdims
                                       else ["V", 4])],
        initializer=[numpy_helper.from_array(np.array([0], np.int64), "axis0"),
                     numpy_helper.from_array(np.array([1], np.int64), "axis1")])
    proto = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 20)])
    proto.ir_version = 9
    assert views_max_as_scan(proto) == 1
    assert [n.op_type for n in proto.graph.node].count("ReduceMax") == 1
    onnx.checker.check_model(proto)
    sess = ort.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"])
    rng = np.random.default_rng(0)
    for V in range(1, 8):
        x = rng.standard_normal((V, 33, 4)).astype(np.float32)
        y, z = sess.run(None, {"x": x})
        assert np.array_equal(y, x.max(0, keepdims=bool(keepdims)))
        assert np.array_equal(z, x.max(1, keepdims=bool(keepdims)))


# -- export option ---------------------------------------------------------------------------------
def test_toposort_with_subgraphs_orders_an_if_after_what_its_branches_read():
    """``export.graphs.toposort_with_subgraphs``: an ``If`` whose branch reads a main-graph tensor
    produced after it (what ONNX Runtime's quantiser leaves, export.graphs.quantize_int8) is moved
    after the producer; the graph then passes the checker and runs; independent nodes keep their
    order."""
    from onnx import TensorProto, helper

    from export.graphs import toposort_with_subgraphs
    t = TensorProto.FLOAT
    branch = lambda name, op: helper.make_graph(                                # noqa: E731
        [helper.make_node(op, ["late"], [f"{name}_out"])], name, [],
        [helper.make_tensor_value_info(f"{name}_out", t, [3])])
    nodes = [helper.make_node("ReduceMin", ["x"], ["m"], keepdims=0, name="min"),
             helper.make_node("Greater", ["m", "zero"], ["c"], name="cond"),
             helper.make_node("If", ["c"], ["y"], name="if", then_branch=branch("t", "Relu"),
                              else_branch=branch("e", "Neg")),
             helper.make_node("Abs", ["x"], ["late"], name="late"),
             helper.make_node("Exp", ["x"], ["z"], name="other")]
    graph = helper.make_graph(nodes, "g", [helper.make_tensor_value_info("x", t, [3])],
                              [helper.make_tensor_value_info("y", t, [3]),
                               helper.make_tensor_value_info("z", t, [3])],
                              initializer=[onnx.numpy_helper.from_array(
                                  np.array(0, np.float32), "zero")])
    proto = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 20)])
    proto.ir_version = 9
    with pytest.raises(onnx.checker.ValidationError):
        onnx.checker.check_model(proto)
    toposort_with_subgraphs(proto.graph)
    assert [n.name for n in proto.graph.node] == ["min", "cond", "late", "if", "other"]
    onnx.checker.check_model(proto)
    sess = ort.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"])
    x = np.array([1.0, -2.0, 3.0], np.float32)
    np.testing.assert_array_equal(sess.run(None, {"x": x})[0], -np.abs(x))      # min < 0: Neg
    np.testing.assert_array_equal(sess.run(None, {"x": np.abs(x)})[0], np.abs(x))


def test_export_model_refuses_unknown_renderer(tmp_path):
    from export.pipeline import export_model
    with pytest.raises(ExportArgumentError, match="renderer"):
        export_model(random_model("tiny"), tmp_path / "out", renderer="fastest", progress=False)
    assert not (tmp_path / "out").exists()


def test_cli_renderer_option():
    from export.cli import build_parser
    from export.fast_renderer import RENDERER_KINDS
    parser = build_parser()
    choices = next(a.choices for a in parser._actions if a.dest == "renderer")
    assert tuple(choices) == RENDERER_KINDS
    assert parser.parse_args(["c.pt", "out"]).renderer == "fast"
    assert parser.parse_args(["c.pt", "out", "--renderer", "reference"]).renderer == "reference"
    with pytest.raises(SystemExit):
        parser.parse_args(["c.pt", "out", "--renderer", "fastest"])


def test_export_model_with_fast_renderer_runs_in_the_runtime(request, tmp_path):
    """``export_model(..., renderer="fast")``: validated, recorded in the manifest, and
    ``IrisRuntime`` renders it (culling, packed calls, empty rays) like torch. The model is an
    explicit-colour one: the shipped model (its views blended by angle), whose session export
    (conftest ``shipped_export``: ``export_model`` with its default renderer, "fast", checked
    here) is shared rather than a second full export traced; without it, a random ``tiny-rgb``
    exported here."""
    import inspect

    from export.manifest import read_manifest
    from export.pipeline import export_model
    from iris_runtime import IrisRuntime

    from .conftest import SHIPPED
    if SHIPPED.is_file():
        assert inspect.signature(export_model).parameters["renderer"].default == "fast"
        out, model = request.getfixturevalue("shipped_export")
    else:
        model = random_model("tiny-rgb")
        out = export_model(model, tmp_path / "fast", renderer="fast", quick=True, progress=False,
                           threads=1)
    assert model.cfg.explicit_rgb
    m = read_manifest(out)
    assert m["validation"]["renderer"]["passed"]
    assert m["export"]["renderer_graph"] == "fast"
    assert op_histogram(out / "renderer.onnx")["Where"] == 0
    rt = IrisRuntime(out, threads=1)
    H, W = rt.image_size
    images = [np.asarray(x.permute(1, 2, 0).numpy() * 255, dtype=np.uint8)
              for x in scene_images(3, H, W, torch.Generator().manual_seed(2))]
    scene = rt.encode(images, cameras="model")          # the encoder graph's, as torch's encode
    pose = np.eye(4)
    c, s = np.cos(0.6), np.sin(0.6)                        # sideways: part of the view is empty
    pose[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    pose[:3, 3] = [0.25, 0.0, -0.05]
    res = rt.render(scene, pose, height=12, width=16, depth=True)
    x = np.stack(images).astype(np.float32).transpose(0, 3, 1, 2) / np.float32(255.0)
    with torch.no_grad():
        tscene = model.encode(torch.from_numpy(x))
        rgb, depth = model.render(tscene, torch.tensor(pose, dtype=torch.float32)[None], 12, 16)
    assert np.abs(res.image_float - rgb[0].numpy()).max() <= 1e-4
    assert np.abs(res.depth - depth[0].numpy()).max() <= 1e-4
