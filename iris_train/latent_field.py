"""Latent field: the value of the scene at a 3D point, from the reference views (Algorithm 1).

For a point x and each reference view k: project x, sample the view's features, compute the
geometric cue Δ_k(x) and the validity mask m_k(x); project the features to the model width
(u_k = φ_proj(v_k)), initialise the point token by a masked max-pool over views, and refine it with
the view transformer (masked attention of the point token over its views).

Design for inference speed: everything applied to a view's features before anything that depends on
the point is per-pixel, so it runs once per scene on the feature maps (``prepare``) instead of once
per sample. That is φ_proj (LayerNorm + Linear) and, for every view-transformer block, the key and
value projections of u_k, which are affine in u_k (no norm on keys/values, the cue enters additively
through its own linear map). Bilinear sampling has weights that sum to one, so it commutes with
these affine maps: sampling [u, W_k u + b_k, W_v u + b_v] equals projecting the sampled u, the
order of Algorithm 1. The per-sample work left is the query path, the cue's 4 -> 2W map, the
attention itself and the MLP.

The two orders agree up to float32 rounding; what the precompute saves:
``python benchmarks/field_precompute.py`` (results in benchmarks/results/field_precompute.md).
"""
from __future__ import annotations

import torch
import torch.nn as nn

from .config import ModelConfig
from .layers import MLP, masked_max, masked_softmax


class ViewBlock(nn.Module):
    """One view-transformer block: the point token attends over its reference views."""

    def __init__(self, width: int, heads: int, mlp_ratio: float):
        super().__init__()
        self.heads = heads
        self.width = width
        self.norm_q = nn.LayerNorm(width)
        self.to_q = nn.Linear(width, width)
        self.to_kv = nn.Linear(width, 2 * width)          # applied per pixel, in LatentField.prepare
        self.cue_to_kv = nn.Linear(4, 2 * width, bias=False)
        self.proj = nn.Linear(width, width)
        self.norm_mlp = nn.LayerNorm(width)
        self.mlp = MLP(width, int(width * mlp_ratio), width)

    def forward(self, q: torch.Tensor, kv: torch.Tensor, cues: torch.Tensor, mask: torch.Tensor):
        """``q [N, W]``, sampled ``kv [N, V, 2W]``, ``cues [N, V, 4]``, ``mask [N, V]`` -> ``[N, W]``."""
        N, V, _ = kv.shape
        H, W = self.heads, self.width
        kv = kv + self.cue_to_kv(cues)
        k = kv[..., :W].reshape(N, V, H, W // H)
        v = kv[..., W:].reshape(N, V, H, W // H)
        qh = self.to_q(self.norm_q(q)).reshape(N, H, 1, W // H)
        logits = (qh * k.transpose(1, 2)).sum(-1) * (W // H) ** -0.5          # [N, H, V]
        weights = masked_softmax(logits, mask[:, None, :], dim=-1)
        out = (weights[..., None] * v.transpose(1, 2)).sum(2)                    # [N, H, Dh]
        q = q + self.proj(out.reshape(N, W))
        return q + self.mlp(self.norm_mlp(q))


class ViewTransformer(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.blocks = nn.ModuleList(ViewBlock(cfg.field_width, cfg.field_heads, cfg.mlp_ratio)
                                    for _ in range(cfg.view_blocks))

    def forward(self, q0: torch.Tensor, kv: torch.Tensor, cues: torch.Tensor, mask: torch.Tensor):
        """``q0 [N, W]``; ``kv [N, V, 2W * blocks]`` (every block's keys/values of u^(0))."""
        q = q0
        step = kv.shape[-1] // len(self.blocks)
        for i, block in enumerate(self.blocks):
            q = block(q, kv[..., i * step:(i + 1) * step], cues, mask)
        return q


class LatentField(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.width = cfg.field_width
        self.feature_norm = nn.LayerNorm(cfg.encoder_width)
        self.proj = nn.Linear(cfg.encoder_width, cfg.field_width)          # φ_proj
        self.view_transformer = ViewTransformer(cfg)
        # Explicit colour: the sampled reference RGB enters every field-map channel additively
        # (u and each block's keys/values), so it is one affine map per sample and view.
        self.rgb_to_maps = nn.Linear(3, cfg.field_channels) if cfg.explicit_rgb else None
        # The views' disagreement (cfg.colour_deviation): [d_k, |d_k|] of each view's colour
        # from the sample's mean, additively into its channels; zero at first.
        self.deviation_to_maps = None
        if cfg.colour_deviation:
            self.deviation_to_maps = nn.Linear(6, cfg.field_channels, bias=False)
            nn.init.zeros_(self.deviation_to_maps.weight)

    def prepare(self, features: torch.Tensor) -> torch.Tensor:
        """Per-scene, per-pixel work: ``features [V, D, h, w]`` -> field maps ``[V, C', h, w]``.

        C' = W * (1 + 2 * view_blocks): u = φ_proj(f), then each block's [keys, values] of u.
        """
        u = self.proj(self.feature_norm(features.permute(0, 2, 3, 1)))           # [V, h, w, W]
        maps = [u] + [block.to_kv(u) for block in self.view_transformer.blocks]
        return torch.cat(maps, dim=-1).permute(0, 3, 1, 2).contiguous()

    def forward(self, sampled: torch.Tensor, cues: torch.Tensor, mask: torch.Tensor,
                colours: torch.Tensor | None = None) -> torch.Tensor:
        """Point-wise latent features ``f~ [N, W]`` from ``sampled [N, V, C']`` field-map values,
        ``cues [N, V, 4]``, validity ``mask [N, V]`` (bool) and, with ``explicit_rgb``, the
        reference ``colours [N, V, 3]`` in [0, 1] sampled at full resolution (and, with
        ``colour_deviation``, each view's deviation from their mean). Points valid in no view
        get the view transformer's response to a zero token with no attention (finite, and
        masked out of the ray transformer anyway)."""
        if self.rgb_to_maps is not None:
            sampled = sampled + self.rgb_to_maps(colours - 0.5)
        if self.deviation_to_maps is not None:
            sampled = sampled + self.deviation_to_maps(colour_deviation(colours, mask))
        u = sampled[..., :self.width]
        q0 = masked_max(u, mask[..., None], dim=1)                                # [N, W]
        return self.view_transformer(q0, sampled[..., self.width:], cues, mask)


def colour_deviation(colours: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``colours [N, V, 3]``, validity ``mask [N, V]`` -> ``[d, |d|] [N, V, 6]``, d the view's
    colour minus the validity-weighted mean colour of the sample (a mean of 0 where no view sees
    it: d is then the colour)."""
    w = mask.to(colours.dtype)[..., None]                                         # [N, V, 1]
    mean = (colours * w).sum(1, keepdim=True) / w.sum(1, keepdim=True).clamp_min(1e-6)
    d = colours - mean
    return torch.cat([d, d.abs()], dim=-1)
