"""Shared multi-view encoder: patch embedding, one camera token per view, alternating per-view and
cross-view attention (a small Muskie/VGGT-style backbone).

There is deliberately no image-index embedding: every view gets the same learnable camera token and
the same 2D positional encoding, so the encoder is permutation-equivariant over views 1..V-1. View
0 is the canonical frame: the camera head expresses every pose relative to it, and with
``ModelConfig.canonical_marker`` its tokens also carry a learnable marker (as VGGT's first frame),
which the relative poses need (docs/TRAINING.md).

**References are isolated.** Views are either references (they build the scene) or queries (views
whose camera is wanted but whose image must not leak into the scene: training targets, evaluation
targets, a photo to locate). In cross-view attention a reference token attends to reference tokens
only; a query token attends to the references and to its own view. So the features and cameras of
the references are exactly the same whether queries are present, changed or absent, and a query's
camera is predicted in the references' frame. View 0 (the canonical frame) must be a reference.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from .config import ModelConfig
from .layers import MASK_FILL, SelfAttentionBlock, conv_block, sincos_2d

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
        self.canonical_embed = nn.Parameter(torch.randn(1, 1, d) * 0.02) if cfg.canonical_marker else None
        # Even blocks attend within a view, odd blocks across all views of the scene.
        self.blocks = nn.ModuleList(SelfAttentionBlock(d, cfg.encoder_heads, cfg.mlp_ratio)
                                    for _ in range(2 * cfg.encoder_pairs))
        self.norm = nn.LayerNorm(d)
        self.feature_grid = cfg.feature_grid
        self.register_buffer("pos_embed", sincos_2d(*self.feature_grid, d)[None], persistent=False)

    def forward(self, images: torch.Tensor, is_reference: torch.Tensor | None = None):
        """``images [B, V, 3, H, W]`` in [0, 1], ``is_reference`` bool ``[V]`` or ``[B, V]`` (None:
        all views are references) -> ``features [B, V, D, h, w]``, ``camera_tokens [B, V, D]``."""
        B, V, _, H, W = images.shape
        x = self.patch_embed((images.flatten(0, 1) - _PIXEL_MEAN) / _PIXEL_STD)   # [BV, D, h, w]
        D, h, w = x.shape[1:]
        pos = self.pos_embed
        if (h, w) != self.feature_grid:     # not just h*w: a 4x16 grid must not reuse the 8x8 table
            pos = sincos_2d(h, w, D, x.dtype, x.device)[None]
        tokens = x.flatten(2).transpose(1, 2) + pos                                 # [BV, hw, D]
        tokens = torch.cat([self.camera_token.expand(B * V, 1, D), tokens], dim=1)  # [BV, T, D]
        T = tokens.shape[1]
        if self.canonical_embed is not None:
            is_canonical = (torch.arange(V, device=tokens.device) == 0).to(tokens.dtype)
            marker = is_canonical.repeat(B)[:, None, None] * self.canonical_embed       # [BV, 1, D]
            tokens = tokens + marker
        # Cross-view attention's mask as an additive bias (0, or MASK_FILL where a token may not
        # attend), built once: in ONNX Runtime a bool mask costs a Where and a NaN guard a block.
        bias = None if is_reference is None else \
            (~cross_view_mask(is_reference, T)).to(tokens.dtype) * MASK_FILL
        for i, block in enumerate(self.blocks):
            if i % 2 == 0:
                tokens = block(tokens)                                   # per-view attention
            else:                                                        # cross-view
                tokens = block(tokens.reshape(B, V * T, D), bias).reshape(B * V, T, D)
        tokens = self.norm(tokens)
        camera_tokens = tokens[:, 0].reshape(B, V, D)
        features = tokens[:, 1:].transpose(1, 2).reshape(B, V, D, h, w)
        return features, camera_tokens


#: Channels of the fine-feature stem (``FineFeatures``).
FINE_CHANNELS = 64


class FineFeatures(nn.Module):
    """The field's features at ``ModelConfig.field_grid`` (``map_scale`` times the token grid).

    The encoder's tokens see a whole patch (8x8 pixels in the tiny preset), so a sample's field
    value cannot tell two depths apart whose projections fall in the same patch: the weights along
    a ray spread. Image-based renderers sample features at 1/4 resolution or finer (pixelNeRF,
    IBRNet). Here a small per-view convolutional stem (stride ``patch_size / map_scale``) gives
    that detail, and a 1x1 conv mixes it with the token features upsampled bilinearly:
    ``features_fine = up(features) + mix([up(features), stem(image)])``. ``mix`` starts at zero,
    so a model fine-tuned from one of ``map_scale`` 1 starts from (nearly) its renders: bilinear
    sampling of the upsampled map instead of the coarse one. The stem sees one view only, so
    the references' isolation from the queries holds (``cross_view_mask``)."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.scale = cfg.map_scale
        layers, c_in = [], 3
        for _ in range((cfg.patch_size // cfg.map_scale).bit_length() - 1):   # log2(stride)
            layers += conv_block(c_in, FINE_CHANNELS, 3, 2)
            c_in = FINE_CHANNELS
        self.stem = nn.Sequential(*layers, *conv_block(c_in, FINE_CHANNELS, 3, 1))
        self.mix = nn.Conv2d(cfg.encoder_width + FINE_CHANNELS, cfg.encoder_width, 1)
        nn.init.zeros_(self.mix.weight)
        nn.init.zeros_(self.mix.bias)

    def forward(self, features: torch.Tensor, images: torch.Tensor) -> torch.Tensor:
        """``features [B, V, D, h, w]``, ``images [B, V, 3, H, W]`` in [0, 1] ->
        ``[B, V, D, scale*h, scale*w]``."""
        B, V = features.shape[:2]
        up = F.interpolate(features.flatten(0, 1), scale_factor=self.scale, mode="bilinear",
                           align_corners=False)                                    # [BV, D, sh, sw]
        detail = self.stem((images.flatten(0, 1) - _PIXEL_MEAN) / _PIXEL_STD)     # [BV, C, sh, sw]
        fine = up + self.mix(torch.cat([up, detail], dim=1))
        return fine.reshape(B, V, *fine.shape[1:])


def cross_view_mask(is_reference: torch.Tensor, tokens_per_view: int) -> torch.Tensor:
    """Which token may attend to which in cross-view attention: ``is_reference`` bool ``[V]`` or
    ``[B, V]`` -> ``attend`` bool ``[B or 1, V*T, V*T]``. Query view i (row) may see key view j iff
    j is a reference or j == i. Also the graph's contract: the exported encoder builds the same mask
    from its ``is_reference`` input."""
    ref = is_reference if is_reference.ndim == 2 else is_reference[None]           # [B, V]
    V = ref.shape[1]
    same = torch.eye(V, dtype=torch.bool, device=ref.device)[None]                 # [1, V, V]
    views = ref[:, None, :] | same                                                 # [B, V(q), V(k)]
    return views.repeat_interleave(tokens_per_view, 1).repeat_interleave(tokens_per_view, 2)
