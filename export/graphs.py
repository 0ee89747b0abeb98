"""Export wrappers: IRIS split into the two graphs of docs/ARCHITECTURE.md, and their ONNX export.

``EncoderGraph`` and ``RendererGraph`` are thin ``nn.Module`` views of a built ``IrisModel``. They
are used only for ONNX export (and as the torch reference of the graphs in validation); the model
itself carries no ONNX special case. Given the same numbers, they compute exactly what
``IrisModel.encode`` / ``IrisModel.render_rays`` compute:

* ``EncoderGraph(images [V, 3, H, W], is_reference bool [V])`` -> ``field_maps [V, C', h, w]``
  (encoder features through ``LatentField.prepare``: the per-scene, per-pixel half of the field),
  ``world_from_cam [V, 4, 4]``, ``focal [2]``. ``is_reference`` says which views are references
  (isolated: they attend to references only) and which are queries (they attend to the references
  and to themselves); the graph builds the cross-view attention mask from it with
  ``iris_train.encoder.cross_view_mask``. All True = ``IrisModel.encode``; references first, then
  queries = ``IrisModel.encode`` of the references plus ``IrisModel.locate`` of the queries. View 0
  must be a reference (the runtime never feeds anything else; the graph does not check it).
* ``RendererGraph(field_maps [V', C', h, w], grid [V', R, S, 2], cues [V', R, S, 4],
  mask [V', R, S], positions [R, S, 3], directions [R, 3])`` -> ``rgb [R, 3]``,
  ``weights [R, S]``: ``IrisModel.render_samples``; an explicit-colour model
  (``ModelConfig.explicit_rgb``) also takes ``colours [V', R, S, 3]`` after ``directions`` (the
  reference RGB sampled by the caller at the samples' projections). Feature sampling happens in
  the graph, with the model's own sampler; projection, grid coordinates, cues and masks come from
  the caller (``iris_runtime.geometry``; ``Scene.project_samples`` is their torch twin).

Names, dtypes, layouts and dynamic axes come from the I/O spec (``iris_runtime.io_spec``).
Measurements behind the choices below: docs/PERFORMANCE.md, "Renderer and encoder graphs".

Sampling. Small feature grids (up to ``iris_train.model.DENSE_SAMPLING_MAX_CELLS`` cells: the
tiny and paper presets) are sampled with a dense bilinear weight matrix built from per-axis tent
functions and one MatMul (``geometry.sample_bilinear_dense``), because ONNX ``GridSample`` was
the largest single cost of the renderer graph; same values as ``grid_sample`` up to rounding.
``RendererGraph(model, sampler="grid_sample")`` keeps the ``GridSample`` graph.

Masking. ``mask`` holds validity weights in [0, 1] (``geometry.validity``). ``layers.masked_softmax``
/ ``masked_max`` add ``layers.validity_bias`` (0 at weight 1, the finite ``MASK_FILL = -1e30`` at 0)
and multiply by ``mask > 0`` afterwards, and the non-final ray blocks use the same additive bias in
``scaled_dot_product_attention``; ONNX ``Softmax`` subtracts the row max, so an all-masked row
becomes a uniform softmax times a zero mask = 0, never NaN. Checked in validation and tests on
points masked in every view and rays with every sample masked.

Exporter. ``torch.onnx.export(dynamo=True)``: both it and the legacy TorchScript exporter give
correct graphs of the same speed in ONNX Runtime, but dynamo is torch's maintained path (the
TorchScript exporter is deprecated), its graphs are smaller and readable, and it names dynamic
axes from the spec directly. Its traps are handled here: the example inputs never use a size of 1
on a dynamic axis (1 would freeze it), the program is taken in memory and saved by ``onnx.save``
(no side ``.data`` file), and ``ir_version`` is lowered to the minimum the opset needs (9 for
opset 20) so that older onnxruntime releases load the files.

Reference isolation. A bool ``is_reference [V]`` input exports as is with dynamo
(``cross_view_mask``'s ``eye``/``|``/``repeat_interleave`` become Range/Equal/Or/Expand/Reshape),
so no float stand-in or second entry point is needed; isolation inside ONNX Runtime is bitwise,
and the mask costs a few ms per scene, so one graph serves both encode and locate.

int8 (dynamic, ``quantize_int8``): recorded in the manifest, not held to the fp32 tolerance, and
no faster at this model size.
"""
from __future__ import annotations

import contextlib
import heapq
import logging
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import onnx
import torch
import torch.nn as nn

from iris_train.config import ModelConfig
from iris_train.model import SAMPLERS as MODEL_SAMPLERS
from iris_train.model import IrisModel, sampler_for

from . import io_spec
from .errors import ExportArgumentError, ExportError
from .fast_weights import SELECTION_PREFIX
from .io_spec import DEFAULT_OPSET, MIN_OPSET

EXPORTER = "torch.onnx.export(dynamo=True)"


class EncoderGraph(nn.Module):
    """Encoder + camera head + per-scene field precompute, for ONNX export only.

    ``images [V, 3, H, W]`` in [0, 1], ``is_reference`` bool ``[V]`` (view 0 must be True) ->
    ``field_maps [V, C', h, w]``, ``world_from_cam [V, 4, 4]`` (view 0 = I), ``focal [2]``
    (fx/W, fy/H): ``IrisModel.encode_batch`` with isolated references, then ``LatentField.prepare``.
    (``encode_batch``'s check that view 0 is a reference is data-dependent control flow, which
    torch.export cannot trace; the wrapper calls ``encode_stages`` instead.)
    """

    def __init__(self, model: IrisModel):
        super().__init__()
        self.model = model

    def forward(self, images: torch.Tensor, is_reference: torch.Tensor):
        features, world_from_cam, focal = self.model.encode_stages(images[None], is_reference)
        return self.model.field.prepare(features[0]), world_from_cam[0], focal[0]


#: Field-map samplers of the renderer graphs: the model's (``iris_train.model.SAMPLERS``), or
#: "auto", the model's own choice for its feature grid (``resolve_sampler``).
SAMPLERS = ("auto", *MODEL_SAMPLERS)


def resolve_sampler(model: IrisModel, sampler: str) -> str:
    """The field-map sampler a renderer graph of ``model`` uses for ``sampler`` (``SAMPLERS``), or
    ``ExportArgumentError``."""
    if sampler not in SAMPLERS:
        raise ExportArgumentError(f"sampler: expected one of {SAMPLERS}, got {sampler!r}")
    return sampler_for(*model.cfg.field_grid) if sampler == "auto" else sampler


class RendererGraph(nn.Module):
    """Feature sampling + latent field + ray renderer for one chunk of rays, for ONNX export only.

    ``IrisModel.render_samples`` with ``need_weights=True``: ``render_rays`` after its projection
    step, on the view-major inputs of ``io_spec.RENDERER`` (``mask``: each sample's validity
    weight in each view). An explicit-colour model (``ModelConfig.explicit_rgb``) also
    takes ``colours [V', R, S, 3]`` (last; the reference RGB at each sample's projection,
    ``io_spec.EXPLICIT_RGB_INPUTS``); other models have no such input.

    ``sampler``: ``"dense"`` (``geometry.sample_bilinear_dense``, a matmul), ``"grid_sample"``
    (ONNX ``GridSample``) or ``"auto"``: the model's own choice (``iris_train.model.sampler_for``).
    """

    def __init__(self, model: IrisModel, sampler: str = "auto"):
        super().__init__()
        self.model = model
        self.sampler = resolve_sampler(model, sampler)

    def forward(self, field_maps: torch.Tensor, grid: torch.Tensor, cues: torch.Tensor,
                mask: torch.Tensor, positions: torch.Tensor, directions: torch.Tensor,
                colours: torch.Tensor | None = None):
        if self.model.cfg.explicit_rgb and colours is None:
            raise ExportArgumentError("colours: this model (explicit_rgb) renders from the "
                                      "reference RGB sampled at the samples, [V', R, S, 3]")
        return self.model.render_samples(field_maps, grid, cues, mask, positions, directions,
                                         colours, need_weights=True, sampler=self.sampler)


class EncoderCamerasGraph(nn.Module):
    """The camera half of ``EncoderGraph``, for ONNX export only (``io_spec.ENCODER_CAMERAS``):
    ``images``, ``is_reference`` -> ``world_from_cam``, ``focal`` through the camera head's own
    encoder alone (``IrisModel.camera_stages``; models with ``cfg.camera_encoder``)."""

    def __init__(self, model: IrisModel):
        super().__init__()
        self.model = model

    def forward(self, images: torch.Tensor, is_reference: torch.Tensor):
        world_from_cam, focal = self.model.camera_stages(images[None], is_reference)
        return world_from_cam[0], focal[0]


WRAPPERS = {"encoder": EncoderGraph, "renderer": RendererGraph,
            "encoder_cameras": EncoderCamerasGraph}


def fixed_dims(cfg: ModelConfig) -> dict[str, int]:
    """Values of the spec's model-fixed axis names (everything but the dynamic V, R, S)."""
    h, w = cfg.field_grid
    return {"H": cfg.image_height, "W": cfg.image_width, "h": h, "w": w, "C'": cfg.field_channels}


def example_inputs(cfg: ModelConfig, graph: str, generator: torch.Generator | None = None):
    """Export-time example inputs of ``graph`` in spec order.

    No dynamic axis has size 1 (torch.export would specialise it) and V, R, S differ from each
    other and from the static sizes, so that no two axes are unified by accident.
    """
    g = generator if generator is not None else torch.Generator().manual_seed(0)
    V, R, S = 3, 6, 5
    H, W, h, w, C = (fixed_dims(cfg)[k] for k in ("H", "W", "h", "w", "C'"))
    if graph in ("encoder", "encoder_cameras"):   # two references and a query: both kinds of rows
        return (torch.rand(V, 3, H, W, generator=g), torch.arange(V) < V - 1)
    if graph == "renderer_views":        # P = 9 groups of G = 11 pairs, K = 7 slots per point
        P, Gp, K = 9, 11, 7
        args = (torch.randn(V, C, h, w, generator=g), torch.randint(0, V, (P,), generator=g),
                torch.rand(P, Gp, 2, generator=g) * 2 - 1, torch.randn(P, Gp, 4, generator=g),
                torch.randint(0, P * Gp, (K, R, S), generator=g),
                _example_weights((K, R, S), g), torch.randn(R, S, 3, generator=g),
                torch.randn(R, 3, generator=g))
        return args + ((torch.rand(P, Gp, 3, generator=g),) if cfg.explicit_rgb else ())
    mask = _example_weights((V, R, S), g)
    args = (torch.randn(V, C, h, w, generator=g), torch.rand(V, R, S, 2, generator=g) * 2 - 1,
            torch.randn(V, R, S, 4, generator=g), mask, torch.randn(R, S, 3, generator=g),
            torch.randn(R, 3, generator=g))
    if cfg.explicit_rgb:
        args += (torch.rand(V, R, S, 3, generator=g),)
    return args


def _example_weights(shape, g: torch.Generator) -> torch.Tensor:
    """Validity weights: 0 (30 %), fractional, and 1 (the rest)."""
    w = torch.rand(shape, generator=g)
    return torch.where(w < 0.3, 0.0, torch.where(w < 0.5, (w - 0.3) * 5.0, 1.0))


@dataclass
class GraphFile:
    """What the export of one graph produced."""
    name: str
    path: Path
    nodes: int
    seconds: float


@contextlib.contextmanager
def _quiet_exporter():
    """The dynamo exporter logs progress and warns about renamed axes; keep the CLI readable."""
    loggers = [logging.getLogger(n) for n in ("torch.onnx", "torch.export", "torch._dynamo",
                                               "torch.fx.experimental.symbolic_shapes")]
    levels = [lg.level for lg in loggers]
    try:
        for lg in loggers:
            lg.setLevel(logging.ERROR)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


def check_opset(opset: int) -> int:
    if not isinstance(opset, int) or isinstance(opset, bool):
        raise ExportArgumentError(f"opset: expected an integer, got {opset!r}")
    newest = onnx.defs.onnx_opset_version()
    if not MIN_OPSET <= opset <= newest:
        raise ExportArgumentError(f"opset: expected {MIN_OPSET} <= opset <= {newest} (installed onnx "
                                  f"{onnx.__version__}), got {opset}")
    return opset


def set_min_ir_version(proto: onnx.ModelProto) -> onnx.ModelProto:
    """Lower ``ir_version`` to the minimum the model's opsets need (onnx writes its newest IR,
    which an older onnxruntime refuses to load)."""
    needed = onnx.helper.find_min_ir_version_for(list(proto.opset_import), ignore_unknown=True)
    proto.ir_version = min(proto.ir_version, needed)
    return proto


def _name_axes(proto: onnx.ModelProto, spec: dict, dims: dict[str, int]) -> None:
    """Give every dynamic axis the spec's name and check every fixed axis against the spec."""
    for value, entry in [(v, spec["inputs"].get(v.name) or spec["outputs"].get(v.name))
                         for v in list(proto.graph.input) + list(proto.graph.output)]:
        if entry is None:
            raise ExportError(f"exported graph has an input/output {value.name!r} the I/O spec lacks")
        shape = value.type.tensor_type.shape.dim
        if len(shape) != len(entry["shape"]):
            raise ExportError(f"{value.name}: exported rank {len(shape)}, spec {entry['shape']}")
        got = [d.dim_param or d.dim_value for d in shape]
        for dim, want in zip(shape, entry["shape"]):
            want = dims.get(want, want)
            if isinstance(want, int) and dim.dim_value != want:
                raise ExportError(f"{value.name}: exported shape {got}, spec {entry['shape']}")
            if isinstance(want, str):
                if dim.HasField("dim_value"):      # torch.export specialised a dynamic axis
                    raise ExportError(f"{value.name}: axis {want!r} was frozen to {dim.dim_value} "
                                      f"by the export (exported shape {got})")
                dim.dim_param = want


def _check_self_contained(proto: onnx.ModelProto, name: str) -> None:
    for tensor in proto.graph.initializer:
        if tensor.data_location == onnx.TensorProto.EXTERNAL:
            raise ExportError(f"{name}: initializer {tensor.name!r} refers to external data")


def export_graph(model: IrisModel, graph: str, path: str | Path, opset: int = DEFAULT_OPSET,
                 wrapper: nn.Module | None = None) -> GraphFile:
    """Export ``graph`` ("encoder", "renderer", "renderer_views" or "encoder_cameras") of ``model``
    to one self-contained file ``path``.

    ``wrapper``: the module to export instead of ``WRAPPERS[graph](model)``, with the same I/O
    (e.g. ``export.fast_renderer.FastRendererGraph``); its ``custom_translation_table``
    attribute, if any, goes to ``torch.onnx.export``; its ``rewrite_onnx(proto)``, if any, is
    applied to the exported graph."""
    spec = io_spec.spec_for(graph, model.cfg.explicit_rgb)
    check_opset(opset)
    wrapper = (WRAPPERS[graph](model) if wrapper is None else wrapper).eval()
    extra = {}
    if getattr(wrapper, "custom_translation_table", None):
        extra["custom_translation_table"] = wrapper.custom_translation_table
    args = example_inputs(model.cfg, graph)
    names = list(spec["inputs"])
    axes = {}
    for axis_names in spec["dynamic_axes"].values():
        for a in axis_names.values():
            axes.setdefault(a, torch.export.Dim(a, min=1))
    dynamic_shapes = {n: {i: axes[a] for i, a in spec["dynamic_axes"].get(n, {}).items()}
                      for n in names}
    start = time.perf_counter()
    with _quiet_exporter(), torch.no_grad():
        program = torch.onnx.export(
            wrapper, args, dynamo=True, opset_version=opset, verbose=False,
            input_names=names, output_names=list(spec["outputs"]),
            dynamic_shapes=dynamic_shapes, optimize=True, **extra)
    proto = program.model_proto
    if getattr(wrapper, "rewrite_onnx", None) is not None:
        wrapper.rewrite_onnx(proto)
    _name_axes(proto, spec, fixed_dims(model.cfg))
    set_min_ir_version(proto)
    _check_self_contained(proto, graph)
    path = Path(path)
    onnx.save_model(proto, str(path), save_as_external_data=False)
    return GraphFile(graph, path, len(proto.graph.node), time.perf_counter() - start)


def quantize_int8(src: str | Path, dst: str | Path) -> GraphFile:
    """Dynamic int8 quantisation (``onnxruntime.quantization.quantize_dynamic``, int8 weights,
    activations quantised at run time) of the graph at ``src``, written self-contained to ``dst``.

    The dynamo exporter's ``value_info`` is cleared first: the quantiser's own shape inference
    trips over the exporter's symbolic shapes otherwise.
    """
    from onnxruntime.quantization import QuantType, quantize_dynamic

    start = time.perf_counter()
    proto = onnx.load_model(str(src))
    del proto.graph.value_info[:]
    quant_logger = logging.getLogger()          # the quantiser logs pre-processing advice at root
    level = quant_logger.level
    try:
        quant_logger.setLevel(logging.ERROR)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            # DefaultTensorType: onnx's shape inference gives no type past ONNX Runtime's
            # contrib ops (export.fast_renderer's "fast-contrib" graph); float32 is every
            # tensor's type here. Graphs whose types are all inferred are unaffected.
            # reduce_range: 7-bit weights. Without AVX-512 VNNI, ORT's u8 x s8 kernels sum
            # pairs of products in int16 and saturate with 8-bit weights (tests/test_export.py
            # bounds the int8 error; the figures: docs/PERFORMANCE.md, "int8").
            # The fast graphs' 0/1 selection matmuls stay float: they carry the bilinear and
            # attention weights, which 8 bits would round.
            exclude = [n.name for n in proto.graph.node
                       if any(i.startswith(SELECTION_PREFIX) for i in n.input)]
            quantize_dynamic(proto, str(dst), weight_type=QuantType.QInt8, reduce_range=True,
                             nodes_to_exclude=exclude,
                             extra_options={"DefaultTensorType": onnx.TensorProto.FLOAT})
    finally:
        quant_logger.setLevel(level)
    proto = set_min_ir_version(onnx.load_model(str(dst)))
    # The quantiser sorts nodes by their explicit inputs only; an If whose branches read a
    # tensor of the main graph (export.fast_renderer._key_softmax) can end up before it.
    toposort_with_subgraphs(proto.graph)
    _check_self_contained(proto, Path(dst).name)
    onnx.save_model(proto, str(dst), save_as_external_data=False)
    return GraphFile(Path(dst).stem, Path(dst), len(proto.graph.node), time.perf_counter() - start)


def _outer_inputs(node) -> set[str]:
    """Every tensor ``node`` reads: its inputs and the outer-scope names its subgraphs use."""
    names = {i for i in node.input if i}
    for attr in node.attribute:
        for g in ([attr.g] if attr.HasField("g") else []) + list(attr.graphs):
            local = {i.name for i in g.input} | {t.name for t in g.initializer}
            local |= {o for n in g.node for o in n.output}
            names |= {i for n in g.node for i in _outer_inputs(n)} - local
    return names


def toposort_with_subgraphs(graph) -> None:
    """Sort ``graph.node`` (in place) so that every node, subgraph reads included, comes after
    the nodes it reads from; ties keep the current order. Raises ``ValueError`` on a cycle."""
    nodes = list(graph.node)
    producer = {o: k for k, n in enumerate(nodes) for o in n.output if o}
    deps = [{producer[i] for i in _outer_inputs(n) if i in producer} for n in nodes]
    users: list[list[int]] = [[] for _ in nodes]
    for k, d in enumerate(deps):
        for j in d:
            users[j].append(k)
    pending = [len(d) for d in deps]
    ready = [k for k, p in enumerate(pending) if p == 0]
    heapq.heapify(ready)
    order = []
    while ready:
        k = heapq.heappop(ready)
        order.append(k)
        for u in users[k]:
            pending[u] -= 1
            if pending[u] == 0:
                heapq.heappush(ready, u)
    if len(order) != len(nodes):
        raise ValueError("graph has a cycle")
    del graph.node[:]
    graph.node.extend(nodes[k] for k in order)


__all__ = ["EncoderGraph", "EncoderCamerasGraph", "RendererGraph", "WRAPPERS", "DEFAULT_OPSET",
           "MIN_OPSET", "EXPORTER", "fixed_dims", "example_inputs", "export_graph",
           "quantize_int8", "check_opset", "set_min_ir_version", "toposort_with_subgraphs",
           "GraphFile", "SAMPLERS", "resolve_sampler"]
