"""Camera geometry in torch: the differentiable twin of ``iris_runtime.geometry``.

Same convention, same names, same maths (see that module's docstring and docs/ARCHITECTURE.md, "Conventions"):
OpenCV axes, ``world_from_cam`` poses, pixel centres at +0.5, ``d = R K^-1 [u, v, 1]``.
Every function here is differentiable where its numpy twin is finite, and never produces inf or
NaN for masked points (points behind a camera, far outside its image).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from iris_runtime.geometry import CUE_EPS, DEPTH_EPS, EDGE_FADE, GRID_CLIP, NORM_EPS

__all__ = [
    "CUE_EPS", "DEPTH_EPS", "EDGE_FADE", "GRID_CLIP", "NORM_EPS", "pixel_centres",
    "intrinsics_from_focal", "scale_intrinsics", "invert_pose", "compose", "rotation_from_6d", "rays_from_pixels",
    "sample_depths", "project_points", "validity", "pixels_to_grid", "sample_bilinear", "sample_bilinear_dense",
    "tent_axes",
    "geometric_cue",
]


def pixel_centres(height: int, width: int, dtype=torch.float32, device=None) -> torch.Tensor:
    """Pixel centres ``[H*W, 2]`` as (u, v) = (j + 0.5, i + 0.5), row-major."""
    v, u = torch.meshgrid(torch.arange(height, dtype=dtype, device=device) + 0.5,
                          torch.arange(width, dtype=dtype, device=device) + 0.5, indexing="ij")
    return torch.stack([u.reshape(-1), v.reshape(-1)], dim=-1)


def intrinsics_from_focal(focal: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """``K [3, 3]`` in pixels from the normalised focal ``[fx/W, fy/H]`` (or one number fx/W for
    square pixels); centred principal point."""
    zero = torch.zeros((), dtype=focal.dtype, device=focal.device)
    one = torch.ones((), dtype=focal.dtype, device=focal.device)
    fx = focal[0] * width if focal.ndim else focal * width
    fy = focal[1] * height if focal.ndim else focal * width
    return torch.stack([
        torch.stack([fx, zero, zero + width / 2.0]),
        torch.stack([zero, fy, zero + height / 2.0]),
        torch.stack([zero, zero, one]),
    ])


def scale_intrinsics(K: torch.Tensor, from_hw, to_hw) -> torch.Tensor:
    """Intrinsics for an image resized from ``from_hw`` to ``to_hw`` (pixel centres at +0.5)."""
    S = torch.diag(torch.tensor([to_hw[1] / from_hw[1], to_hw[0] / from_hw[0], 1.0],
                                dtype=K.dtype, device=K.device))
    return S @ K


def invert_pose(T: torch.Tensor) -> torch.Tensor:
    """Inverse of rigid transforms ``[..., 4, 4]``."""
    R = T[..., :3, :3]
    t = T[..., :3, 3:]
    Rt = R.transpose(-1, -2)
    top = torch.cat([Rt, -Rt @ t], dim=-1)
    bottom = torch.zeros_like(T[..., 3:, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def compose(a_from_b: torch.Tensor, b_from_c: torch.Tensor) -> torch.Tensor:
    """``a_from_c = a_from_b @ b_from_c``."""
    return a_from_b @ b_from_c


def rotation_from_6d(a: torch.Tensor) -> torch.Tensor:
    """6D rotation ``[..., 6]`` to ``[..., 3, 3]`` by Gram-Schmidt; finite for degenerate inputs.

    Gram-Schmidt: b1 = a1/|a1|, b2 = unit(a2 - (b1.a2) b1), b3 = b1 x b2; columns [b1, b2, b3].
    Degenerate inputs stay finite and orthonormal with det +1: where |a1| is below ``tol`` times
    the input's scale, b1 falls back to x; where a2's part orthogonal to b1 is below it (a2 zero or
    parallel to a1), b2 falls back to the coordinate axis least aligned with b1. A second
    Gram-Schmidt pass keeps b2 orthogonal to b1 to rounding even when a2 is nearly parallel.
    Its numpy twin (a float64 reference for the tests; the runtime gets rotations from the
    encoder graph) is tests/np_geometry.py.
    """
    dtype = a.dtype
    tiny = torch.finfo(dtype).tiny
    tol = 64 * torch.finfo(dtype).eps
    scale = a.abs().amax(dim=-1, keepdim=True).clamp_min(tiny)
    a1, a2 = a[..., 0:3] / scale, a[..., 3:6] / scale
    n1 = a1.norm(dim=-1, keepdim=True)
    ex = torch.tensor([1.0, 0.0, 0.0], dtype=dtype, device=a.device).expand_as(a1)
    b1 = torch.where(n1 > tol, a1 / n1.clamp_min(tiny), ex)
    eye = torch.eye(3, dtype=dtype, device=a.device)
    fallback = eye[b1.abs().argmin(dim=-1)]
    a2p = a2 - (b1 * a2).sum(-1, keepdim=True) * b1
    n2 = a2p.norm(dim=-1, keepdim=True)
    a2p = torch.where(n2 > tol, a2p, fallback - (b1 * fallback).sum(-1, keepdim=True) * b1)
    b2 = a2p - (b1 * a2p).sum(-1, keepdim=True) * b1
    b2 = b2 / b2.norm(dim=-1, keepdim=True).clamp_min(tiny)
    b3 = torch.linalg.cross(b1, b2, dim=-1)
    return torch.stack([b1, b2, b3], dim=-1)


def rays_from_pixels(uv: torch.Tensor, K: torch.Tensor, world_from_cam: torch.Tensor):
    """Rays through ``uv [N, 2]``: ``origins [N, 3]``, ``directions [N, 3]`` (camera-z component 1).

    Batched: ``world_from_cam [..., 4, 4]`` with ``uv [..., N, 2]`` gives ``[..., N, 3]``.
    """
    x = (uv[..., 0] - K[0, 2]) / K[0, 0]
    y = (uv[..., 1] - K[1, 2]) / K[1, 1]
    d_cam = torch.stack([x, y, torch.ones_like(x)], dim=-1)
    R = world_from_cam[..., :3, :3]
    directions = d_cam @ R.transpose(-1, -2)
    origins = world_from_cam[..., None, :3, 3].expand_as(directions)
    return origins, directions


def sample_depths(near: float, far: float, n_samples: int, n_rays: int = 1,
                  stratified: bool = False, generator: torch.Generator | None = None,
                  dtype=torch.float32, device=None) -> torch.Tensor:
    """Camera depths ``[n_rays, S]``: bin centres, or one uniform draw per bin (training)."""
    edges = torch.linspace(near, far, n_samples + 1, dtype=torch.float64, device=device)
    width = (far - near) / n_samples
    if stratified:
        jitter = torch.rand((n_rays, n_samples), generator=generator, dtype=torch.float64,
                            device=device)
    else:
        jitter = torch.full((n_rays, n_samples), 0.5, dtype=torch.float64, device=device)
    return (edges[:-1] + jitter * width).to(dtype)


def project_points(points: torch.Tensor, K: torch.Tensor, cam_from_world: torch.Tensor,
                   height: int, width: int):
    """Project ``points [..., 3]`` into views ``cam_from_world [V, 4, 4]``.

    Returns ``uv [V, ..., 2]`` (finite, clipped where masked), ``z [V, ...]``, ``valid [V, ...]``.
    """
    V = cam_from_world.shape[0]
    flat = points.reshape(-1, 3)
    cam = torch.einsum("vij,nj->vni", cam_from_world[:, :3, :3], flat) + cam_from_world[:, None, :3, 3]
    z = cam[..., 2]
    valid_z = z > DEPTH_EPS
    z_safe = torch.where(valid_z, z, torch.full_like(z, DEPTH_EPS))
    u = K[0, 0] * cam[..., 0] / z_safe + K[0, 2]
    v = K[1, 1] * cam[..., 1] / z_safe + K[1, 2]
    valid = valid_z & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    u = torch.nan_to_num(u, nan=0.0).clamp(-GRID_CLIP * width, GRID_CLIP * width)
    v = torch.nan_to_num(v, nan=0.0).clamp(-GRID_CLIP * height, GRID_CLIP * height)
    shape = (V,) + tuple(points.shape[:-1])
    return torch.stack([u, v], dim=-1).reshape(shape + (2,)), z.reshape(shape), valid.reshape(shape)


def validity(uv: torch.Tensor, z: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Validity weights ``[V, ...]`` in [0, 1]: 0 at or behind the camera plane, else 1 in the
    image fading to 0 at ``EDGE_FADE`` pixels outside it (``iris_runtime.geometry.validity``)."""
    u, v = uv[..., 0], uv[..., 1]
    d = torch.maximum(torch.maximum(-u, u - width), torch.maximum(-v, v - height)).clamp_min(0.0)
    w = (1.0 - d / EDGE_FADE).clamp(0.0, 1.0)
    return torch.where(z > DEPTH_EPS, w, torch.zeros_like(w))


def pixels_to_grid(uv: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Pixels to normalised ``grid_sample`` coordinates (align_corners=False), clipped."""
    scale = torch.tensor([2.0 / width, 2.0 / height], dtype=uv.dtype, device=uv.device)
    return (uv * scale - 1.0).clamp(-GRID_CLIP, GRID_CLIP)


def sample_bilinear(feature_maps: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """Sample ``feature_maps [V, C, h, w]`` at ``grid [V, ..., 2]`` -> ``[V, ..., C]`` (channel-last).

    ``grid_sample(align_corners=False, padding_mode="border")``; bilinear weights sum to one, so
    sampling commutes with any per-pixel affine map of the features.
    """
    V, C = feature_maps.shape[:2]
    lead = grid.shape[1:-1]
    g = grid.reshape(V, 1, -1, 2)
    out = F.grid_sample(feature_maps, g, mode="bilinear", padding_mode="border", align_corners=False)
    return out.reshape(V, C, -1).transpose(1, 2).reshape((V,) + tuple(lead) + (C,))


def sample_bilinear_dense(feature_maps: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """Same result as ``sample_bilinear``, computed as a matmul with a dense interpolation matrix.

    The continuous cell coordinate is clamped to [0, size - 1] (``padding_mode="border"``) and the
    weight of cell y along an axis is the tent max(0, 1 - |y - g|), so the [N, h*w] weight matrix
    is the product of two per-axis tents: no gather or scatter, plain Sub/Abs/Max/Mul/MatMul when
    exported to ONNX (the renderer graph samples with this function too). Equal to grid_sample up
    to float rounding.

    Why dense: for the small feature grids of IRIS (8x8 in the tiny preset) the weight matrix is
    cheap and both the forward and the backward pass become BLAS matmuls, where grid_sample's
    backward scatters one point at a time (it dominated the training step), and ONNX
    ``GridSample`` dominated the exported renderer (docs/PERFORMANCE.md, "Renderer graph").
    """
    V, C, h, w = feature_maps.shape
    lead = grid.shape[1:-1]
    dense = tent_weights(grid.reshape(V, -1, 2).to(feature_maps.dtype), h, w)       # [V, N, h*w]
    out = dense @ feature_maps.reshape(V, C, h * w).transpose(1, 2)                # [V, N, C]
    return out.reshape((V,) + tuple(lead) + (C,))


def tent_axes(grid: torch.Tensor, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The per-axis bilinear weights of ``grid [..., 2]`` on an h x w map (align_corners=False,
    border-clamped): ``(wy [..., h], wx [..., w])``, the tent max(0, 1 - |cell - g|) per row and
    per column; cell (y, x) weighs ``wy[y] * wx[x]`` (``tent_weights``)."""
    gx = (((grid[..., 0] + 1.0) * w - 1.0) / 2.0).clamp(0.0, w - 1.0)
    gy = (((grid[..., 1] + 1.0) * h - 1.0) / 2.0).clamp(0.0, h - 1.0)
    xs = torch.arange(w, dtype=grid.dtype, device=grid.device)
    ys = torch.arange(h, dtype=grid.dtype, device=grid.device)
    wx = (1.0 - (gx[..., None] - xs).abs()).clamp_min(0.0)                         # [..., w]
    wy = (1.0 - (gy[..., None] - ys).abs()).clamp_min(0.0)                         # [..., h]
    return wy, wx


def tent_weights(grid: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """The dense bilinear weight matrix ``[V, N, h*w]`` of ``grid [V, N, 2]`` on an h x w map
    (align_corners=False, border-clamped): ``tent_axes``' row and column weights, their product
    per cell. ``sample_bilinear_dense`` multiplies it with the maps."""
    wy, wx = tent_axes(grid, h, w)
    return (wy[..., :, None] * wx[..., None, :]).reshape(grid.shape[0], grid.shape[1], h * w)


def geometric_cue(points: torch.Tensor, target_centre: torch.Tensor, source_centres: torch.Tensor,
                  eps: float = NORM_EPS, cue_eps: float = CUE_EPS) -> torch.Tensor:
    """GNT-style 4-d cue ``[..., V, 4]``: ``[(t - s)/max(|t - s|, cue_eps), t . s]`` (numpy twin).

    ``target_centre`` broadcasts against ``points`` (``[3]`` or ``[..., 3]``).
    """
    t = target_centre - points
    t = t / t.norm(dim=-1, keepdim=True).clamp_min(eps)
    s = source_centres - points[..., None, :]
    s = s / s.norm(dim=-1, keepdim=True).clamp_min(eps)
    diff = t[..., None, :] - s
    diff = diff / diff.norm(dim=-1, keepdim=True).clamp_min(cue_eps)
    dot = (t[..., None, :] * s).sum(-1, keepdim=True)
    return torch.cat([diff, dot], dim=-1)
