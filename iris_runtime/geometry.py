"""Camera geometry in numpy: the one convention of docs/ARCHITECTURE.md, used by the runtime.

Convention (everywhere in IRIS): OpenCV camera axes (x right, y down, z forward). Poses are
``world_from_cam`` 4x4 (camera-to-world): rotation columns are the camera axes in world, the last
column is the camera centre. Pixel (row i, col j) has its centre at (u, v) = (j + 0.5, i + 0.5).
Rays are ``x = o + z * d`` with ``d = R K^-1 [u, v, 1]`` so that ``z`` is the camera depth.

``iris_train.geometry`` is the torch twin of this file (same names, same maths); a test checks that
the two agree in float64 to 1e-10 (twins the runtime does not need, ``pixel_centres``, ``compose``
and ``rotation_from_6d``, live in tests/np_geometry.py). Functions work for float32 and float64 and
keep the dtype of their main input.
"""
from __future__ import annotations

import numpy as np

# The rigid-transform maths of the boundary checks, here under their geometric names.
from .validation import RIGID_ATOL, nearest_rotation, rigidity_error  # noqa: F401

#: A point is valid in a view only when its camera depth exceeds this (model units). Keeps
#: ``u = x / z`` finite and excludes points on or behind the camera plane.
DEPTH_EPS = 1e-6
#: A sample's validity in a view fades from 1 at the image's edge to 0 at this many pixels outside
#: it (``validity``), so that the render is continuous in the cameras: with a hard edge, float32
#: cameras differing in the last bits put a sample on either side of it and the colour jumps.
#: Outside the image, so that samples of the image keep weight 1 exactly (STABILITY.md; figures:
#: docs/PERFORMANCE.md, "Continuous validity").
EDGE_FADE = 1.0
#: Normalised grid coordinates are clipped to this range so that masked points never carry inf
#: or NaN into the feature sampler; any |g| > 1 is outside the image and masked anyway.
GRID_CLIP = 2.0
#: Norm floor for unit vectors (directions to camera centres).
NORM_EPS = 1e-12
#: Norm floor of (t - s) in the geometric cue. The direction of t - s is undefined where target and
#: source directions coincide (e.g. rendering exactly at an input camera); below this norm the cue's
#: first three entries shrink linearly to 0 instead of jumping between unit vectors, so the cue is
#: Lipschitz with constant 1/CUE_EPS (STABILITY.md, "Target centre = reference centre").
CUE_EPS = 1e-4


def intrinsics_from_focal(focal, height: int, width: int) -> np.ndarray:
    """``K [3, 3]`` in pixels from a normalised focal, principal point at the image centre: the
    model's ``[fx/W, fy/H]``, or one number fx/W for square pixels (fy = fx in pixels, the focal
    of the camera solve)."""
    focal = np.asarray(focal)
    K = np.zeros((3, 3), dtype=np.result_type(focal.dtype, np.float32))
    K[0, 0] = focal[0] * width if focal.ndim else focal * width
    K[1, 1] = focal[1] * height if focal.ndim else focal * width
    K[0, 2] = width / 2.0
    K[1, 2] = height / 2.0
    K[2, 2] = 1.0
    return K


def scale_intrinsics(K: np.ndarray, from_hw: tuple[int, int], to_hw: tuple[int, int]) -> np.ndarray:
    """Intrinsics of the same camera for an image resized from ``from_hw`` to ``to_hw`` (no crop).

    With pixel centres at +0.5 a resize by s maps u to s*u exactly, so fx and cx scale alike.
    """
    sy = to_hw[0] / from_hw[0]
    sx = to_hw[1] / from_hw[1]
    S = np.diag([sx, sy, 1.0]).astype(K.dtype)
    return S @ K


def invert_pose(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms ``[..., 4, 4]`` (``cam_from_world`` from ``world_from_cam``)."""
    R = T[..., :3, :3]
    t = T[..., :3, 3:]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3:] = -Rt @ t
    out[..., 3, 3] = 1.0
    return out


def rays_from_pixels(uv: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray):
    """Rays through pixel positions ``uv [N, 2]`` of a camera ``K [3,3]``, ``world_from_cam [4,4]``.

    Returns ``origins [N, 3]`` and ``directions [N, 3]``; directions are ``R K^-1 [u, v, 1]``, not
    normalised, so ``o + z d`` is the point at camera depth ``z``.
    """
    dtype = np.result_type(uv.dtype, K.dtype, world_from_cam.dtype)
    x = (uv[:, 0] - K[0, 2]) / K[0, 0]
    y = (uv[:, 1] - K[1, 2]) / K[1, 1]
    d_cam = np.stack([x, y, np.ones_like(x)], axis=-1).astype(dtype)
    directions = d_cam @ world_from_cam[:3, :3].T.astype(dtype)
    # A real (writable) array, not a broadcast view: callers may write into it.
    origins = np.repeat(world_from_cam[None, :3, 3].astype(dtype), directions.shape[0], axis=0)
    return origins, directions


def sample_depths(near: float, far: float, n_samples: int, n_rays: int = 1,
                  stratified: bool = False, rng: np.random.Generator | None = None,
                  dtype=np.float64) -> np.ndarray:
    """Camera depths ``[n_rays, S]`` in ``[near, far]``: bin centres, or one uniform draw per bin."""
    edges = np.linspace(near, far, n_samples + 1, dtype=np.float64)
    width = (far - near) / n_samples
    if stratified:
        rng = rng if rng is not None else np.random.default_rng()
        jitter = rng.random((n_rays, n_samples))
    else:
        jitter = np.full((n_rays, n_samples), 0.5)
    return (edges[:-1] + jitter * width).astype(dtype)


def project_points(points: np.ndarray, K: np.ndarray, cam_from_world: np.ndarray,
                   height: int, width: int):
    """Project world points ``[..., 3]`` into views ``K [3,3]``, ``cam_from_world [V, 4, 4]``.

    Returns ``uv [V, ..., 2]`` (pixels; finite, clipped for masked points), ``z [V, ...]`` camera
    depth, and ``valid [V, ...]`` (bool): z > DEPTH_EPS and 0 <= u < W and 0 <= v < H.
    """
    R_cam_from_world = cam_from_world[:, :3, :3]                 # [V, 3, 3]
    t_cam_from_world = cam_from_world[:, :3, 3]                  # [V, 3]
    flat = points.reshape(-1, 3)
    # Batched matmul, not einsum (which runs without BLAS here; docs/PERFORMANCE.md).
    cam = (np.matmul(flat, np.swapaxes(R_cam_from_world, -1, -2))
           + t_cam_from_world[:, None, :])                      # [V, N, 3] camera coordinates
    z = cam[..., 2]
    z_safe = np.where(z > DEPTH_EPS, z, DEPTH_EPS)
    u = K[0, 0] * cam[..., 0] / z_safe + K[0, 2]
    v = K[1, 1] * cam[..., 1] / z_safe + K[1, 2]
    valid = (z > DEPTH_EPS) & (u >= 0) & (u < width) & (v >= 0) & (v < height)
    # Clip so that points behind or far outside stay finite (they are masked).
    lim_u, lim_v = GRID_CLIP * width, GRID_CLIP * height
    u = np.clip(np.nan_to_num(u, nan=0.0), -lim_u, lim_u)
    v = np.clip(np.nan_to_num(v, nan=0.0), -lim_v, lim_v)
    V = cam_from_world.shape[0]
    shape = (V,) + points.shape[:-1]
    uv = np.stack([u, v], axis=-1).reshape(shape + (2,))
    return uv, z.reshape(shape), valid.reshape(shape)


def validity(uv: np.ndarray, z: np.ndarray, height: int, width: int) -> np.ndarray:
    """Validity weights ``[V, ...]`` in [0, 1] of ``project_points``' ``uv [V, ..., 2]`` and
    ``z [V, ...]``: 0 at or behind the camera plane (z <= DEPTH_EPS), else
    ``clip(1 - d / EDGE_FADE, 0, 1)`` with d the distance in pixels outside the image
    [0, W] x [0, H] (0 inside): 1 wherever ``project_points``' ``valid`` is True. The renderer's
    ``mask`` input (io_spec)."""
    return edge_validity(uv[..., 0], uv[..., 1], z, height, width)


def edge_validity(u: np.ndarray, v: np.ndarray, z: np.ndarray, height: int,
                  width: int) -> np.ndarray:
    """``validity`` of pixel positions given as ``u``, ``v`` and depths ``z``, each ``[V, ...]``
    (bit for bit)."""
    d = np.maximum(np.maximum(np.maximum(-u, u - width), np.maximum(-v, v - height)), 0.0)
    w = np.clip(1.0 - d / u.dtype.type(EDGE_FADE), 0.0, 1.0).astype(u.dtype)
    return np.where(z > DEPTH_EPS, w, u.dtype.type(0.0))


def pixels_to_grid(uv: np.ndarray, height: int, width: int) -> np.ndarray:
    """Pixel positions to normalised ``grid_sample`` coordinates (align_corners=False).

    The image's left edge u = 0 maps to -1 and its right edge u = W to +1; feature cell centres of
    an h x w map over the same image sit at patch centres.
    """
    scale = np.array([2.0 / width, 2.0 / height], dtype=uv.dtype)
    return np.clip(uv * scale - 1.0, -GRID_CLIP, GRID_CLIP)


def sample_bilinear(feature_map: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Bilinear sampling of ``feature_map [C, h, w]`` at ``grid [..., 2]`` (normalised x, y).

    Same semantics as ``torch.nn.functional.grid_sample(align_corners=False,
    padding_mode="border")``: the sample position is clamped to the border of the cell-centre
    lattice. Returns ``[..., C]`` (channel-last, what the renderer consumes).
    """
    C, h, w = feature_map.shape
    gx = ((grid[..., 0] + 1.0) * w - 1.0) / 2.0
    gy = ((grid[..., 1] + 1.0) * h - 1.0) / 2.0
    gx = np.clip(gx, 0.0, w - 1.0)
    gy = np.clip(gy, 0.0, h - 1.0)
    x0 = np.floor(gx).astype(np.int64)
    y0 = np.floor(gy).astype(np.int64)
    x1 = np.minimum(x0 + 1, w - 1)
    y1 = np.minimum(y0 + 1, h - 1)
    wx = (gx - x0)[..., None].astype(feature_map.dtype)
    wy = (gy - y0)[..., None].astype(feature_map.dtype)
    flat = feature_map.reshape(C, h * w).T                       # [h*w, C] channel-last gather
    f00 = flat[y0 * w + x0]
    f01 = flat[y0 * w + x1]
    f10 = flat[y1 * w + x0]
    f11 = flat[y1 * w + x1]
    return (f00 * (1 - wx) + f01 * wx) * (1 - wy) + (f10 * (1 - wx) + f11 * wx) * wy


def sample_bilinear_views(feature_maps: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """``sample_bilinear`` of each view's map: ``feature_maps [V, C, h, w]`` at ``grid [V, ..., 2]``
    -> ``[V, ..., C]``, bit for bit; the numpy twin of ``iris_train.geometry.sample_bilinear``.
    (``sample_taps(bilinear_taps(feature_maps), ...)``: the runtime builds the taps once per
    render and samples every call's views from them.)
    """
    if feature_maps.ndim != 4 or grid.shape[0] != feature_maps.shape[0] or grid.shape[-1] != 2:
        raise ValueError(f"expected feature_maps [V, C, h, w] and grid [V, ..., 2], got "
                         f"{feature_maps.shape} and {grid.shape}")
    return sample_taps(bilinear_taps(feature_maps), feature_maps.shape[2:], grid)


def bilinear_taps(feature_maps: np.ndarray) -> np.ndarray:
    """The gather table of ``sample_taps``: for every cell (y, x) of ``feature_maps [V, C, h, w]``
    the four values a bilinear sample in that cell reads, (y, x), (y, x + 1), (y + 1, x),
    (y + 1, x + 1), clamped at the last row and column as in ``sample_bilinear`` ->
    ``[V, 4, C, h * w]`` (4x the maps' memory)."""
    V, C, h, w = feature_maps.shape
    xs = np.minimum(np.arange(w) + 1, w - 1)
    ys = np.minimum(np.arange(h) + 1, h - 1)
    below = feature_maps[:, :, ys]
    taps = np.stack([feature_maps, feature_maps[..., xs], below, below[..., xs]], axis=1)
    return taps.reshape(V, 4, C, h * w)


def sample_taps(taps: np.ndarray, size: tuple[int, int], grid: np.ndarray,
                views: np.ndarray | None = None) -> np.ndarray:
    """``sample_bilinear`` of the maps of ``bilinear_taps`` (maps of ``size`` (h, w)) at ``grid
    [V', ..., 2]``, view ``views[k]`` (default k) at ``grid[k]`` -> ``[V', ..., C]``, bit for bit
    (float taps; integer taps, such as uint8 photos, are interpolated in float32).

    One gather of a cell's four taps per sample, channel-major (the weights broadcast along
    contiguous rows), instead of four gathers of C-value rows and arithmetic on ``[N, C]`` with a
    trailing broadcast, which numpy runs several times slower (``benchmarks/call_numpy.py``,
    docs/PERFORMANCE.md). The weights ``g - floor(g)`` are exact in the grid's dtype, the same
    values ``sample_bilinear`` computes.
    """
    h, w = size
    C = taps.shape[2]
    views = np.arange(grid.shape[0]) if views is None else views
    # Integer taps (uint8 photos) are interpolated in float32 with the same rule.
    dtype = taps.dtype if taps.dtype.kind == "f" else np.dtype(np.float32)
    out = np.empty(grid.shape[:-1] + (C,), dtype=dtype)
    for k, view in enumerate(views):
        gx = np.clip(((grid[k, ..., 0] + 1.0) * w - 1.0) / 2.0, 0.0, w - 1.0).reshape(-1)
        gy = np.clip(((grid[k, ..., 1] + 1.0) * h - 1.0) / 2.0, 0.0, h - 1.0).reshape(-1)
        fx, fy = np.floor(gx), np.floor(gy)
        wx = (gx - fx).astype(dtype)
        wy = (gy - fy).astype(dtype)
        f = taps[view].take(fy.astype(np.intp) * w + fx.astype(np.intp), axis=2)   # [4, C, N]
        s = (f[0] * (1 - wx) + f[1] * wx) * (1 - wy) + (f[2] * (1 - wx) + f[3] * wx) * wy
        out[k] = s.T.reshape(out.shape[1:])
    return out


def geometric_cue(points: np.ndarray, target_centre: np.ndarray, source_centres: np.ndarray,
                  eps: float = NORM_EPS, cue_eps: float = CUE_EPS) -> np.ndarray:
    """GNT-style 4-d cue ``Δ_k(x)`` for points ``[..., 3]`` and views ``source_centres [V, 3]``.

    With t = unit(target_centre - x) and s = unit(source_centre_k - x):
    ``[(t - s) / max(|t - s|, cue_eps), t . s]`` -> ``[..., V, 4]``. Equal centres (t = s) give
    ``[0, 0, 0, 1]``; a point on a camera centre gives a zero unit vector, never NaN.
    (``cue_from_vectors(*cue_vectors(...))``: the ray march keeps the vectors for view selection.)
    """
    return cue_from_vectors(*cue_vectors(points, target_centre, source_centres, eps), cue_eps)


def cue_vectors(points: np.ndarray, target_centre: np.ndarray, source_centres: np.ndarray,
                eps: float = NORM_EPS):
    """The directions the cue is made of, for points ``[..., 3]`` and views ``[V, 3]``:
    ``t`` = unit(target_centre - x) ``[..., 3]``, ``s`` = source_centre_k - x ``[..., V, 3]``
    (not normalised) and its norm floored at ``eps``, ``s_norm [..., V, 1]``."""
    target_centre = np.asarray(target_centre, dtype=points.dtype)
    t = target_centre - points
    t = t / np.maximum(_norm3(t), eps)
    s = source_centres.astype(points.dtype) - points[..., None, :]          # [..., V, 3]
    return t, s, np.maximum(_norm3(s), eps)


def cue_from_vectors(t: np.ndarray, s: np.ndarray, s_norm: np.ndarray,
                     cue_eps: float = CUE_EPS) -> np.ndarray:
    """``geometric_cue`` from ``cue_vectors``' output -> ``[..., V, 4]``."""
    s = s / s_norm
    out = np.empty(s.shape[:-1] + (4,), s.dtype)
    diff = np.subtract(t[..., None, :], s, out=out[..., :3])
    np.divide(diff, np.maximum(_norm3(diff), cue_eps), out=diff)
    out[..., 3:] = _dot3(t[..., None, :], s)
    return out


def cue_cosine(points: np.ndarray, target_centre: np.ndarray,
               source_centres: np.ndarray) -> np.ndarray:
    """The last entry of ``geometric_cue`` alone, ``t . s`` -> ``[V, ...]`` (view-major), bit for
    bit: the angular weighting of the colour blend needs only it (``colour.mean_colour``)."""
    t, s, s_norm = cue_vectors(points, target_centre, source_centres)
    cos = _dot3(t[..., None, :], s / s_norm)[..., 0]                      # [..., V]
    return np.moveaxis(cos, -1, 0)


def _dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(a * b).sum(-1, keepdims=True)`` over a last axis of 3, summed in the same order
    (bit for bit) without numpy's slow reduction over a short axis (the cue and the view
    alignment of a renderer call: ``benchmarks/call_numpy.py``, docs/PERFORMANCE.md)."""
    return a[..., 0:1] * b[..., 0:1] + a[..., 1:2] * b[..., 1:2] + a[..., 2:3] * b[..., 2:3]


def _norm3(x: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(x, axis=-1, keepdims=True)`` over a last axis of 3, bit for bit
    (``_dot3``)."""
    return np.sqrt(_dot3(x, x))


def cue_alignment(t: np.ndarray, s: np.ndarray, s_norm: np.ndarray) -> np.ndarray:
    """The cue's t . s from ``cue_vectors``' output -> ``[..., V]``, rounded as the runtime's
    view selection (``top_k``) has always rounded it: ``(s . t) / |s|``, where the cue's last
    entry is ``t . (s / |s|)``. The two differ in the last bit for about half of the points, which
    flips the per-point choice between nearly tied views; the selection keeps its own rounding so
    that ``top_k`` renders stay bit for bit what they were."""
    return _dot3(s, t[..., None, :])[..., 0] / s_norm[..., 0]


def is_rigid(T: np.ndarray, atol: float = RIGID_ATOL) -> bool:
    """True when ``T [4, 4]`` is finite with an orthonormal, det +1 rotation and last row [0,0,0,1],
    to ``atol`` (default: the boundary's one tolerance, ``validation.RIGID_ATOL``; the predicate of
    ``validation.check_world_from_cam``, which says what is wrong)."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    return bool(rigidity_error(T) <= atol)
