"""Shared multi-view encoder: patch embedding, one camera token per view, alternating per-view and
cross-view attention (a small Muskie/VGGT-style backbone).

There is deliberately no image-index embedding: every view gets the same learnable camera token and
the same 2D positional encoding, so the encoder is permutation-equivariant over views. The only
thing that singles out view 0 is the camera head, which expresses every pose relative to it.
"""
from __future__ import annotations

import torch
import torch.nn as nn

from .config import ModelConfig
from .layers import SelfAttentionBlock, sincos_2d

# Images arrive in [0, 1]; centre them so that patch embeddings start near zero mean.
_PIXEL_MEAN = 0.5
_PIXEL_STD = 0.25


class MultiViewEncoder(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        d = cfg.encoder_width
        self.patch_size = cfg.patch_size
        self.patch_embed = nn.Conv2d(3, d, kernel_size=cfg.patch_size, stride=cfg.patch_size)
        self.camera_token = nn.Parameter(torch.randn(1, 1, d) * 0.02)
        # Even blocks attend within a view, odd blocks across all views of the scene.
        self.blocks = nn.ModuleList(SelfAttentionBlock(d, cfg.encoder_heads, cfg.mlp_ratio)
                                    for _ in range(2 * cfg.encoder_pairs))
        self.norm = nn.LayerNorm(d)
        self.feature_grid = cfg.feature_grid
        self.register_buffer("pos_embed", sincos_2d(*self.feature_grid, d)[None], persistent=False)

    def forward(self, images: torch.Tensor):
        """``images [B, V, 3, H, W]`` in [0, 1] -> ``features [B, V, D, h, w]``, ``camera_tokens [B, V, D]``."""
        B, V, _, H, W = images.shape
        x = self.patch_embed((images.flatten(0, 1) - _PIXEL_MEAN) / _PIXEL_STD)   # [BV, D, h, w]
        D, h, w = x.shape[1:]
        pos = self.pos_embed
        if (h, w) != self.feature_grid:     # not just h*w: a 4x16 grid must not reuse the 8x8 table
            pos = sincos_2d(h, w, D, x.dtype, x.device)[None]
        tokens = x.flatten(2).transpose(1, 2) + pos                                 # [BV, hw, D]
        tokens = torch.cat([self.camera_token.expand(B * V, 1, D), tokens], dim=1)  # [BV, T, D]
        T = tokens.shape[1]
        for i, block in enumerate(self.blocks):
            if i % 2 == 0:
                tokens = block(tokens)                                   # per-view attention
            else:
                tokens = block(tokens.reshape(B, V * T, D)).reshape(B * V, T, D)   # cross-view
        tokens = self.norm(tokens)
        camera_tokens = tokens[:, 0].reshape(B, V, D)
        features = tokens[:, 1:].transpose(1, 2).reshape(B, V, D, h, w)
        return features, camera_tokens
