"""Correlation camera head: each view's pose from explicit cross-view evidence, the correlation
volume of its fine feature map with view 0's, beside the encoder's camera tokens
(``ModelConfig.camera_head = "correlation"``).

Why. The token head (``camera_head.CameraHead``) regresses a pose from two pooled tokens; it fits
training scenes and does not generalise (held-out RPA@15 ~0.27, docs/TRAINING.md "L1 continued").
What generalises in published work is a dense correlation volume between the two images'
feature maps, processed by convolutions with one image's positions as channels ("Extreme Rotation
Estimation using Dense Correlation Volumes", Cai et al., CVPR 2021): how view 0's patches move in
view i is nearly independent of what the scene looks like, so the mapping from it to a rotation
can transfer across scenes.

The stages, for images ``[B, V, 3, H, W]`` (tiny preset: 64x64, 8x8 tokens):

1. **Stem** (``CorrelationStem``): per view, three 3x3 convs (stride 2, 2, 1; GroupNorm + ReLU
   between) -> descriptors ``[B, V, C, 2h, 2w]`` (C = ``CORRELATION_CHANNELS`` = 64; 16x16 for
   the tiny preset: twice the token grid, ``ModelConfig.correlation_grid``; with
   ``correlation_scale`` 4 the second conv keeps its input's size, 4x the token grid; patches
   larger than 8 average-pool the map down to the grid). The stem sees one image only: a
   siamese descriptor, as in the paper. The encoder's 8x8 features are deliberately *not*
   concatenated: they carry the encoder's fixed sin-cos positional encoding, so their correlation
   favours "same position matches same position", i.e. the identity pose, which is exactly where
   the token head got stuck (docs/TRAINING.md, R3); and the encoder's context already reaches the
   pose MLP through the camera tokens.
2. **Correlation** (``correlation_volume``): descriptors L2-normalised over channels;
   ``corr[b, i, p0, y, x] = <f_0(p0), f_i(y, x)>`` for every position p0 = (y0, x0) of view 0:
   one batched MatMul, ``[B, V, (2h)(2w), 2h, 2w]``. Every view is correlated with view 0 only,
   and view 0 is always a reference, so a reference's evidence never involves a query image: the
   encoder's reference isolation holds for the cameras too (``tests/test_correlation_head.py``).
   No coarser pooled level: the volume is global (every view-0 position against every view-i
   position), so displacement range needs no pyramid at this grid size.
3. **Correlation network**: view 0's positions as channels, view i's grid as space: a 1x1 conv
   (a learned weighting of view 0's positions) and two 3x3 convs (the second of stride 2), each
   with GroupNorm + ReLU -> ``[BV, E, h, w]`` (E = ``EVIDENCE_CHANNELS``).
4. **Pooling that keeps where**: a plain global average would make the evidence invariant to where
   in view i a pattern of view 0 was found, which is the displacement a rotation causes. So each
   channel is pooled twice: its mean, and its *spatial-softmax keypoint* (the softmax-weighted
   mean image coordinate, x and y in [-1, 1]; Levine et al., "End-to-End Training of Deep
   Visuomotor Policies", 2016) -> ``[B, V, 3E]``.
5. **Pose MLP** on ``[evidence_i, token_i, token_0]`` -> 9 numbers (6D rotation residual on the
   identity + translation), the last layer initialised small (std ``POSE_INIT_STD``, zero bias) so
   every camera starts near the identity, as the token head's does; view 0's pose is exactly the
   identity (``camera_head.world_from_cam_from_residual``). The focal is the token head's
   (``focal_mlp`` on token 0; same name and shape, so it loads from a token-head checkpoint).

Everything is standard ONNX (Conv, GroupNorm's decomposition, MatMul, Softmax, ReduceMean):
no SVD, no matrix inverse; ``export.graphs.EncoderGraph`` exports it unchanged.
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from .camera_head import _IDENTITY_6D, POSE_INIT_STD, CameraHead, world_from_cam_from_residual
from .config import ModelConfig
from .layers import MLP, conv_block

#: Channels of the stem's descriptors (the correlation's dot products are over these).
CORRELATION_CHANNELS = 64
#: Channels of the correlation network's output (the evidence is 3x this: mean + keypoint x, y).
EVIDENCE_CHANNELS = 64
#: GroupNorm groups in the stem and the correlation network (per sample: no batch statistics,
#: so a view's output never depends on the other views of the batch).
NORM_GROUPS = 8
#: The same pixel normalisation as the encoder's patch embedding (``encoder._PIXEL_MEAN/STD``).
_PIXEL_MEAN = 0.5
_PIXEL_STD = 0.25


class CorrelationStem(nn.Sequential):
    """Per-view descriptors on the correlation grid: ``images [N, 3, H, W]`` in [0, 1] ->
    ``[N, C, *ModelConfig.correlation_grid]``, not normalised."""

    def __init__(self, cfg: ModelConfig, channels: int = CORRELATION_CHANNELS):
        second = 2 if cfg.correlation_scale == 2 else 1
        layers = [*conv_block(3, channels // 2, 3, 2, NORM_GROUPS),
                  *conv_block(channels // 2, channels, 3, second, NORM_GROUPS),
                  nn.Conv2d(channels, channels, 3, padding=1)]
        # Stride 4 (2 at correlation_scale 4) so far: a patch of 8 has the correlation grid
        # already, a patch of 16 (the paper and 128 presets) averages 2x2 cells down to it.
        pool = cfg.patch_size // 8
        if pool > 1:
            layers.append(nn.AvgPool2d(pool))
        super().__init__(*layers)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return super().forward((images - _PIXEL_MEAN) / _PIXEL_STD)


def correlation_volume(descriptors: torch.Tensor) -> torch.Tensor:
    """``descriptors [B, V, C, h, w]`` -> ``corr [B, V, h*w, h, w]``: the cosine similarity of
    every position p0 of view 0 (channel index p0 = y0 * w + x0) with every position (y, x) of
    view i; ``corr[:, 0]`` is view 0 against itself."""
    B, V, C, h, w = descriptors.shape
    f = F.normalize(descriptors.flatten(3), dim=2, eps=1e-6)                  # [B, V, C, hw]
    f0 = f[:, :1].transpose(2, 3)                                             # [B, 1, hw(p0), C]
    return torch.matmul(f0, f).reshape(B, V, h * w, h, w)                    # [B, V, hw, h, w]


def spatial_softmax_keypoints(x: torch.Tensor) -> torch.Tensor:
    """``x [N, E, h, w]`` -> ``[N, E, 2]``: per channel the softmax-weighted mean position (x, y),
    cell centres in [-1, 1] (``align_corners=False`` convention)."""
    N, E, h, w = x.shape
    ys = (torch.arange(h, dtype=x.dtype, device=x.device) + 0.5) * (2.0 / h) - 1.0
    xs = (torch.arange(w, dtype=x.dtype, device=x.device) + 0.5) * (2.0 / w) - 1.0
    coords = torch.stack([xs.repeat(h), ys.repeat_interleave(w)], dim=-1)     # [hw, 2]
    weights = torch.softmax(x.flatten(2), dim=-1)                             # [N, E, hw]
    return torch.matmul(weights, coords)                                      # [N, E, 2]


class CorrelationCameraHead(nn.Module):
    """Camera head on explicit cross-view evidence (module docstring) and the camera tokens."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        d = cfg.encoder_width
        h2, w2 = cfg.correlation_grid
        self.stem = CorrelationStem(cfg)
        self.correlation_net = nn.Sequential(
            *conv_block(h2 * w2, EVIDENCE_CHANNELS, 1, 1, NORM_GROUPS),
            *conv_block(EVIDENCE_CHANNELS, EVIDENCE_CHANNELS, 3, 1, NORM_GROUPS),
            *conv_block(EVIDENCE_CHANNELS, EVIDENCE_CHANNELS, 3, 2, NORM_GROUPS))
        # Not ``pose_mlp``: its input differs from the token head's, and a token-head checkpoint
        # must not half-load into it (``iris_train.train.load_init_weights``).
        self.fused_pose_mlp = MLP(3 * EVIDENCE_CHANNELS + 2 * d, d, 9)
        self.focal_mlp = MLP(d, d // 2, 2)
        # Small last layers, as the token head's (camera_head.CameraHead): cameras start near the
        # identity with the unit focal, and the encoder still gets a gradient through the head.
        for last, std in ((self.fused_pose_mlp[-1], POSE_INIT_STD), (self.focal_mlp[-1], 1e-3)):
            nn.init.normal_(last.weight, std=std)
            nn.init.zeros_(last.bias)
        self.log_focal_min = math.log(cfg.focal_min)
        self.log_focal_range = math.log(cfg.focal_max) - math.log(cfg.focal_min)
        self.register_buffer("identity_6d", torch.tensor(_IDENTITY_6D), persistent=False)
        self.image_size = (cfg.image_height, cfg.image_width)

    def evidence(self, images: torch.Tensor) -> torch.Tensor:
        """``images [B, V, 3, H, W]`` in [0, 1] -> cross-view evidence ``[B, V, 3E]`` of each view
        against view 0 (view 0's row: against itself)."""
        B, V = images.shape[:2]
        descriptors = self.stem(images.flatten(0, 1))                          # [BV, C, 2h, 2w]
        corr = correlation_volume(descriptors.unflatten(0, (B, V)))             # [B, V, P0, 2h, 2w]
        x = self.correlation_net(corr.flatten(0, 1))                            # [BV, E, h, w]
        pooled = torch.cat([x.mean(dim=(2, 3)), spatial_softmax_keypoints(x).flatten(1)], dim=1)
        return pooled.unflatten(0, (B, V))                                      # [B, V, 3E]

    def forward(self, camera_tokens: torch.Tensor, images: torch.Tensor | None):
        """``camera_tokens [B, V, D]``, ``images [B, V, 3, H, W]`` in [0, 1] at the model's
        resolution -> ``world_from_cam [B, V, 4, 4]`` (view 0 = I), ``focal [B, 2]``."""
        B, V, D = camera_tokens.shape
        if images is None or images.shape[:2] != (B, V) or tuple(images.shape[2:]) != (3, *self.image_size):
            # The correlation's channels are view 0's positions: one resolution only.
            raise ValueError(f"images: the correlation camera head needs the views' images "
                             f"[{B}, {V}, 3, {self.image_size[0]}, {self.image_size[1]}], got "
                             f"{None if images is None else tuple(images.shape)}")
        token0 = camera_tokens[:, :1].expand(B, V, D)
        features = torch.cat([self.evidence(images), camera_tokens, token0], dim=-1)
        out = self.fused_pose_mlp(features)                                     # [B, V, 9]
        return world_from_cam_from_residual(out, self.identity_6d), self.focal(camera_tokens)

    #: The shared focal from token 0: the token head's own (same ``focal_mlp`` and bounds).
    focal = CameraHead.focal
