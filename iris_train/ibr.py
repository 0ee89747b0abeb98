"""Explicit image-based rendering at the ray samples: a geometric training signal for the cameras.

A learned renderer can co-adapt to wrong cameras (it learns the best depth-free blur when every
camera sits at one place). These renderers cannot: they colour a target ray only with reference
RGB sampled where the ray's samples project, so their error falls only when the cameras (and the
focal) put corresponding pixels together. Both use the samples the model already draws.

* ``plane_sweep_render``: no parameters. Per sample, mean and variance of the reference colours
  over the views that see it; the ray's colour is the mean at the samples of low variance
  (softmax of ``-variance / tau`` over the samples seen by at least two views). A plane sweep.
* ``blend_render``: a learned per-sample logit (from the latent field's point feature) picks the
  samples, the colour is the same view-mean of reference RGB. The logit learns where the surface
  is; the colour stays explicit, so the cameras get a gradient that the logit cannot absorb.

Both work on full-resolution images and on blurred copies (``blur``): blurring widens the basin of
the photometric loss around the right cameras (coarse to fine).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from . import geometry as G

#: 5-tap binomial kernel; applied with dilation 2 (an ~9-pixel support at 64x64).
_BINOMIAL = (1.0, 4.0, 6.0, 4.0, 1.0)


def blur(images: torch.Tensor, dilation: int = 2) -> torch.Tensor:
    """Separable 5-tap binomial blur of ``images [N, C, H, W]`` with ``dilation`` (reflect padding)."""
    C = images.shape[1]
    k = torch.tensor(_BINOMIAL, dtype=images.dtype, device=images.device)
    k = k / k.sum()
    pad = 2 * dilation
    x = F.pad(images, (pad, pad, pad, pad), mode="reflect")
    x = F.conv2d(x, k.view(1, 1, 1, 5).expand(C, 1, 1, 5), groups=C, dilation=(1, dilation))
    return F.conv2d(x, k.view(1, 1, 5, 1).expand(C, 1, 5, 1), groups=C, dilation=(dilation, 1))


def sample_reference_rgb(ref_images: torch.Tensor, points: torch.Tensor, K: torch.Tensor,
                         world_from_cam: torch.Tensor):
    """Reference colours at ``points [R, S, 3]``: ``ref_images [V, 3, H, W]``, ``K [3, 3]`` in
    pixels of those images, ``world_from_cam [V, 4, 4]`` -> ``rgb [V, R, S, 3]``, ``valid [V, R, S]``.
    Bilinear, align_corners=False, border-clamped (the sampling rule of docs/ARCHITECTURE.md)."""
    H, W = ref_images.shape[-2:]
    uv, _, valid = G.project_points(points, K, G.invert_pose(world_from_cam), H, W)
    rgb = G.sample_bilinear(ref_images, G.pixels_to_grid(uv, H, W))
    return rgb, valid


def view_mean(rgb: torch.Tensor, valid: torch.Tensor):
    """Mean and variance over the valid views: ``rgb [V, R, S, 3]``, ``valid [V, R, S]`` ->
    ``mean [R, S, 3]``, ``var [R, S]`` (mean over channels), ``count [R, S]``."""
    m = valid.to(rgb.dtype)[..., None]
    count = m.sum(0)                                                       # [R, S, 1]
    mean = (rgb * m).sum(0) / count.clamp_min(1.0)
    var = (((rgb - mean) ** 2) * m).sum(0) / count.clamp_min(1.0)
    return mean, var.mean(-1), count[..., 0]


def plane_sweep_render(ref_images: torch.Tensor, world_from_cam: torch.Tensor, K: torch.Tensor,
                       origins: torch.Tensor, directions: torch.Tensor, depths: torch.Tensor,
                       tau: float = 0.03) -> torch.Tensor:
    """Parameter-free colour of rays ``origins, directions [R, 3]`` with sample depths ``[R, S]``
    from ``ref_images [V, 3, H, W]`` (in [0, 1]) at ``world_from_cam [V, 4, 4]``, ``K [3, 3]`` ->
    ``rgb [R, 3]``. A ray with no sample seen by two views gets the mean over its seen samples
    (or 0 if it sees nothing)."""
    points = origins[:, None, :] + depths[..., None] * directions[:, None, :]
    rgb, valid = sample_reference_rgb(ref_images, points, K, world_from_cam)
    mean, var, count = view_mean(rgb, valid)
    multi = count >= 2
    seen = count >= 1
    use = torch.where(multi.any(-1, keepdim=True), multi, seen)                    # [R, S]
    logits = torch.where(use, -var / tau, torch.full_like(var, -1e30))
    w = torch.softmax(logits, dim=-1) * use.to(var.dtype)
    return (w[..., None] * mean).sum(1)


def blend_render(logits: torch.Tensor, mean: torch.Tensor, count: torch.Tensor) -> torch.Tensor:
    """Learned-logit blend: per-sample ``logits [R, S]``, view-mean colours ``mean [R, S, 3]`` and
    view counts ``count [R, S]`` -> ``rgb [R, 3]``; only samples seen by a reference take part."""
    seen = count >= 1
    w = torch.softmax(torch.where(seen, logits, torch.full_like(logits, -1e30)), dim=-1)
    return ((w * seen.to(w.dtype))[..., None] * mean).sum(1)
