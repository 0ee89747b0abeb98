"""An alternative renderer export graph laid out for ONNX Runtime's CPU kernels.

``FastRendererGraph(model)`` computes the same function as ``RendererGraph(model)``
(``IrisModel.render_samples`` with ``need_weights=True``), with the same inputs and outputs
(``iris_runtime.io_spec.RENDERER``, plus ``colours`` for explicit-colour models), so the runtime
runs either graph unchanged. It is built from the model's own modules (norms, MLPs, projections,
heads, ``layers.sinusoidal_encoding``) and parameters; the weights it needs in another form are
derived from them at construction (see the class). tests/test_fast_renderer.py holds it to torch
within 1e-5 on rgb and weights for both renderer kinds, in torch and in ONNX Runtime.

``SelectedViewsRendererGraph(model)`` is the same renderer on per-point pre-selected views
(``iris_runtime.io_spec.RENDERER_VIEWS``: the kept (view, point) pairs in groups of one view,
and K view slots per point), which the runtime uses for per-point top-k.

What differs from the reference graph, and why: each change replaces a layout that ONNX Runtime's
CPU kernels run slowly by one they run fast, with the same values. What each was worth, and the
commands that measure it: docs/PERFORMANCE.md, "The fast renderer graph".

* Masks are additive biases, no ``Where``: the validity weights become
  ``layers.validity_bias_where_free`` once per call, the masked max-pool over views is
  ``ReduceMax(u + bias) * any_view`` and the masked softmaxes are ``Softmax(logits + bias)``. For
  every row with a valid entry this is exactly the masked fill (``x + MASK_FILL`` rounds to
  ``MASK_FILL``, whose ``exp`` is exactly 0). Rows with no valid entry keep the reference's
  meaning: a point seen by no view gets ``q0 = 0`` and zero view-attention weights (the
  attention's normaliser is multiplied by ``any_view``, as in ``layers.masked_max`` /
  ``masked_softmax``); a ray with no valid sample gets uniform, finite ray-attention rows, but its
  samples are all pooled away (weight 0 in the mean pool and in the depth weights), so rgb =
  head(0) and weights = 0 as in the reference.
* View-major throughout the latent field, so no Transpose: the field runs on ``[V', R*S, .]``,
  every reduction over views is over the leading axis and leaves the point-major ``[R*S, W]``
  the ray transformer needs. The softmax over views is written out (ReduceMax, Sub, Exp, sum),
  because ONNX ``Softmax`` on a non-last axis transposes internally.
* One sampling matmul per field-map slot (u, and every view block's keys and values):
  ``A @ B_slot`` with the design matrix ``A = [tent | cues | colours | bias]`` and ``B_slot =
  [maps_slot ; cue_to_kv_slot ; rgb_to_maps_slot ; 1 for u, 0 for k and v]``, so the cue's and
  the colour's maps, the max-pool's bias and their Adds disappear into the matmul's K dimension.
  ``A`` is ``([wy | extras] @ select_rows) * (wx @ select_cols)``: 0/1 matmuls copy the per-axis
  tent weights to their cells (the outer product, bit for bit) instead of a broadcast outer
  product and a wide Concat.
* Reductions over views as matmuls: sums are ``ones [1, V] @ x [V, -1]`` (``_sum_views``), the
  view attention's per-head sums and broadcasts 0/1 matmuls (``select_head_sum``,
  ``select_head_expand``); the maxima, which have no matmul form, are a ``Scan`` of element-wise
  ``Max`` (``views_max_as_scan``, applied by ``rewrite_onnx``).
* No broadcast over a trailing axis of 1 on per-sample tensors: masks and normalisers are widened
  by ``x @ ones [1, n]`` (``_expand``, exact copies), the tent's ``g - centres`` is a Gemm
  (``_tent_axes``) and the position encoding's ``x_c 2^k pi`` a matmul with one nonzero per
  column (the same products).
* Ray attention on per-head q/k/v weights: ``y [R, 1, S, W] @ Wq [H, W, Dh]`` gives
  ``[R, H, S, Dh]`` directly (no Gemm + Reshape + Transpose + Split). The attention scale is in
  the query weights (exact for the presets' power-of-two scales), the query bias is a row of them
  times an appended column of ones, the key bias is dropped (it adds ``q . b_k`` to a whole row:
  softmax-invariant) and the value bias is folded into the output projection's bias (attention
  rows sum to one). The key mask stays an Add over ``[R, H, S, S]`` (a 17th q . k component
  carrying it would make the projections 17 wide) and is skipped when every key has full weight
  (``_key_softmax``, an ONNX ``If``; the runtime gives such rays calls of their own,
  ``iris_runtime.raymarch.plan_calls``). One Transpose per ray block remains, merging the heads
  (the transpose-free forms cost H x the memory or the attention FLOPs).
* Per-ray work out of the per-sample path (each block's injection ``psi(enc)`` split into a
  per-sample position part and a per-ray direction part); the mean pool and the paper renderer's
  depth weights as matmuls; the residual streams 2-D ``[R*S, W]`` so that every linear layer
  exports as a Gemm with its bias fused.

``contrib=True`` (``export.ort_contrib``): every residual Add + LayerNormalization becomes
``SkipLayerNormalization`` (the pending bias of the preceding linear layer as its bias) and every
MLP's first layer MatMul + ``BiasGelu``; ONNX Runtime's own optimiser fuses neither in this
layout. The ray attentions stay explicit: ``MultiHeadAttention``'s ``key_padding_mask`` cannot
carry fractional validity weights.

``renderer_wrapper(model, kind)`` builds the wrapper of each of ``RENDERER_KINDS``;
``export_model(..., renderer=...)`` / ``iris-export --renderer`` ship it, validated against the
torch reference ``RendererGraph`` like the reference graph and recorded as
``export.renderer_graph`` in the manifest. "fast" is the default: the fastest per frame of the
three (docs/PERFORMANCE.md).
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from iris_train.layers import sinusoidal_encoding, validity_bias_where_free
from iris_train.model import SAMPLERS as MODEL_SAMPLERS
from iris_train.model import IrisModel, blend_views
from iris_train.ray_renderer import BLEND_EPS

from .errors import ExportArgumentError
from .fast_weights import SELECTION_PREFIX, derive_weights
from .graphs import RendererGraph, resolve_sampler

#: Renderer graph kinds of ``export_model(..., renderer=...)``: "reference" is ``RendererGraph``
#: (the model's render_samples traced as is), "fast" (the default) this module's graph
#: in standard ONNX ops, "fast-contrib" the same with ONNX Runtime's com.microsoft fused ops.
RENDERER_KINDS = ("reference", "fast", "fast-contrib")


class FastRendererGraph(nn.Module):
    """The renderer graph of ``RendererGraph(model, sampler)``, rewritten for ONNX Runtime's CPU
    kernels (module docstring). Same inputs, outputs and values; export only (and its torch twin
    in tests).

    The model's modules (norms, MLPs, projections, heads) are used as they are; the weights this
    layout needs in another form (u/k/v slot rows, per-head q/k/v, folded scales and biases, the
    split injection) are derived from the model's parameters at construction
    (``export.fast_weights``) and kept as non-persistent buffers, so that they are initializers
    of the exported graph rather than ops on weights (the exporter folds no constant above a
    small size). Build the wrapper from the model as it is to be exported
    (``export_fast_renderer`` does).
    """

    def rewrite_onnx(self, proto) -> None:
        """Called by ``export.graphs.export_graph`` on the exported ONNX graph (in place)."""
        views_max_as_scan(proto)

    def __init__(self, model: IrisModel, sampler: str = "auto", contrib: bool = False):
        super().__init__()
        self.model = model
        self.sampler = resolve_sampler(model, sampler)
        self.contrib = bool(contrib)
        if self.contrib:
            from . import ort_contrib
            self._ops = ort_contrib
            #: Read by ``export.graphs.export_graph`` (the contrib ops' ONNX translations).
            self.custom_translation_table = ort_contrib.translation_table()
        with torch.no_grad():
            self._derive()

    # -- derived weights ---------------------------------------------------------------------
    def _keep(self, name: str, tensor: torch.Tensor) -> None:
        self.register_buffer(name, tensor.detach().clone().contiguous(), persistent=False)

    def _derive(self) -> None:
        """Register ``export.fast_weights.derive_weights``' tensors as buffers and keep its
        slots (the channels of u and of each view block's keys and values)."""
        self.slots, weights = derive_weights(self.model)
        for name, tensor in weights.items():
            self._keep(name, tensor)

    # -- the latent field, view-major --------------------------------------------------------
    def _sample_slots(self, field_maps, grid, cues, colours, bias, groups=None):
        """Every slot's ``[V, N, W]``: sampled maps + cue term (+ colour term); the first slot
        (u) also + the mask ``bias``. ``groups [P]``: the per-view inputs are P groups of
        points, group p on view ``groups[p]`` (the per-view matrices are built once per view and
        then indexed), and the slots ``[P, N, W]``."""
        C, h, w = field_maps.shape[1:]
        V, N = grid.shape[0], grid.shape[1] * grid.shape[2]
        extras = [cues.reshape(V, N, 4)]
        if colours is not None:
            extras.append(colours.reshape(V, N, 3))
        extras.append(bias[..., None])
        consts = [getattr(self, f"slot{i}_const", None) for i in range(len(self.slots))]
        rows = [getattr(self, f"slot{i}_rows") for i in range(len(self.slots))]
        out = []
        if self.sampler == "dense":
            wy, wx = self._tent_axes(grid.reshape(V * N, 2))                          # [VN, h|w]
            A = ((torch.cat([wy.reshape(V, N, h), *extras], dim=-1) @ self.select_rows)
                 * (wx.reshape(V, N, w) @ self.select_cols))                          # [V, N, hw+E]
            maps = field_maps.reshape(-1, C, h * w)
            for ch, r, const in zip(self.slots, rows, consts):
                m = maps[:, ch]                                                       # [V, W, hw]
                if const is not None:
                    m = m + const[:, None]
                Bt = torch.cat([m, r.expand(m.shape[0], -1, -1)], dim=-1)             # [V, W, K]
                out.append(A @ (Bt if groups is None else Bt[groups]).transpose(1, 2))
            return out
        # Large feature grids: ONNX GridSample (the model's sampler), then the extras' matmul.
        maps = field_maps if groups is None else field_maps[groups]
        sampled = MODEL_SAMPLERS[self.sampler](maps, grid).reshape(V, N, C)
        X = torch.cat(extras, dim=-1)
        for ch, r, const in zip(self.slots, rows, consts):
            s = sampled[..., ch] + X @ r.t()
            out.append(s if const is None else s + const)
        return out

    def _tent_axes(self, grid):
        """``tent_axes(grid [N, 2])``: ``(wy [N, h], wx [N, w])``, bit for bit."""
        def axis(g, n: int, name: str):
            pix = (((g + 1.0) * n - 1.0) / 2.0).clamp(0.0, n - 1.0)[:, None]          # [N, 1]
            d = F.linear(pix, getattr(self, f"select_tent_{name}"),
                         getattr(self, f"tent_{name}_centres"))                       # Gemm
            return (1.0 - d.abs()).clamp_min(0.0)

        h, w = self.model.cfg.field_grid
        return axis(grid[:, 1], h, "y"), axis(grid[:, 0], w, "x")

    @staticmethod
    def _expand(x, ones):
        """``x [..., 1]`` broadcast to ``[..., n]`` as ``x @ ones [1, n]`` (a copy, exact)."""
        return x @ ones

    # -- residual stream helpers (plain ops, or the contrib ops with ``contrib``) ----------------
    def _linear(self, x, linear: nn.Linear, weight=None, bias=None):
        """``linear(x)`` as ``(x W^T, b)`` with ``contrib`` (the bias goes into the next
        SkipLayerNormalization), else ``(linear(x), None)``."""
        weight = linear.weight if weight is None else weight
        bias = linear.bias if bias is None else bias
        if self.contrib:
            return F.linear(x, weight), bias
        return F.linear(x, weight, bias), None

    def _mlp(self, mlp: nn.Sequential, x):
        """``mlp(x)`` (Linear, GELU, Linear) as ``(delta, bias)`` like ``_linear``."""
        first, _, second = mlp
        if self.contrib:
            return self._linear(self._ops.bias_gelu(F.linear(x, first.weight), first.bias), second)
        return mlp(x), None

    def _add_norm(self, x, delta, bias, norm: nn.LayerNorm):
        """Residual update and the next LayerNorm: ``s = x + delta (+ bias)`` ->
        ``(norm(s), s)``."""
        if self.contrib:
            return self._ops.skip_layer_norm(x, delta, norm.weight, norm.bias, bias, norm.eps)
        s = x + delta if bias is None else x + delta + bias
        return norm(s), s

    # -- the view transformer ----------------------------------------------------------------
    def _field(self, slots, bias, any_view, next_norm: nn.LayerNorm, next_delta):
        """View transformer on view-major slots -> ``(next_norm(f + next_delta), f + next_delta)``
        with the point features ``f [N, W]`` (point-major)."""
        cfg = self.model.cfg
        blocks = self.model.field.view_transformer.blocks
        # Masked max-pool over views (the bias is in slots[0]); 0 for a point seen by no view
        # (layers.masked_max).
        W = cfg.field_width
        ones_w = getattr(self, f"select_ones{W}")
        ones_h = getattr(self, f"select_ones{cfg.field_heads}")
        q = slots[0].amax(0) * self._expand(any_view[:, None], ones_w)                  # [N, W]
        normed = blocks[0].norm_q(q)
        bias_h = self._expand(bias[..., None], ones_h)                                 # [V, N, H]
        any_view_h = self._expand(any_view[:, None], ones_h)                           # [N, H]
        for i, block in enumerate(blocks):
            k, v = slots[1 + 2 * i], slots[2 + 2 * i]
            qh = F.linear(normed, getattr(self, f"view{i}_wq"), getattr(self, f"view{i}_bq"))
            logits = (k * qh) @ self.select_head_sum + bias_h                          # [V, N, H]
            e = torch.exp(logits - logits.amax(0, keepdim=True))
            # Normaliser times any_view: all-zero weights for a point seen by no view.
            weights = e * (any_view_h / _sum_views(e))                                 # [V, N, H]
            out = _sum_views((weights @ self.select_head_expand) * v)                  # [N, W]
            normed, q = self._add_norm(q, *self._linear(out, block.proj), block.norm_mlp)
            delta, b = self._mlp(block.mlp, normed)
            if i + 1 < len(blocks):
                normed, q = self._add_norm(q, delta, b, blocks[i + 1].norm_q)
        return self._add_norm(q, delta + next_delta, b, next_norm)

    # -- the ray transformer ------------------------------------------------------------------
    def _ray_attention(self, i: int, normed, R: int, S: int, ones, key_bias, no_key_bias,
                       keep_attn: bool):
        """Masked self-attention of ray block ``i`` on ``normed [R*S, W]`` -> its output
        ``[R*S, W]`` before the output projection, the attention ``[R, H, S, S]`` if
        ``keep_attn`` (else None) and the output projection's bias to use with it.
        ``ones [R*S, 1]``, ``key_bias [R, 1, 1, S]`` (the validity bias of the sample
        weights), ``no_key_bias`` (a bool scalar: ``key_bias`` is all 0, see ``_key_softmax``)."""
        W = normed.shape[-1]
        y = normed.reshape(R, 1, S, W)                                              # [R, 1, S, W]
        y1 = torch.cat([normed, ones], -1).reshape(R, 1, S, W + 1)
        q = y1 @ getattr(self, f"ray{i}_wq")                                       # [R, H, S, Dh]
        k = y @ getattr(self, f"ray{i}_wk")
        v = y @ getattr(self, f"ray{i}_wv")
        attn = _key_softmax(q @ k.transpose(-1, -2), key_bias, no_key_bias)        # [R, H, S, S]
        out = (attn @ v).transpose(1, 2).reshape(R * S, W)           # heads merged: one Transpose
        # The value bias is in the output projection's bias (the rows of attn sum to one).
        return out, (attn if keep_attn else None), getattr(self, f"ray{i}_bproj")

    def forward(self, field_maps: torch.Tensor, grid: torch.Tensor, cues: torch.Tensor,
                mask: torch.Tensor, positions: torch.Tensor, directions: torch.Tensor,
                colours: torch.Tensor | None = None):
        colours = self._check_colours(colours)
        return self._render(lambda bias: self._sample_slots(field_maps, grid, cues, colours, bias),
                            field_maps.dtype, mask, positions, directions, colours,
                            cues[..., 3] if colours is not None else None)

    def _check_colours(self, colours):
        if self.model.cfg.explicit_rgb and colours is None:
            raise ExportArgumentError("colours: this model (explicit_rgb) renders from the "
                                      "reference RGB sampled at the samples, [V', R, S, 3]")
        return colours if self.model.cfg.explicit_rgb else None

    def _render(self, sample_slots, dtype, mask, positions, directions, colours, cos=None):
        """Field and ray transformer on the view slots ``sample_slots(bias)`` (view-major, the
        first slot with the mask ``bias`` added) of the points of ``mask [V, R, S]``; explicit
        colour: ``colours [V, R, S, 3]`` and the cue's cosine ``cos [V, R, S]`` of each slot."""
        cfg = self.model.cfg
        V, R, S = mask.shape
        N = R * S
        W = cfg.field_width
        m = mask.to(dtype).reshape(V, N)                                     # [V, N] weights
        bias = validity_bias_where_free(m)                                   # 0 / -1e30 at 1 / 0
        s = m.amax(0)                                                        # [N] sample weights
        any_view = (s > 0).to(dtype)                                         # [N] 0 / 1

        renderer = self.model.renderer
        rt = renderer.ray_transformer
        sample_mask = s.reshape(R, S)
        key_bias = validity_bias_where_free(sample_mask)                               # [R, S]
        no_key_bias = key_bias.min() == 0.0                 # every sample at full weight
        ones = torch.ones_like(key_bias).reshape(N, 1)
        unit_dir = directions / directions.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        p = positions.reshape(N, 3)
        pf = p @ self.select_pos_freqs                                                 # [N, 3F]
        e_pos = torch.cat([p, torch.sin(pf), torch.cos(pf)], dim=-1)                   # [N, P]
        e_dir = sinusoidal_encoding(unit_dir, rt.dir_freqs)                            # [R, D]

        def injection(i):          # psi^(i)(enc) [N, W]: per-sample position + per-ray direction
            pos = F.linear(e_pos, getattr(self, f"inject{i}_wpos")).reshape(R, S, W)
            per_ray = F.linear(e_dir, getattr(self, f"inject{i}_wdir"), rt.inject[i].bias)
            return (pos + per_ray[:, None]).reshape(N, W)

        slots = sample_slots(bias)
        if cfg.colour_deviation:         # the views' disagreement, one more additive term a slot
            dev = _colour_deviation(colours.reshape(V, N, 3), m)                      # [V, N, 6]
            slots = [x + dev @ getattr(self, f"slot{i}_deviation").t()
                     for i, x in enumerate(slots)]
        # The field's last residual update, the first injection and the first ray norm in one.
        normed, x = self._field(slots, bias, any_view, rt.blocks[0].norm1, injection(0))
        attn = None
        last = len(rt.blocks) - 1
        for i, block in enumerate(rt.blocks):
            out, attn, bproj = self._ray_attention(i, normed, R, S, ones, key_bias[:, None, None],
                                                   no_key_bias,
                                                   keep_attn=i == last and not cfg.explicit_rgb)
            normed, x = self._add_norm(x, *self._linear(out, block.proj, bias=bproj), block.norm2)
            delta, b = self._mlp(block.mlp, normed)
            if i < last:
                normed, x = self._add_norm(x, delta + injection(i + 1), b, rt.blocks[i + 1].norm1)
        normed, _ = self._add_norm(x, delta, b, renderer.norm)                         # [N, W]

        n_valid = sample_mask.sum(-1, keepdim=True)                                    # [R, 1]
        pool = sample_mask / n_valid.clamp_min(1.0)                                    # [R, S]
        h = (pool[:, None, :] @ normed.reshape(R, S, W))[:, 0]                         # [R, W]
        if cfg.explicit_rgb:
            logits = renderer.sample_logit(normed).reshape(R, S) + key_bias             # [R, S]
            # Times the ray's largest sample weight (rows of no valid sample: uniform times 0).
            w = torch.softmax(logits, dim=-1) * sample_mask.amax(-1, keepdim=True)
            if cfg.blend_angle:         # the views weighted by angle (one formula: blend_views)
                mean_colour = blend_views(colours, m.reshape(V, R, S), cos, cfg.blend_angle)
            else:
                mv = self._expand(m.reshape(V, R, S, 1), self.select_ones3)          # [V, R, S, 3]
                mean_colour = _sum_views(colours * mv) / _sum_views(mv).clamp_min(1.0)  # [R, S, 3]
            blend = (w[:, None, :] @ mean_colour)[:, 0].clamp(BLEND_EPS, 1 - BLEND_EPS)
            rgb = torch.sigmoid(torch.log(blend) - torch.log1p(-blend) + renderer.rgb_head(h))
            return rgb, w
        rgb = torch.sigmoid(renderer.rgb_head(h))
        H = rt.blocks[last].heads
        weights = ((pool / H)[:, None, None, :] @ attn).sum(1)[:, 0]                   # [R, S]
        return rgb, weights


class SelectedViewsRendererGraph(FastRendererGraph):
    """The renderer on per-point pre-selected views (``iris_runtime.io_spec.RENDERER_VIEWS``).

    The inputs are the (view, point) pairs the caller keeps, in groups of G pairs of one view
    each (``groups [P]`` names the view of each group; pair g of group p has its ``grid``,
    ``cues`` and ``colours`` at ``[p, g]``); each point has K view slots, slot k of point (r, s)
    holding pair ``pairs[k, r, s]`` (a flat index p * G + g) where ``mask[k, r, s]``. The maps
    are sampled at the kept pairs only (the parent's dense tent matmul, one batch per group, on
    its view's maps), each slot's features are gathered, and the field runs on K slots. Same
    values as ``FastRendererGraph`` fed every view of the call with the pairs not kept masked
    (the field pools and attends over the valid views of each point, in any order): per-point
    top-k shrinks the sampling to the kept pairs and the field's view axis to K, instead of
    masking them. Groups of a fixed size, not one padded row per view: the views a top-k keeps
    are uneven (the best-aligned view is kept by most points), and padding every view to the
    busiest one would sample as much as the full renderer.
    """

    def forward(self, field_maps: torch.Tensor, groups: torch.Tensor, grid: torch.Tensor,
                cues: torch.Tensor, pairs: torch.Tensor, mask: torch.Tensor,
                positions: torch.Tensor, directions: torch.Tensor,
                colours: torch.Tensor | None = None):
        colours = self._check_colours(colours)
        P, G = grid.shape[:2]
        K, R, S = pairs.shape
        index = pairs.reshape(K * R * S)

        def gather(x):                                    # [P, G, C] -> [K, R * S, C]
            return x.reshape(P * G, x.shape[-1])[index].reshape(K, R * S, x.shape[-1])

        def slots(bias):
            # The mask bias belongs to the slots, not to the pairs: added after the gather.
            per_pair = self._sample_slots(field_maps, grid[:, :, None], cues[:, :, None],
                                          None if colours is None else colours[:, :, None],
                                          torch.zeros_like(cues[..., 0]), groups)
            out = [gather(p) for p in per_pair]
            return [out[0] + bias[..., None], *out[1:]]

        slot_colours = slot_cos = None
        if colours is not None:
            slot_colours = gather(colours).reshape(K, R, S, 3)
            slot_cos = gather(cues[..., 3:]).reshape(K, R, S)
        return self._render(slots, field_maps.dtype, mask, positions, directions, slot_colours,
                            slot_cos)


def _key_softmax(scores: torch.Tensor, key_bias: torch.Tensor,
                 no_key_bias: torch.Tensor) -> torch.Tensor:
    """``softmax(scores + key_bias)`` over the last axis, with the Add over ``scores [R, H, S, S]``
    left out when ``no_key_bias`` (``key_bias`` all 0: then ``scores + 0`` is ``scores``, bit for
    bit). Exported as an ONNX ``If`` (``torch.cond``). Most calls need no key bias: the runtime
    gives the rays whose every sample has full weight calls of their own
    (``iris_runtime.raymarch.plan_calls``)."""
    def plain(s, b):
        return torch.softmax(s, dim=-1)

    def biased(s, b):
        return torch.softmax(s + b, dim=-1)

    return torch.cond(no_key_bias, plain, biased, (scores, key_bias))


def _colour_deviation(colours: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """``latent_field.colour_deviation`` view-major: ``colours [V, N, 3]``, validity weights
    ``m [V, N]`` -> ``[d, |d|] [V, N, 6]``."""
    w = m[..., None]
    mean = _sum_views(colours * w) / _sum_views(w).clamp_min(1e-6)                      # [N, 3]
    d = colours - mean
    return torch.cat([d, d.abs()], dim=-1)


def _sum_views(x: torch.Tensor) -> torch.Tensor:
    """``x.sum(0)`` of a view-major ``x [V, ...]`` as ``ones [1, V] @ x [V, -1]``: ONNX Runtime's
    MatMul runs this reduction over the leading axis several times faster than its ReduceSum
    (``benchmarks/ort_reductions.py``, docs/PERFORMANCE.md)."""
    V = x.shape[0]
    ones = torch.ones(1, V, dtype=x.dtype, device=x.device)
    return (ones @ x.reshape(V, -1)).reshape(x.shape[1:])


def views_max_as_scan(proto) -> int:
    """Rewrite, in place, every ``ReduceMax`` over the leading axis of the ONNX graph ``proto``
    (the fast graphs' reductions over views: the max-pool and the softmax maxima) as a ``Scan``
    whose body is one element-wise ``Max``, seeded with the first slice; -> the number rewritten.

    Same values (max is exact, in any order). The ``Scan`` runs a vectorised same-shape ``Max``
    per slice, several times faster than ONNX Runtime's ``ReduceMax`` over a leading axis
    (``benchmarks/ort_reductions.py``, docs/PERFORMANCE.md). The view count is a dynamic axis, so
    a fixed-arity ``Max`` of slices cannot express it."""
    import onnx
    from onnx import helper, numpy_helper

    g = proto.graph
    consts = {t.name: t for t in g.initializer}            # the axes: initializers or Constants
    consts.update((n.output[0], n.attribute[0].t) for n in g.node
                  if n.op_type == "Constant" and n.attribute and n.attribute[0].name == "value")
    # ONNX Runtime's Scan needs the rank of its body's tensors: the input's, from the graph.
    rank = {v.name: len(v.type.tensor_type.shape.dim) for v in
            [*g.input, *g.value_info, *g.output] if v.type.tensor_type.HasField("shape")}
    nodes, count = [], 0
    for n in g.node:
        axes = consts.get(n.input[1]) if n.op_type == "ReduceMax" and len(n.input) > 1 else None
        axes = None if axes is None else numpy_helper.to_array(axes).reshape(-1)
        if (axes is None or axes.tolist() != [0]
                or rank.get(n.input[0], 0) < 2):
            nodes.append(n)
            continue
        dims = [f"d{i}" for i in range(rank[n.input[0]] - 1)]
        keep = next((a.i for a in n.attribute if a.name == "keepdims"), 1)
        tag = f"views_max{count}"
        zero = f"{tag}_zero"
        g.initializer.append(numpy_helper.from_array(np.array(0, np.int64), zero))
        body = helper.make_graph(
            [helper.make_node("Max", ["acc", "x"], ["acc_out"])], f"{tag}_body",
            [helper.make_tensor_value_info("acc", onnx.TensorProto.FLOAT, dims),
             helper.make_tensor_value_info("x", onnx.TensorProto.FLOAT, dims)],
            [helper.make_tensor_value_info("acc_out", onnx.TensorProto.FLOAT, dims)])
        out = n.output[0] if not keep else f"{tag}_out"
        nodes += [helper.make_node("Gather", [n.input[0], zero], [f"{tag}_first"], axis=0,
                                   name=f"{tag}_first"),
                  helper.make_node("Scan", [f"{tag}_first", n.input[0]], [out], name=tag,
                                   num_scan_inputs=1, body=body)]
        if keep:
            axes0 = f"{tag}_axes"
            g.initializer.append(numpy_helper.from_array(np.array([0], np.int64), axes0))
            nodes.append(helper.make_node("Unsqueeze", [out, axes0], [n.output[0]],
                                          name=f"{tag}_keepdims"))
        count += 1
    del g.node[:]
    g.node.extend(nodes)
    return count


def renderer_wrapper(model: IrisModel, renderer: str = "reference") -> nn.Module:
    """The renderer export wrapper of kind ``renderer`` (``RENDERER_KINDS``)."""
    if renderer not in RENDERER_KINDS:
        raise ExportArgumentError(f"renderer: expected one of {list(RENDERER_KINDS)}, got "
                                  f"{renderer!r}")
    if renderer in ("fast", "fast-contrib"):
        return FastRendererGraph(model, contrib=renderer == "fast-contrib")
    return RendererGraph(model)


__all__ = ["FastRendererGraph", "SelectedViewsRendererGraph", "RENDERER_KINDS", "renderer_wrapper",
           "views_max_as_scan", "SELECTION_PREFIX"]
