"""Camera geometry: the numpy runtime functions, their torch twins, and external oracles.

What is checked (docs/ARCHITECTURE.md, "Conventions"):

* twins: every ``iris_runtime.geometry`` function (and the numpy twins the runtime does not need,
  tests/np_geometry.py) equals its ``iris_train.geometry`` twin in float64 to 1e-10 on random
  inputs (and ``sample_bilinear_dense`` equals ``sample_bilinear``);
* oracles: projection vs OpenCV ``cv2.projectPoints``; bilinear sampling vs torch ``grid_sample``
  and SciPy ``ndimage.map_coordinates``; projection vs a float64 direct formula (hypothesis);
* round trips: pixel -> ray -> point -> pixel, pose inverse, intrinsics rescale, principal ray;
* edge cases: degenerate 6D rotations, points behind / on the camera plane / on image borders,
  the geometric cue at coincident centres;
* gradients: ``torch.autograd.gradcheck`` in float64.

Tests that need torch carry the ``torch`` marker and skip where torch is not installed, so the
numpy half also runs in the torch-free runtime environment.
"""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import ndimage

from iris_runtime import geometry as NG

from . import np_geometry as NPG          # numpy twins the runtime does not need
from .tolerances import f32_tol

try:
    import torch
    import torch.nn.functional as F

    from iris_train import geometry as TG
except ImportError:          # the torch-free runtime environment
    torch = None


def needs_torch(f):
    f = pytest.mark.torch(f)
    return pytest.mark.skipif(torch is None, reason="torch is not installed")(f)


TWIN_ATOL = 1e-10
SEEDS = [0, 1, 2]


# -- helpers ---------------------------------------------------------------------------------
def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniform random rotation (QR of a Gaussian matrix, sign-fixed, det +1)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 2] = -q[:, 2]
    return q


def random_pose(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    """A random rigid ``world_from_cam`` 4x4."""
    T = np.eye(4)
    T[:3, :3] = random_rotation(rng)
    T[:3, 3] = rng.normal(size=3) * scale
    return T


def random_K(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """Pinhole K with fx != fy and an off-centre principal point (zero skew)."""
    fx = rng.uniform(0.5, 2.0) * width
    fy = rng.uniform(0.5, 2.0) * height
    cx = rng.uniform(0.3, 0.7) * width
    cy = rng.uniform(0.3, 0.7) * height
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def points_seen_by(rng, K, world_from_cam, n, height, width, zmin=0.2, zmax=5.0, margin=0.5):
    """World points whose projection lies in ``[-margin W, (1 + margin) W] x ...`` at depth z."""
    u = rng.uniform(-margin * width, (1 + margin) * width, n)
    v = rng.uniform(-margin * height, (1 + margin) * height, n)
    z = rng.uniform(zmin, zmax, n)
    cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=-1)
    return cam @ world_from_cam[:3, :3].T + world_from_cam[:3, 3]


def orthonormality_error(R: np.ndarray) -> tuple[float, float]:
    R = np.asarray(R, dtype=np.float64)
    eye = np.eye(3)
    ortho = np.abs(np.swapaxes(R, -1, -2) @ R - eye).max()
    det = np.abs(np.linalg.det(R) - 1.0).max()
    return float(ortho), float(det)


def t64(a) -> "torch.Tensor":
    return torch.from_numpy(np.ascontiguousarray(np.asarray(a, dtype=np.float64)))


def n(t) -> np.ndarray:
    return t.detach().cpu().numpy()


def degenerate_6d_cases() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(123)
    a1 = rng.normal(size=3)
    return {
        "random": rng.normal(size=6),
        "near_parallel": np.concatenate([a1, a1 + 1e-9 * rng.normal(size=3)]),
        "parallel": np.concatenate([a1, 2.5 * a1]),
        "anti_parallel": np.concatenate([a1, -a1]),
        "axis_parallel": np.array([0.0, 0.0, 1.0, 0.0, 0.0, 3.0]),
        "near_zero": 1e-30 * rng.normal(size=6),
        "zero": np.zeros(6),
        "huge": 1e30 * rng.normal(size=6),
        "a1_zero": np.concatenate([np.zeros(3), rng.normal(size=3)]),
        "a2_zero": np.concatenate([a1, np.zeros(3)]),
        "tiny_a1_big_a2": np.concatenate([1e-20 * a1, rng.normal(size=3)]),
    }


DEGENERATE = degenerate_6d_cases()


# -- numpy == torch, float64, every function --------------------------------------------------
@needs_torch
@pytest.mark.parametrize("hw", [(1, 1), (3, 5), (8, 6)])
def test_twin_pixel_centres(hw):
    a = NPG.pixel_centres(*hw)
    b = n(TG.pixel_centres(*hw, dtype=torch.float64))
    assert a.shape == b.shape == (hw[0] * hw[1], 2)
    np.testing.assert_allclose(a, b, atol=TWIN_ATOL, rtol=0)
    # Row-major (u, v) = (j + 0.5, i + 0.5).
    np.testing.assert_array_equal(a[0], [0.5, 0.5])
    if hw[1] > 1:
        np.testing.assert_array_equal(a[1], [1.5, 0.5])
    np.testing.assert_array_equal(a[-1], [hw[1] - 0.5, hw[0] - 0.5])


@needs_torch
@pytest.mark.parametrize("seed", SEEDS)
def test_twin_intrinsics_and_scale(seed):
    rng = np.random.default_rng(seed)
    focal = rng.uniform(0.3, 3.0, 2)
    H, W = int(rng.integers(4, 200)), int(rng.integers(4, 200))
    K = NG.intrinsics_from_focal(focal, H, W)
    np.testing.assert_allclose(K, n(TG.intrinsics_from_focal(t64(focal), H, W)), atol=TWIN_ATOL, rtol=0)
    np.testing.assert_allclose(K, [[focal[0] * W, 0, W / 2], [0, focal[1] * H, H / 2], [0, 0, 1]],
                               atol=1e-12, rtol=0)
    to_hw = (int(rng.integers(4, 300)), int(rng.integers(4, 300)))
    Ks = NG.scale_intrinsics(K, (H, W), to_hw)
    np.testing.assert_allclose(Ks, n(TG.scale_intrinsics(t64(K), (H, W), to_hw)), atol=TWIN_ATOL, rtol=0)
    # A resize of a centred camera keeps the normalised focal and the centred principal point.
    np.testing.assert_allclose(Ks, NG.intrinsics_from_focal(focal, *to_hw), atol=1e-9, rtol=0)
    # One number: fx/W with square pixels (the epipolar solve's focal), bit for bit its K.
    f = float(focal[0])
    square = NG.intrinsics_from_focal(f, H, W)
    np.testing.assert_array_equal(square, [[f * W, 0, W / 2], [0, f * W, H / 2], [0, 0, 1]])
    twin = TG.intrinsics_from_focal(torch.tensor(f, dtype=torch.float64), H, W)
    np.testing.assert_allclose(square, n(twin), atol=TWIN_ATOL, rtol=0)


@needs_torch
@pytest.mark.parametrize("batch", [(), (5,), (2, 3)])
def test_twin_invert_and_compose(batch):
    rng = np.random.default_rng(len(batch))
    T = np.stack([random_pose(rng) for _ in range(int(np.prod(batch, dtype=int)))]).reshape(batch + (4, 4))
    U = np.stack([random_pose(rng) for _ in range(int(np.prod(batch, dtype=int)))]).reshape(batch + (4, 4))
    np.testing.assert_allclose(NG.invert_pose(T), n(TG.invert_pose(t64(T))), atol=TWIN_ATOL, rtol=0)
    np.testing.assert_allclose(NPG.compose(T, U), n(TG.compose(t64(T), t64(U))), atol=TWIN_ATOL, rtol=0)
    np.testing.assert_allclose(NG.invert_pose(T), np.linalg.inv(T), atol=1e-12, rtol=0)


@needs_torch
@pytest.mark.parametrize("case", sorted(DEGENERATE))
def test_twin_rotation_from_6d(case):
    a = DEGENERATE[case]
    np.testing.assert_allclose(NPG.rotation_from_6d(a), n(TG.rotation_from_6d(t64(a))),
                               atol=TWIN_ATOL, rtol=0)


@needs_torch
@pytest.mark.parametrize("shape", [(6,), (10, 6), (2, 3, 6)])
def test_twin_rotation_from_6d_batched(shape):
    a = np.random.default_rng(7).normal(size=shape)
    R = NPG.rotation_from_6d(a)
    assert R.shape == shape[:-1] + (3, 3)
    np.testing.assert_allclose(R, n(TG.rotation_from_6d(t64(a))), atol=TWIN_ATOL, rtol=0)


@needs_torch
@pytest.mark.parametrize("seed", SEEDS)
def test_twin_rays_from_pixels(seed):
    rng = np.random.default_rng(seed)
    H, W = 24, 40
    K, pose = random_K(rng, H, W), random_pose(rng)
    uv = rng.uniform(-5, 45, size=(33, 2))
    o, d = NG.rays_from_pixels(uv, K, pose)
    to, td = TG.rays_from_pixels(t64(uv), t64(K), t64(pose))
    assert o.shape == d.shape == (33, 3)
    np.testing.assert_allclose(o, n(to), atol=TWIN_ATOL, rtol=0)
    np.testing.assert_allclose(d, n(td), atol=TWIN_ATOL, rtol=0)


@needs_torch
def test_torch_rays_from_pixels_batched():
    rng = np.random.default_rng(8)
    K = random_K(rng, 10, 12)
    poses = np.stack([random_pose(rng) for _ in range(3)])
    uv = rng.uniform(0, 12, size=(3, 7, 2))
    o, d = TG.rays_from_pixels(t64(uv), t64(K), t64(poses))
    assert o.shape == d.shape == (3, 7, 3)
    for b in range(3):
        ob, db = NG.rays_from_pixels(uv[b], K, poses[b])
        np.testing.assert_allclose(n(o[b]), ob, atol=TWIN_ATOL, rtol=0)
        np.testing.assert_allclose(n(d[b]), db, atol=TWIN_ATOL, rtol=0)


@needs_torch
@pytest.mark.parametrize("near,far,S,R", [(0.1, 1.0, 64, 3), (0.5, 7.0, 1, 2), (2.0, 3.0, 5, 1)])
def test_twin_sample_depths_bin_centres(near, far, S, R):
    z = NG.sample_depths(near, far, S, R)
    zt = n(TG.sample_depths(near, far, S, R, dtype=torch.float64))
    assert z.shape == zt.shape == (R, S)
    np.testing.assert_allclose(z, zt, atol=TWIN_ATOL, rtol=0)
    centres = near + (np.arange(S) + 0.5) * (far - near) / S
    np.testing.assert_allclose(z, np.broadcast_to(centres, (R, S)), atol=1e-12, rtol=0)


def test_sample_depths_stratified_within_bins():
    near, far, S = 0.1, 1.0, 16
    z = NG.sample_depths(near, far, S, 50, stratified=True, rng=np.random.default_rng(0))
    lo = near + np.arange(S) * (far - near) / S
    assert np.all(z >= lo - 1e-12) and np.all(z <= lo + (far - near) / S + 1e-12)
    assert np.std(z - (lo + 0.5 * (far - near) / S)) > 0.01     # really jittered


@needs_torch
@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("lead", [(17,), (4, 6)])
def test_twin_project_points(seed, lead):
    rng = np.random.default_rng(seed)
    H, W, V = 20, 30, 3
    K = random_K(rng, H, W)
    cfw = np.stack([NG.invert_pose(random_pose(rng, 0.3)) for _ in range(V)])
    pts = rng.normal(size=lead + (3,)) * 2.0           # some behind, some outside, some inside
    uv, z, valid = NG.project_points(pts, K, cfw, H, W)
    tuv, tz, tvalid = TG.project_points(t64(pts), t64(K), t64(cfw), H, W)
    assert uv.shape == (V,) + lead + (2,) and z.shape == valid.shape == (V,) + lead
    np.testing.assert_allclose(uv, n(tuv), atol=TWIN_ATOL, rtol=0)
    np.testing.assert_allclose(z, n(tz), atol=TWIN_ATOL, rtol=0)
    np.testing.assert_array_equal(valid, n(tvalid))
    assert valid.any() and not valid.all()


@needs_torch
@pytest.mark.parametrize("seed", SEEDS)
def test_twin_pixels_to_grid(seed):
    rng = np.random.default_rng(seed)
    uv = rng.uniform(-40, 80, size=(5, 7, 2))
    g = NG.pixels_to_grid(uv, 20, 30)
    np.testing.assert_allclose(g, n(TG.pixels_to_grid(t64(uv), 20, 30)), atol=TWIN_ATOL, rtol=0)
    assert np.all(np.abs(g) <= NG.GRID_CLIP)
    # Image edges map to -1 and +1 (align_corners=False).
    np.testing.assert_allclose(NG.pixels_to_grid(np.array([[0.0, 0.0], [30.0, 20.0]]), 20, 30),
                               [[-1, -1], [1, 1]], atol=1e-15)


@needs_torch
@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("chw", [(3, 5, 7), (2, 1, 4), (4, 8, 8)])
def test_twin_sample_bilinear(seed, chw):
    rng = np.random.default_rng(seed)
    V = 2
    maps = rng.normal(size=(V,) + chw)
    grid = rng.uniform(-1.4, 1.4, size=(V, 6, 5, 2))
    ours = np.stack([NG.sample_bilinear(maps[k], grid[k]) for k in range(V)])
    tmaps, tgrid = t64(maps), t64(grid)
    twin = n(TG.sample_bilinear(tmaps, tgrid))
    dense = n(TG.sample_bilinear_dense(tmaps, tgrid))
    assert ours.shape == twin.shape == dense.shape == (V, 6, 5, chw[0])
    np.testing.assert_allclose(ours, twin, atol=TWIN_ATOL, rtol=0)
    np.testing.assert_allclose(dense, twin, atol=TWIN_ATOL, rtol=0)


@needs_torch
@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("target_shape", ["single", "per_ray"])
def test_twin_geometric_cue(seed, target_shape):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(4, 5, 3))
    src = rng.normal(size=(3, 3))
    tgt = rng.normal(size=3) if target_shape == "single" else rng.normal(size=(4, 1, 3))
    cue = NG.geometric_cue(pts, tgt, src)
    assert cue.shape == (4, 5, 3, 4)
    np.testing.assert_allclose(cue, n(TG.geometric_cue(t64(pts), t64(tgt), t64(src))),
                               atol=TWIN_ATOL, rtol=0)


@needs_torch
def test_twins_keep_float32():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(4, 6)).astype(np.float32)
    assert NPG.rotation_from_6d(a).dtype == np.float32
    assert TG.rotation_from_6d(torch.from_numpy(a)).dtype == torch.float32
    pts = rng.normal(size=(5, 3)).astype(np.float32)
    K = NG.intrinsics_from_focal(np.array([1.0, 1.0], np.float32), 8, 8)
    assert K.dtype == np.float32
    cfw = np.eye(4, dtype=np.float32)[None]
    uv, z, _ = NG.project_points(pts, K, cfw, 8, 8)
    assert uv.dtype == np.float32 and z.dtype == np.float32
    fmap = rng.normal(size=(2, 4, 4)).astype(np.float32)
    assert NG.sample_bilinear(fmap, NG.pixels_to_grid(uv[0], 8, 8)).dtype == np.float32


# -- external oracles ------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(5))
def test_projection_matches_opencv(seed):
    rng = np.random.default_rng(seed)
    H, W = 48, 64
    K = random_K(rng, H, W)
    assert K[0, 0] != K[1, 1] and K[0, 2] != W / 2
    world_from_cam = random_pose(rng, 2.0)
    cam_from_world = NG.invert_pose(world_from_cam)
    pts = points_seen_by(rng, K, world_from_cam, 200, H, W)   # in front, |uv| inside the clip range
    rvec, _ = cv2.Rodrigues(cam_from_world[:3, :3])
    tvec = cam_from_world[:3, 3].copy()
    ref, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), rvec, tvec, K, np.zeros(5))
    uv, z, valid = NG.project_points(pts, K, cam_from_world[None], H, W)
    np.testing.assert_allclose(uv[0], ref.reshape(-1, 2), atol=1e-6, rtol=0)
    inside = (ref[:, 0, 0] >= 0) & (ref[:, 0, 0] < W) & (ref[:, 0, 1] >= 0) & (ref[:, 0, 1] < H)
    np.testing.assert_array_equal(valid[0], inside)
    assert inside.any() and not inside.all()


def border_grid(h: int, w: int) -> np.ndarray:
    """Normalised positions: image edges, cell-centre borders, outside, corners, random."""
    xc = lambda c: (2.0 * c + 1.0) / w - 1.0      # cell centre c -> normalised x
    yc = lambda c: (2.0 * c + 1.0) / h - 1.0
    gx = [-1.0, 1.0, xc(0), xc(w - 1), -1.7, 1.9, -5.0, 5.0, 0.0, xc(0.5 * (w - 1))]
    gy = [-1.0, 1.0, yc(0), yc(h - 1), -1.7, 1.9, -5.0, 5.0, 0.0, yc(0.5 * (h - 1))]
    edge = np.array([(x, y) for x in gx for y in gy])
    rand = np.random.default_rng(h * 31 + w).uniform(-1.5, 1.5, size=(200, 2))
    return np.concatenate([edge, rand])


@needs_torch
@pytest.mark.parametrize("chw", [(3, 6, 9), (2, 8, 8), (1, 1, 5), (2, 3, 1)])
def test_bilinear_matches_grid_sample(chw):
    rng = np.random.default_rng(sum(chw))
    fmap = rng.normal(size=chw)
    grid = border_grid(*chw[1:])
    ref = F.grid_sample(t64(fmap)[None], t64(grid)[None, None], mode="bilinear",
                        padding_mode="border", align_corners=False)[0, :, 0].T.numpy()
    np.testing.assert_allclose(NG.sample_bilinear(fmap, grid), ref, atol=1e-6, rtol=0)
    np.testing.assert_allclose(n(TG.sample_bilinear_dense(t64(fmap)[None], t64(grid)[None]))[0], ref,
                               atol=1e-6, rtol=0)


@pytest.mark.parametrize("chw", [(3, 6, 9), (2, 8, 8), (1, 1, 5), (2, 3, 1)])
def test_bilinear_matches_scipy(chw):
    rng = np.random.default_rng(sum(chw) + 1)
    C, h, w = chw
    fmap = rng.normal(size=chw)
    grid = border_grid(h, w)
    x_cell = ((grid[:, 0] + 1.0) * w - 1.0) / 2.0
    y_cell = ((grid[:, 1] + 1.0) * h - 1.0) / 2.0
    ref = np.stack([ndimage.map_coordinates(fmap[c], [y_cell, x_cell], order=1, mode="nearest")
                    for c in range(C)], axis=-1)
    np.testing.assert_allclose(NG.sample_bilinear(fmap, grid), ref, atol=1e-6, rtol=0)


@pytest.mark.parametrize("chw", [(3, 64, 64), (3, 6, 9), (1, 1, 5)])
def test_bilinear_views_matches_scipy_grid_sample_and_the_single_view_sampler(chw):
    """``sample_bilinear_views`` (the runtime's sampler of the reference photos' RGB for
    explicit-colour models, full 64x64 resolution included): each view equals ``sample_bilinear``
    of that view bitwise, SciPy ``map_coordinates`` (order 1, nearest = border clamp) within
    1e-6, torch ``grid_sample(align_corners=False, padding_mode="border")`` on the [V, C, h, w]
    stack within 1e-6 (float64) and, in float32 as the runtime runs it, within the float32
    rounding of two samplers (below)."""
    rng = np.random.default_rng(sum(chw) + 7)
    C, h, w = chw
    V = 3
    maps = rng.random((V,) + chw)
    base = border_grid(h, w)
    grid = np.stack([np.roll(base, 37 * k, axis=0) for k in range(V)]).reshape(V, 4, -1, 2)
    ours = NG.sample_bilinear_views(maps, grid)
    assert ours.shape == (V, 4, grid.shape[2], C) and ours.dtype == np.float64
    for k in range(V):
        np.testing.assert_array_equal(ours[k], NG.sample_bilinear(maps[k], grid[k]))
        x_cell = ((grid[k, ..., 0] + 1.0) * w - 1.0) / 2.0
        y_cell = ((grid[k, ..., 1] + 1.0) * h - 1.0) / 2.0
        ref = np.stack([ndimage.map_coordinates(maps[k, c], [y_cell, x_cell], order=1,
                                                mode="nearest") for c in range(C)], axis=-1)
        np.testing.assert_allclose(ours[k], ref, atol=1e-6, rtol=0)
    maps32, grid32 = maps.astype(np.float32), grid.astype(np.float32)
    ours32 = NG.sample_bilinear_views(maps32, grid32)
    assert ours32.dtype == np.float32
    # Two float32 samplers on the same float32 inputs differ by the rounding of the sample
    # position ((g + 1) * w - 1) / 2 (3 roundings of values <= 2 max(h, w) pixels; a kernel
    # that fuses them into an FMA rounds them differently) times the maps' slope (values in
    # [0, 1): <= 1 per pixel), plus the interpolation's (8 roundings of values <= 1): 4.7e-5 at
    # 64 pixels (tests/tolerances.py). A tap off by one pixel moves a sample by ~0.3.
    tol32 = f32_tol(3, 2 * max(h, w)) + f32_tol(8)
    if torch is not None:
        # float32 against the same float32 inputs (a float32 grid moves a 64-pixel-wide sample
        # by up to 2e-6 px-values from the float64 one: the inputs' rounding, not the sampler's)
        for (m, g), got, tol in (((maps, grid), ours, 1e-6), ((maps32, grid32), ours32, tol32)):
            ref = F.grid_sample(torch.from_numpy(m), torch.from_numpy(g), mode="bilinear",
                                padding_mode="border", align_corners=False)       # [V, C, 4, N]
            np.testing.assert_allclose(got, ref.permute(0, 2, 3, 1).double().numpy(),
                                       atol=tol, rtol=0)
            np.testing.assert_allclose(got, n(TG.sample_bilinear(torch.from_numpy(m),
                                                                 torch.from_numpy(g))),
                                       atol=tol, rtol=0)
    with pytest.raises(ValueError, match="grid"):
        NG.sample_bilinear_views(maps, grid[:2])


def test_bilinear_hits_cell_values_at_cell_centres():
    fmap = np.arange(2 * 3 * 4, dtype=np.float64).reshape(2, 3, 4)
    i, j = np.meshgrid(np.arange(3), np.arange(4), indexing="ij")
    grid = np.stack([(2 * j + 1) / 4 - 1, (2 * i + 1) / 3 - 1], axis=-1)
    np.testing.assert_allclose(NG.sample_bilinear(fmap, grid), np.moveaxis(fmap, 0, -1), atol=1e-12)


# -- round trips -----------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(4))
def test_pixel_ray_point_pixel_round_trip(seed):
    rng = np.random.default_rng(seed)
    H, W = 30, 50
    K, pose = random_K(rng, H, W), random_pose(rng, 3.0)
    uv = np.concatenate([NPG.pixel_centres(H, W)[::37], rng.uniform(0, [W, H], size=(50, 2))])
    z = rng.uniform(0.1, 10.0, size=len(uv))
    o, d = NG.rays_from_pixels(uv, K, pose)
    pts = o + z[:, None] * d
    uv2, z2, valid = NG.project_points(pts, K, NG.invert_pose(pose)[None], H, W)
    np.testing.assert_allclose(uv2[0], uv, atol=1e-9, rtol=0)
    np.testing.assert_allclose(z2[0], z, atol=1e-9, rtol=0)
    assert valid.all()
    if torch is not None:
        to, td = TG.rays_from_pixels(t64(uv), t64(K), t64(pose))
        tuv, tz, _ = TG.project_points(to + t64(z)[:, None] * td, t64(K), TG.invert_pose(t64(pose))[None], H, W)
        np.testing.assert_allclose(n(tuv)[0], uv, atol=1e-9, rtol=0)
        np.testing.assert_allclose(n(tz)[0], z, atol=1e-9, rtol=0)


@pytest.mark.parametrize("seed", range(3))
def test_invert_pose_round_trip(seed):
    rng = np.random.default_rng(seed)
    T = np.stack([random_pose(rng, 5.0) for _ in range(6)])
    Ti = NG.invert_pose(T)
    for P in (NPG.compose(Ti, T), NPG.compose(T, Ti)):
        np.testing.assert_allclose(P, np.broadcast_to(np.eye(4), P.shape), atol=1e-12, rtol=0)
    np.testing.assert_allclose(NG.invert_pose(Ti), T, atol=1e-12, rtol=0)
    if torch is not None:
        P = TG.compose(TG.invert_pose(t64(T)), t64(T))
        np.testing.assert_allclose(n(P), np.broadcast_to(np.eye(4), P.shape), atol=1e-12, rtol=0)


@pytest.mark.parametrize("seed", range(3))
def test_scale_intrinsics_round_trip(seed):
    rng = np.random.default_rng(seed)
    K = random_K(rng, 37, 53)
    there = NG.scale_intrinsics(K, (37, 53), (120, 17))
    np.testing.assert_allclose(NG.scale_intrinsics(there, (120, 17), (37, 53)), K, atol=1e-12, rtol=0)
    # Pixel-centre convention: the image's own corners scale exactly (u -> s u).
    np.testing.assert_allclose(there[0, 2], K[0, 2] * 17 / 53, rtol=1e-14)
    if torch is not None:
        back = TG.scale_intrinsics(TG.scale_intrinsics(t64(K), (37, 53), (120, 17)), (120, 17), (37, 53))
        np.testing.assert_allclose(n(back), K, atol=1e-12, rtol=0)


@pytest.mark.parametrize("seed", range(3))
def test_principal_ray_is_optical_axis_and_rays_have_unit_depth(seed):
    rng = np.random.default_rng(seed)
    H, W = 21, 34
    K, pose = random_K(rng, H, W), random_pose(rng, 2.0)
    R, c = pose[:3, :3], pose[:3, 3]
    o, d = NG.rays_from_pixels(np.array([[K[0, 2], K[1, 2]]]), K, pose)
    np.testing.assert_allclose(d[0], R[:, 2], atol=1e-14)
    np.testing.assert_allclose(o[0], c, atol=1e-14)
    uv = rng.uniform(-10, 50, size=(100, 2))
    o, d = NG.rays_from_pixels(uv, K, pose)
    np.testing.assert_allclose(d @ R[:, 2], 1.0, atol=1e-12)
    np.testing.assert_allclose(o, np.broadcast_to(c, o.shape), atol=0)
    # Camera-frame direction is K^-1 [u, v, 1].
    d_cam = d @ R
    np.testing.assert_allclose(d_cam, np.c_[uv, np.ones(len(uv))] @ np.linalg.inv(K).T, atol=1e-12)
    if torch is not None:
        _, td = TG.rays_from_pixels(t64(uv), t64(K), t64(pose))
        np.testing.assert_allclose(n(td) @ R[:, 2], 1.0, atol=1e-12)


# -- rotation_from_6d ------------------------------------------------------------------------
def rotation_impls():
    impls = [("numpy", lambda a: NPG.rotation_from_6d(a))]
    if torch is not None:
        impls.append(("torch", lambda a: n(TG.rotation_from_6d(torch.from_numpy(np.ascontiguousarray(a))))))
    return impls


@pytest.mark.parametrize("dtype,tol", [(np.float64, 1e-12), (np.float32, 1e-5)])
@pytest.mark.parametrize("case", sorted(DEGENERATE))
def test_rotation_from_6d_orthonormal(case, dtype, tol):
    a = DEGENERATE[case].astype(dtype)
    for name, f in rotation_impls():
        R = f(a)
        assert R.dtype == dtype, name
        assert np.all(np.isfinite(R)), (name, case)
        ortho, det = orthonormality_error(R)
        assert ortho < tol and det < tol, (name, case, ortho, det)


@pytest.mark.parametrize("dtype,tol", [(np.float64, 1e-12), (np.float32, 1e-5)])
def test_rotation_from_6d_random_batch(dtype, tol):
    a = np.random.default_rng(3).normal(size=(500, 6)).astype(dtype)
    for name, f in rotation_impls():
        R = f(a)
        ortho, det = orthonormality_error(R)
        assert ortho < tol and det < tol, name
        # Column convention: the first column is a1 / |a1|.
        a1 = a[:, :3].astype(np.float64)
        np.testing.assert_allclose(R[..., 0], a1 / np.linalg.norm(a1, axis=-1, keepdims=True),
                                   atol=10 * tol)
        # The second column lies in the plane of a1, a2 on a2's side.
        assert np.all((R[..., 1] * a[:, 3:]).sum(-1) > 0), name


def test_rotation_from_6d_identity_and_idempotence():
    rng = np.random.default_rng(4)
    Rs = np.stack([random_rotation(rng) for _ in range(50)])
    six = np.concatenate([Rs[..., 0], Rs[..., 1]], axis=-1)
    for name, f in rotation_impls():
        np.testing.assert_array_equal(f(np.array([1.0, 0, 0, 0, 1, 0])), np.eye(3))
        np.testing.assert_allclose(f(six), Rs, atol=1e-12, rtol=0, err_msg=name)


@pytest.mark.parametrize("scale", [1e-30, 1e30, 1e-300, 1e300])
def test_rotation_from_6d_scale_free(scale):
    a = np.random.default_rng(5).normal(size=(20, 6))
    for name, f in rotation_impls():
        np.testing.assert_allclose(f(a * scale), f(a), atol=1e-12, rtol=0, err_msg=name)


# -- project_points edge cases ----------------------------------------------------------------
def edge_case_points(dtype):
    """Identity camera, K = [[4, 0, 4], [0, 4, 4]] on an 8x8 image: exact pixel positions."""
    pts = np.array([
        [0.0, 0.0, -1.0],      # behind
        [1.0, 0.0, 0.0],       # on the camera plane
        [0.0, 0.0, 1e-12],     # just in front, below DEPTH_EPS
        [0.0, 0.0, -1e-12],
        [0.0, 0.0, NG.DEPTH_EPS],   # exactly at the depth threshold (strict >)
        [-1.0, 0.0, 1.0],      # u = 0    -> valid
        [1.0, 0.0, 1.0],       # u = W    -> invalid
        [0.0, -1.0, 1.0],      # v = 0    -> valid
        [0.0, 1.0, 1.0],       # v = H    -> invalid
        [-1.0, -1.0, 1.0],     # corner (0, 0) -> valid
        [0.75, 0.75, 1.0],     # u = v = 7 -> valid
        [0.0, 0.0, 2e-6],      # centre, z just above DEPTH_EPS -> valid
        [1e300, -1e300, 1e-300],   # huge / tiny -> invalid, finite
        [3e38, 3e38, 1.0],     # far outside (overflows float32 products) -> invalid, finite
    ], dtype=np.float64)
    expected = np.array([0, 0, 0, 0, 0, 1, 0, 1, 0, 1, 1, 1, 0, 0], dtype=bool)
    if dtype == np.float32:
        pts[12] = [1e30, -1e30, 1e-30]
    return pts.astype(dtype), expected


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_project_points_edge_cases(dtype):
    pts, expected = edge_case_points(dtype)
    K = NG.intrinsics_from_focal(np.array([0.5, 0.5], dtype=dtype), 8, 8)
    cfw = np.eye(4, dtype=dtype)[None]
    with np.errstate(all="ignore"):
        results = [NG.project_points(pts, K, cfw, 8, 8)]
    if torch is not None:
        results.append(tuple(n(x) for x in TG.project_points(torch.from_numpy(pts), torch.from_numpy(K),
                                                             torch.from_numpy(cfw), 8, 8)))
    for uv, z, valid in results:
        np.testing.assert_array_equal(valid[0], expected)
        assert np.all(np.isfinite(uv))
        assert np.all(np.abs(uv[..., 0]) <= NG.GRID_CLIP * 8) and np.all(np.abs(uv[..., 1]) <= NG.GRID_CLIP * 8)
        np.testing.assert_array_equal(uv[0, 5], [0.0, 4.0])
        np.testing.assert_array_equal(uv[0, 6], [8.0, 4.0])
        np.testing.assert_array_equal(uv[0, 10], [7.0, 7.0])
        np.testing.assert_array_equal(z[0, :2], [-1.0, 0.0])


def test_is_rigid():
    rng = np.random.default_rng(11)
    T = random_pose(rng, 3.0)
    assert NG.is_rigid(T) and NG.is_rigid(np.eye(4)) and NG.is_rigid(T.astype(np.float32))
    reflect = T.copy()
    reflect[:3, 0] *= -1                      # orthonormal, det -1
    scaled = T.copy()
    scaled[:3, :3] *= 1.01
    bottom = T.copy()
    bottom[3, 0] = 0.1
    nan = T.copy()
    nan[0, 3] = np.nan
    inf = T.copy()
    inf[1, 1] = np.inf
    for bad in (reflect, scaled, bottom, nan, inf, T[:3], np.eye(3)):
        assert not NG.is_rigid(bad)


def test_nearest_rotation_matches_scipy_and_keeps_det_one():
    """``nearest_rotation`` (the one SVD projection of the runtime: validation's snap, the camera
    pictures, the epipolar solve) against SciPy's ``Rotation.from_matrix`` (Markley's nearest
    orthonormal matrix), batched, and a proper rotation for mirrored and singular input."""
    Rotation = pytest.importorskip("scipy.spatial.transform").Rotation
    rng = np.random.default_rng(12)
    R = Rotation.random(16, random_state=3).as_matrix()
    M = R + rng.normal(0.0, 0.05, R.shape)
    got = NG.nearest_rotation(M)
    np.testing.assert_allclose(got, Rotation.from_matrix(M).as_matrix(), atol=1e-10)
    np.testing.assert_allclose(NG.nearest_rotation(R), R, atol=1e-12)
    np.testing.assert_allclose(got[3], NG.nearest_rotation(M[3]), atol=0)
    mirrored = R[0] @ np.diag([1.0, 1.0, -1.0])
    for odd in (mirrored, np.zeros((3, 3)), np.diag([1.0, 1.0, 0.0])):
        out = NG.nearest_rotation(odd)
        assert np.all(np.isfinite(out))
        np.testing.assert_allclose(out.T @ out, np.eye(3), atol=1e-12)
        assert abs(np.linalg.det(out) - 1.0) < 1e-12


# -- geometric cue ---------------------------------------------------------------------------
def cue_by_hand(x, target, source):
    """Float64 loop reference of docs/ARCHITECTURE.md's cue for one point and one source view."""
    x, target, source = (np.asarray(v, dtype=np.float64) for v in (x, target, source))

    def unit(v):
        nv = math.sqrt(float(v @ v))
        return v / max(nv, NG.NORM_EPS)
    t, s = unit(target - x), unit(source - x)
    return np.r_[unit(t - s), t @ s]


def cue_impls():
    impls = [("numpy", NG.geometric_cue)]
    if torch is not None:
        impls.append(("torch", lambda p, t, s: n(TG.geometric_cue(t64(p), t64(t), t64(s)))))
    return impls


@pytest.mark.parametrize("seed", SEEDS)
def test_geometric_cue_against_hand_computation(seed):
    rng = np.random.default_rng(seed)
    pts = rng.normal(size=(30, 3))
    tgt = rng.normal(size=3)
    src = rng.normal(size=(4, 3))
    ref = np.array([[cue_by_hand(p, tgt, s) for s in src] for p in pts])
    for name, f in cue_impls():
        cue = f(pts, tgt, src)
        np.testing.assert_allclose(cue, ref, atol=1e-12, rtol=0, err_msg=name)
        np.testing.assert_allclose(np.linalg.norm(cue[..., :3], axis=-1), 1.0, atol=1e-12)
        # dot term = cos of the angle at x between the target and source directions.
        a, b = tgt - pts[:, None], src[None] - pts[:, None]
        cos = (a * b).sum(-1) / np.linalg.norm(a, axis=-1) / np.linalg.norm(b, axis=-1)
        np.testing.assert_allclose(cue[..., 3], cos, atol=1e-12)


def test_geometric_cue_degenerate_cases():
    rng = np.random.default_rng(9)
    tgt = rng.normal(size=3)
    other = rng.normal(size=3)
    pts = np.concatenate([rng.normal(size=(10, 3)), [other], [tgt]])   # a point on each centre
    src = np.stack([tgt.copy(), other])
    for name, f in cue_impls():
        cue = f(pts, tgt, src)
        assert np.all(np.isfinite(cue)), name
        # Equal target and source centres: [0, 0, 0, 1] (the point on the centre: [0, 0, 0, 0]).
        np.testing.assert_allclose(cue[:-1, 0], np.broadcast_to([0, 0, 0, 1.0], (11, 4)), atol=1e-12)
        np.testing.assert_array_equal(cue[-1, 0], [0, 0, 0, 0])
        # Point on source centre 1: s = 0 -> [t, 0]; point on the target centre: t = 0 -> [-s, 0].
        t_dir = (tgt - other) / np.linalg.norm(tgt - other)
        np.testing.assert_allclose(cue[10, 1], np.r_[t_dir, 0.0], atol=1e-12)
        np.testing.assert_allclose(cue[11, 1], np.r_[-(other - tgt) / np.linalg.norm(other - tgt), 0.0],
                                   atol=1e-12)
        norms = np.linalg.norm(cue[..., :3], axis=-1)
        assert np.all(np.isclose(norms, 1.0, atol=1e-12) | (norms == 0.0)), name


# -- gradients (float64 gradcheck) ------------------------------------------------------------
@needs_torch
def test_gradcheck_rotation_from_6d():
    a = torch.randn(5, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(0),
                    requires_grad=True)
    assert torch.autograd.gradcheck(TG.rotation_from_6d, (a,))


@needs_torch
def test_gradcheck_rays_from_pixels():
    rng = np.random.default_rng(0)
    K = t64(random_K(rng, 20, 30)).requires_grad_()
    pose = t64(random_pose(rng)).requires_grad_()
    uv = t64(rng.uniform(0, 30, size=(6, 2))).requires_grad_()
    assert torch.autograd.gradcheck(lambda u, k, p: TG.rays_from_pixels(u, k, p), (uv, K, pose))


@needs_torch
def test_gradcheck_project_points():
    rng = np.random.default_rng(1)
    H, W = 20, 30
    K = random_K(rng, H, W)
    pose = random_pose(rng)
    pts = t64(points_seen_by(rng, K, pose, 8, H, W)).requires_grad_()
    cfw = TG.invert_pose(t64(pose)[None]).detach().requires_grad_()
    assert torch.autograd.gradcheck(lambda p, c: TG.project_points(p, t64(K), c, H, W)[0], (pts, cfw))


@needs_torch
def test_gradcheck_geometric_cue():
    g = torch.Generator().manual_seed(2)
    pts = torch.randn(4, 3, 3, dtype=torch.float64, generator=g, requires_grad=True)
    tgt = torch.randn(3, dtype=torch.float64, generator=g, requires_grad=True)
    src = torch.randn(2, 3, dtype=torch.float64, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(TG.geometric_cue, (pts, tgt, src))


@needs_torch
def test_gradcheck_sample_bilinear_dense():
    rng = np.random.default_rng(3)
    V, C, h, w = 2, 2, 3, 4
    maps = t64(rng.normal(size=(V, C, h, w))).requires_grad_()
    # Cell coordinates strictly inside cells (fractional part in [0.2, 0.8]) and inside the lattice.
    cx = rng.integers(0, w - 1, size=(V, 5)) + rng.uniform(0.2, 0.8, size=(V, 5))
    cy = rng.integers(0, h - 1, size=(V, 5)) + rng.uniform(0.2, 0.8, size=(V, 5))
    grid = np.stack([(2 * cx + 1) / w - 1, (2 * cy + 1) / h - 1], axis=-1)
    grid = t64(grid).requires_grad_()
    assert torch.autograd.gradcheck(TG.sample_bilinear_dense, (maps, grid))


# -- property test: projection vs a float64 direct formula ------------------------------------
def _quaternion_rotation(q):
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


finite = dict(allow_nan=False, allow_infinity=False)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    quat=st.lists(st.floats(-1, 1, **finite), min_size=4, max_size=4).filter(
        lambda q: np.linalg.norm(q) > 0.1),
    t=st.lists(st.floats(-10, 10, **finite), min_size=3, max_size=3),
    fn=st.tuples(st.floats(0.3, 3.0), st.floats(0.3, 3.0)),
    cn=st.tuples(st.floats(0.2, 0.8), st.floats(0.2, 0.8)),
    hw=st.tuples(st.integers(1, 512), st.integers(1, 512)),
    cam_pts=st.lists(st.tuples(st.floats(-1.15, 1.15), st.floats(-1.15, 1.15),
                               st.floats(1e-3, 1e3)), min_size=1, max_size=20),
)
def test_projection_property_direct_formula(quat, t, fn, cn, hw, cam_pts):
    H, W = hw
    R = _quaternion_rotation(quat)
    t = np.asarray(t)
    cam_from_world = np.eye(4)
    cam_from_world[:3, :3], cam_from_world[:3, 3] = R, t
    K = np.array([[fn[0] * W, 0, cn[0] * W], [0, fn[1] * H, cn[1] * H], [0, 0, 1.0]])
    # Points in front of the camera, generated in camera space as (normalised image pos, depth)
    # and placed in the world with the exact inverse; |uv| stays inside the clip range.
    c = np.array(cam_pts)
    xyz_cam = np.stack([c[:, 0] * c[:, 2] * W / K[0, 0], c[:, 1] * c[:, 2] * H / K[1, 1], c[:, 2]], -1)
    x = (xyz_cam - t) @ R           # R^T (X - t)
    uv, z, valid = NG.project_points(x, K, cam_from_world[None], H, W)
    # Direct formula K (R x + t) / z, in float64, in a different order of operations.
    X = np.array([R @ xi + t for xi in x])
    p = np.array([K @ Xi for Xi in X])
    ref = p[:, :2] / p[:, 2:3]
    # Tolerance from conditioning: both sides commit O(eps (|R||x| + |t|)) absolute errors in the
    # camera coordinates X; u = fx X/Z + cx amplifies them by fx/Z (1 + |X, Y|/Z); then O(eps |u|).
    eps = np.finfo(np.float64).eps
    delta = 8 * eps * (np.linalg.norm(x, axis=-1) + np.linalg.norm(t))
    fmax = max(K[0, 0], K[1, 1])
    Zc = X[:, 2]
    amp = fmax / Zc * (1.0 + np.abs(X[:, :2]).max(-1) / Zc)
    tol = delta * amp + 8 * eps * (np.abs(ref).max(-1) + max(W, H)) + 1e-12
    err = np.abs(uv[0] - ref).max(-1)
    assert np.all(err <= tol), (err, tol)
    np.testing.assert_allclose(z[0], Zc, atol=0, rtol=1e-9)
    # Validity: equals the image test wherever the point is clearly away from the borders.
    inside = (ref[:, 0] >= 0) & (ref[:, 0] < W) & (ref[:, 1] >= 0) & (ref[:, 1] < H)
    far_from_border = np.minimum.reduce([np.abs(ref[:, 0]), np.abs(ref[:, 0] - W),
                                         np.abs(ref[:, 1]), np.abs(ref[:, 1] - H)]) > 2 * tol
    np.testing.assert_array_equal(valid[0][far_from_border], inside[far_from_border])


def test_geometric_cue_is_continuous_where_target_and_source_centres_meet():
    """Rendering exactly at (or 1e-8 away from) an input camera must not flip the cue's direction."""
    rng = np.random.default_rng(11)
    centre = rng.normal(size=3)
    pts = centre + rng.normal(size=(50, 3))
    for name, f in cue_impls():
        at = f(pts, centre, centre[None])
        for _ in range(5):
            near = f(pts, centre + rng.normal(size=3) * 1e-8, centre[None])
            # Lipschitz: |Δcue| <= |Δ(t - s)| / CUE_EPS, with |Δ(t - s)| ~ 1e-8 / |x - c|.
            assert np.abs(near - at).max() < 1e-8 / NG.CUE_EPS * 10, name
