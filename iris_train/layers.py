"""Small building blocks shared by the IRIS stages: MLP, transformer block, masked reductions,
sinusoidal encodings.

Masking has one meaning everywhere, in torch and in the exported ONNX graphs: masked entries are
filled with the finite ``MASK_FILL`` before the softmax (never -inf, which turns into NaN when a
whole row is masked), and the normalised weights are multiplied by the mask afterwards. A row with
no valid entry therefore gets all-zero weights, and a masked max-pool over no valid entry gives 0.

Masks are validity weights ``w`` in [0, 1] (a bool mask is the weights 0 / 1): an entry with
``w > 0`` enters the softmax or max-pool with the additive bias ``FADE_GAIN * (w - 1)``
(``validity_bias``), 0 for a fully valid entry, so 0 / 1 weights give exactly the hard mask, and an
entry fading out (a sample crossing a view's image edge, ``geometry.validity``) leaves the
softmax and the max-pool continuously instead of at once.
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

#: Finite stand-in for -inf in masked softmax and max-pool (exp underflows to exactly 0 in float32).
MASK_FILL = -1e30
#: Slope of the bias of a fractional validity weight (``validity_bias``): an entry at weight w
#: has its logit (max-pool input) lowered by FADE_GAIN * (1 - w). It must exceed the largest gap
#: between one view's max-pool input and the next view's, or that view would still lead the pool
#: at w -> 0, where its bias jumps from -FADE_GAIN to MASK_FILL (the shipped model's gaps:
#: ``benchmarks/pose_sensitivity.py``, "pool gap"). The render's slope in the cameras grows with
#: FADE_GAIN / EDGE_FADE; the same benchmark compares settings (docs/PERFORMANCE.md, "Continuous
#: validity").
FADE_GAIN = 10.0


def validity_bias(weight: torch.Tensor) -> torch.Tensor:
    """The additive bias of validity weights ``weight`` (float in [0, 1]): ``FADE_GAIN * (w -
    1)`` where ``w > 0`` (exactly 0 at w = 1), ``MASK_FILL`` where ``w = 0``."""
    return torch.where(weight > 0, FADE_GAIN * (weight - 1.0), torch.full_like(weight, MASK_FILL))


def validity_bias_where_free(weight: torch.Tensor) -> torch.Tensor:
    """``validity_bias(weight)``, bit for bit, without a ``Where`` (for ONNX graphs laid out
    without one, ``export.fast_renderer``): ``FADE_GAIN * (w - 1) + (w <= 0) * MASK_FILL``. At
    w = 0 that is ``MASK_FILL - FADE_GAIN``, which rounds to ``MASK_FILL`` in float32 and float64;
    elsewhere the added term is a signed zero."""
    return FADE_GAIN * (weight - 1.0) + (weight <= 0).to(weight.dtype) * MASK_FILL


def masked_softmax(logits: torch.Tensor, mask: torch.Tensor, dim: int = -1) -> torch.Tensor:
    """Softmax over ``dim`` restricted to ``mask`` (validity weights in [0, 1] or bool,
    broadcastable; ``validity_bias``); all-masked rows give 0."""
    w = mask.to(logits.dtype)
    filled = torch.where(w > 0, logits + validity_bias(w), torch.full_like(logits, MASK_FILL))
    return torch.softmax(filled, dim=dim) * (w > 0).to(logits.dtype)


def masked_max(x: torch.Tensor, mask: torch.Tensor, dim: int) -> torch.Tensor:
    """Max over ``dim`` of ``x + validity_bias(mask)`` where ``mask > 0`` (validity weights in
    [0, 1] or bool, same shape as x up to broadcasting); 0 if none."""
    w = mask.to(x.dtype)
    filled = torch.where(w > 0, x + validity_bias(w), torch.full_like(x, MASK_FILL))
    any_valid = (w > 0).any(dim=dim)
    return torch.where(any_valid, filled.amax(dim=dim), torch.zeros((), dtype=x.dtype))


def conv_block(c_in: int, c_out: int, kernel: int, stride: int, groups: int = 8) -> list[nn.Module]:
    """Conv (same padding) + GroupNorm (per sample: a view's output never depends on the other
    views of the batch) + ReLU."""
    return [nn.Conv2d(c_in, c_out, kernel, stride=stride, padding=kernel // 2),
            nn.GroupNorm(groups, c_out), nn.ReLU()]


class MLP(nn.Sequential):
    def __init__(self, dim_in: int, dim_hidden: int, dim_out: int):
        super().__init__(nn.Linear(dim_in, dim_hidden), nn.GELU(), nn.Linear(dim_hidden, dim_out))


class SelfAttentionBlock(nn.Module):
    """Pre-norm transformer block (attention + MLP) over tokens ``[B, T, D]``.

    Used by the encoder; uses PyTorch's fused attention. ``bias [B or 1, T, T]`` (float, optional)
    is added to the attention scores: 0 where a query may attend to a key, ``MASK_FILL`` where it
    may not; every query must be allowed at least one key (the encoder always allows a token its
    own view), so no row is fully masked.
    """

    def __init__(self, dim: int, heads: int, mlp_ratio: float):
        super().__init__()
        self.heads = heads
        self.norm1 = nn.LayerNorm(dim)
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = MLP(dim, int(dim * mlp_ratio), dim)

    def forward(self, x: torch.Tensor, bias: torch.Tensor | None = None) -> torch.Tensor:
        B, T, D = x.shape
        q, k, v = self.qkv(self.norm1(x)).view(B, T, 3, self.heads, D // self.heads).permute(2, 0, 3, 1, 4)
        mask = None if bias is None else bias[:, None]                # [B|1, 1, T, T]
        a = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)   # [B, H, T, Dh]
        x = x + self.proj(a.transpose(1, 2).reshape(B, T, D))
        return x + self.mlp(self.norm2(x))


def sinusoidal_encoding(x: torch.Tensor, n_freqs: int) -> torch.Tensor:
    """``[..., C]`` -> ``[..., C * (1 + 2 n_freqs)]``: x, sin(2^k pi x), cos(2^k pi x)."""
    freqs = (2.0 ** torch.arange(n_freqs, dtype=x.dtype, device=x.device)) * math.pi
    xf = (x[..., None] * freqs).flatten(-2)                          # [..., C * F]
    return torch.cat([x, torch.sin(xf), torch.cos(xf)], dim=-1)


def sincos_2d(h: int, w: int, dim: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """Fixed 2D sin-cos positional encoding ``[h*w, dim]`` (half the channels for rows, half for cols)."""
    assert dim % 4 == 0, "2D sin-cos encoding needs dim divisible by 4"
    quarter = dim // 4
    omega = 1.0 / (10000.0 ** (torch.arange(quarter, dtype=torch.float64, device=device) / quarter))
    ys, xs = torch.meshgrid(torch.arange(h, dtype=torch.float64, device=device),
                            torch.arange(w, dtype=torch.float64, device=device), indexing="ij")
    ey = ys.reshape(-1, 1) * omega
    ex = xs.reshape(-1, 1) * omega
    return torch.cat([ey.sin(), ey.cos(), ex.sin(), ex.cos()], dim=1).to(dtype)
