"""Camera head: pose of every view relative to view 0, and one shared focal length.

Pose of view i is regressed from [camera token i, camera token 0] as a residual on the identity
(6D rotation + translation; the last layer starts at zero, so every camera starts at the identity).
View 0 is the canonical frame: its pose is exactly the identity whatever the tokens say. The focal
(fx/W, fy/H) comes from token 0 through a log-space sigmoid bounded to [focal_min, focal_max].

This is ``ModelConfig.camera_head = "tokens"`` (every checkpoint without that field); "correlation"
adds explicit cross-view evidence (``iris_train.correlation.CorrelationCameraHead``), assembled into
poses by the same ``world_from_cam_from_residual``.
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn

from .config import ModelConfig
from .geometry import rotation_from_6d
from .layers import MLP

_IDENTITY_6D = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)   # first two columns of I
POSE_INIT_STD = 0.02


class CameraHead(nn.Module):
    def __init__(self, cfg: ModelConfig):
        super().__init__()
        d = cfg.encoder_width
        self.pose_mlp = MLP(2 * d, d, 9)
        self.focal_mlp = MLP(d, d // 2, 2)
        # Small last layers: cameras start near the identity with the unit focal. The pose layer's
        # std is 0.02, not ~0: the gradient that reaches the encoder through the head scales with
        # it, and at 1e-3 the encoder's camera pathway learned ~nothing (docs/TRAINING.md, R3).
        for last, std in ((self.pose_mlp[-1], POSE_INIT_STD), (self.focal_mlp[-1], 1e-3)):
            nn.init.normal_(last.weight, std=std)
            nn.init.zeros_(last.bias)
        self.log_focal_min = math.log(cfg.focal_min)
        self.log_focal_range = math.log(cfg.focal_max) - math.log(cfg.focal_min)
        self.register_buffer("identity_6d", torch.tensor(_IDENTITY_6D), persistent=False)

    def forward(self, camera_tokens: torch.Tensor, images: torch.Tensor | None = None):
        """``camera_tokens [B, V, D]`` -> ``world_from_cam [B, V, 4, 4]`` (view 0 = I), ``focal [B, 2]``.

        ``images`` is accepted and ignored, so that every camera head is called alike
        (``correlation.CorrelationCameraHead`` reads them)."""
        B, V, D = camera_tokens.shape
        token0 = camera_tokens[:, :1].expand(B, V, D)
        out = self.pose_mlp(torch.cat([camera_tokens, token0], dim=-1))          # [B, V, 9]
        return world_from_cam_from_residual(out, self.identity_6d), self.focal(camera_tokens)

    def focal(self, camera_tokens: torch.Tensor) -> torch.Tensor:
        """``camera_tokens [B, V, D]`` -> the shared ``focal [B, 2]`` (fx/W, fy/H) from token 0."""
        return torch.exp(self.log_focal_min + self.log_focal_range
                         * torch.sigmoid(self.focal_mlp(camera_tokens[:, 0])))   # [B, 2]


def world_from_cam_from_residual(out: torch.Tensor, identity_6d: torch.Tensor) -> torch.Tensor:
    """The pose head's raw output ``out [B, V, 9]`` (6D rotation residual on the identity, then
    translation) -> ``world_from_cam [B, V, 4, 4]``, view 0 exactly the identity (the canonical
    frame, whatever its row of ``out`` says). Shared by every camera head."""
    B, V = out.shape[:2]
    R = rotation_from_6d(identity_6d + out[..., :6])                         # [B, V, 3, 3]
    t = out[..., 6:, None]                                                   # [B, V, 3, 1]
    bottom = torch.zeros_like(out[..., :4])
    bottom = bottom + torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=bottom.dtype, device=bottom.device)
    pose = torch.cat([torch.cat([R, t], dim=-1), bottom[..., None, :]], dim=-2)
    is_canonical = (torch.arange(V, device=pose.device) == 0)[None, :, None, None]
    eye = torch.eye(4, dtype=pose.dtype, device=pose.device)
    return torch.where(is_canonical, eye, pose)
