"""The weights ``export.fast_renderer``'s graphs need in another form than the model's parameters,
derived from them (``derive_weights``), and the name prefix of its selection matrices.

Its own module because two others read it and neither may import the other: the fast graphs
register these tensors as buffers (``export.fast_renderer``), and the int8 quantiser
(``export.graphs.quantize_int8``) leaves the matmuls of the ``SELECTION_PREFIX`` ones in float.
Why each layout: ``export.fast_renderer``'s module docstring and docs/PERFORMANCE.md, "The fast
renderer graph".
"""
from __future__ import annotations

import torch

from iris_train.config import ModelConfig
from iris_train.model import IrisModel

#: Buffers of the graph whose names start with this are selection matrices (copies, sums and
#: broadcasts written as matmuls; 0/1, or one exact scale per column); ``export.graphs.
#: quantize_int8`` leaves their MatMuls and Gemms in float (quantising them would quantise the
#: tent weights, the coordinates and the attention weights they carry).
SELECTION_PREFIX = "select_"

Weights = dict[str, torch.Tensor]


def derive_weights(model: IrisModel) -> tuple[list[slice], Weights]:
    """``(slots, weights)``: the channel slice of each field-map slot (u, then each view block's
    keys and values) and every derived weight by buffer name, in registration order (call under
    ``torch.no_grad()``)."""
    slots, weights = slot_weights(model)
    cfg = model.cfg
    dtype = model.field.proj.weight.dtype
    extras = weights["slot0_rows"].shape[-1]            # every slot's rows are as wide
    weights.update(tent_weights(cfg, extras, dtype))
    weights.update(broadcast_weights(cfg, dtype))
    weights.update(view_block_weights(model))
    weights.update(ray_block_weights(model))
    return slots, weights


def slot_weights(model: IrisModel) -> tuple[list[slice], Weights]:
    """Slots of the field maps: u, then each view block's keys and values. Each slot's matmul
    ``B_slot = [maps_slot ; rows^T]``: ``slot{i}_rows [W, 4 (+ 3) + 1]`` multiply the cues (and
    colours) and the mask bias column; with explicit colour ``slot{i}_const [W]``, the constant
    of ``rgb_to_maps(colours - 0.5)``, is added to the maps."""
    W = model.cfg.field_width
    field = model.field
    slots = [slice(0, W)]
    ref = field.proj.weight
    cue_rows = [torch.zeros(W, 4, dtype=ref.dtype, device=ref.device)]
    for i, block in enumerate(field.view_transformer.blocks):
        base = W * (1 + 2 * i)
        for j in range(2):                                                       # k, v
            slots.append(slice(base + j * W, base + (j + 1) * W))
            cue_rows.append(block.cue_to_kv.weight[j * W:(j + 1) * W])
    weights: Weights = {}
    for i, (ch, cue) in enumerate(zip(slots, cue_rows)):
        rows, const = cue, None
        if field.rgb_to_maps is not None:
            wc = field.rgb_to_maps.weight[ch]                                     # [W, 3]
            rows = torch.cat([cue, wc], dim=-1)
            const = field.rgb_to_maps.bias[ch] - 0.5 * wc.sum(-1)                 # [W]
            weights[f"slot{i}_const"] = const
        # The mask bias column: added to u (the masked max-pool's input), not to k or v.
        rows = torch.cat([rows, torch.full_like(rows[:, :1], 1.0 if i == 0 else 0.0)], -1)
        weights[f"slot{i}_rows"] = rows
        if field.deviation_to_maps is not None:       # applied to the slots after sampling
            weights[f"slot{i}_deviation"] = field.deviation_to_maps.weight[ch]          # [W, 6]
    return slots, weights


def tent_weights(cfg: ModelConfig, extras: int, dtype: torch.dtype) -> Weights:
    """The dense sampler's design matrix ``A = [tent | extras]`` (``extras`` columns: cues,
    colours, mask bias) as Gemms and 0/1 matmuls."""
    weights: Weights = {}
    # The per-axis tent weights as Gemms: a pixel coordinate [N, 1] -> its differences to
    # every row (column) centre [N, h] ([N, w]), a copy and one subtraction, so bit for bit
    # ``tent_axes``' (gy - ys) without its broadcast Sub over a trailing axis of 1
    # (docs/PERFORMANCE.md).
    h, w = cfg.field_grid
    for axis, n in (("y", h), ("x", w)):
        weights[f"select_tent_{axis}"] = torch.ones(n, 1, dtype=dtype)
        weights[f"tent_{axis}_centres"] = -torch.arange(n, dtype=dtype)
    # The design matrix A = [tent | extras] as (row part @ select_rows) * (wx @ select_cols):
    # the 0/1 matmuls copy wy[y] and wx[x] to cell (y, x), so the tent columns are its outer
    # product bit for bit, and the extras' columns are the extra times sum_x wx = 1 (the
    # tent weights of a clamped coordinate sum to one, within one rounding). This replaces a
    # short-span broadcast Mul and a Concat over [V, N, hw + E] (docs/PERFORMANCE.md) with
    # two thin matmuls and one same-shape Mul.
    E = extras
    select_rows = torch.zeros(h + E, h * w + E, dtype=dtype)
    select_rows[:h, :h * w] = torch.eye(h, dtype=dtype).repeat_interleave(w, dim=1)
    select_rows[h:, h * w:] = torch.eye(E, dtype=dtype)
    select_cols = torch.ones(w, h * w + E, dtype=dtype)
    select_cols[:, :h * w] = torch.eye(w, dtype=dtype).repeat(1, h)
    weights["select_rows"] = select_rows                  # wy[y] -> (y, .), extras -> self
    weights["select_cols"] = select_cols                  # wx[x] -> (., x), sum -> extras
    return weights


def broadcast_weights(cfg: ModelConfig, dtype: torch.dtype) -> Weights:
    """Rows of ones and the view attention's per-head 0/1 matrices."""
    W = cfg.field_width
    weights: Weights = {}
    # Broadcasts over a trailing axis of 1 as matmuls with a row of ones (ONNX Runtime runs
    # ``x [..., 1] * y [..., n]`` several times slower than the same-shape op).
    for n in sorted({3, cfg.field_heads, W}):
        weights[f"select_ones{n}"] = torch.ones(1, n, dtype=dtype)
    # Per-head sums and broadcasts in the view attention as 0/1 matmuls (a ReduceSum over
    # the last axis and a broadcast Mul over heads in the layout ONNX Runtime runs slowly).
    H = cfg.field_heads
    head_of = torch.arange(W) // (W // H)
    weights["select_head_sum"] = (head_of[:, None] == torch.arange(H)).to(dtype)      # [W, H]
    weights["select_head_expand"] = weights["select_head_sum"].t()                    # [H, W]
    return weights


def view_block_weights(model: IrisModel) -> Weights:
    """View blocks: the attention scale folded into the query projection."""
    W = model.cfg.field_width
    weights: Weights = {}
    for i, block in enumerate(model.field.view_transformer.blocks):
        scale = (W // block.heads) ** -0.5
        weights[f"view{i}_wq"] = block.to_q.weight * scale
        weights[f"view{i}_bq"] = block.to_q.bias * scale
    return weights


def ray_block_weights(model: IrisModel) -> Weights:
    """Ray blocks: per-head q/k/v ``[H, W, Dh]`` (scale in q; the key bias dropped: it adds
    q . b_k to every logit of a row; the value bias folded into the output projection's bias: the
    rows of the attention sum to one), each injection split in two, and the position encoding's
    frequencies."""
    W = model.cfg.field_width
    rt = model.renderer.ray_transformer
    P = 3 * (1 + 2 * rt.pos_freqs)
    weights: Weights = {}
    for i, (inject, block) in enumerate(zip(rt.inject, rt.blocks)):
        H = block.heads
        Dh = W // H
        scale = Dh ** -0.5
        wq, wk, wv = block.qkv.weight.split(W)
        bq, _, bv = block.qkv.bias.split(W)

        def per_head(weight, H=H, Dh=Dh):          # [W_out, W_in] -> [H, W_in, Dh]
            return weight.reshape(H, Dh, W).transpose(1, 2)

        # q on y = [normed, 1] [W + 1]: its bias from the 1, no Add over [R, H, S, Dh]. (The
        # key mask stays an Add: an extra q . k component carrying it makes the projections
        # 17 wide, which ONNX Runtime's kernels run slower than 16, docs/PERFORMANCE.md.)
        wq_aug = torch.cat([per_head(wq * scale), (bq * scale).reshape(H, 1, Dh)], dim=1)
        weights[f"ray{i}_wq"] = wq_aug                                       # [H, W + 1, Dh]
        weights[f"ray{i}_wk"] = per_head(wk)
        weights[f"ray{i}_wv"] = per_head(wv)
        weights[f"ray{i}_bproj"] = block.proj.bias + block.proj.weight @ bv
        # psi^(l) split into its per-sample (position) and per-ray (direction) parts.
        weights[f"inject{i}_wpos"] = inject.weight[:, :P]
        weights[f"inject{i}_wdir"] = inject.weight[:, P:]
    # The position encoding's products x_c * 2^k pi as a matmul (one nonzero per column: the
    # same products, bit for bit, without a broadcast Mul over a trailing axis of 1).
    F_ = rt.pos_freqs
    freqs = (2.0 ** torch.arange(F_, dtype=model.field.proj.weight.dtype)) * torch.pi
    weights["select_pos_freqs"] = torch.block_diag(*[freqs[None]] * 3)              # [3, 3F]
    return weights


__all__ = ["SELECTION_PREFIX", "derive_weights", "slot_weights", "tent_weights",
           "broadcast_weights", "view_block_weights", "ray_block_weights"]
