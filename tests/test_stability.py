"""Numerical stability on stiff and extreme cases (see STABILITY.md for each case and its handling).

Three layers, each against a float64 reference where one exists:

* the numpy geometry as the runtime runs it (float32), property-based (hypothesis) against a float64
  reference, with tolerances derived from the conditioning of each quantity (below), not tuned;
* ``IrisRuntime`` renders of hand-built scenes (camera planes, grazing rays, equal centres, image
  borders, extreme focal lengths and scales, poses far outside the depth range, 1 and 32 views):
  the renderer's inputs are recorded and compared with a float64 reference of docs/ARCHITECTURE.md's
  formulas; outputs are finite, depth weights sum to 1 within 1e-5;
* the ONNX graphs against the torch model run in float64 (``@pytest.mark.torch``): constant,
  black, white and noise images; large logits; every view masked; degenerate 6D rotations in the
  camera head.

Plus determinism (bitwise across calls; across thread counts up to the encoder's and the
renderer's float32 rounding, tests/tolerances.py) and the 8-thread load test.

The stiff-scene renders, constant images and determinism also run on an explicit-colour model
(``stiff``: conftest's random ``tiny-rgb`` export), whose renderer calls carry the reference RGB
sampled in numpy; the recorded colours are checked against a float64 bilinear sampling of the
photos at the reference projections (tolerance: the projection's, times the photos' Lipschitz
bound of 1 per pixel per axis).

Tolerances. u = 2^-24 is float32's unit roundoff. A float32 dot product of length 3 errs by at
most ~3u times the sum of the absolute terms, and every float64 input is first rounded to float32
(another u relative), so camera coordinates X = R x + t carry |dX| <= 8u (|x| + |t|) (we use 16u
for the ray points, which go through one more product and sum). The pixel u = fx X/Z + cx then
errs by fx/Z (|dX| + |X/Z| |dZ|) + 4u (|u| + W). Mask bits are compared away from their
boundaries only (|Z - DEPTH_EPS| or the distance to an image border above the tolerance).
"""
from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from iris_runtime import IrisRuntime, Scene
from iris_runtime import geometry as G
from iris_runtime import runtime as R

from . import np_geometry as NPG
from .tolerances import encoder_tol, f32_tol, render_tol

try:
    from hypothesis import HealthCheck, settings
    from hypothesis import given as _given
    from hypothesis import strategies as st
    HAVE_HYPOTHESIS = True
except ImportError:                    # the runtime-only environment has no hypothesis
    HAVE_HYPOTHESIS = False

U32 = 2.0 ** -24                        # float32 unit roundoff
F32 = np.float32

#: A float32 rotation from rotation_from_6d is orthonormal with det +1 up to its rounding: the
#: longest chain is b3 = b1 x b2 after two Gram-Schmidt passes (scaling, two norms of 3 terms
#: and a square root each, two projections of 3 terms, the divisions, the cross product): ~32
#: roundings of values <= 1 (tests/tolerances.py: 1.7e-6; the former literal 1e-6 was below the
#: worst case of this chain). A non-orthonormal output (a skipped normalisation or projection)
#: is off by ~1e-1.
ROTATION_TOL = f32_tol(32)


def given(**strategies):
    return _given(**strategies) if HAVE_HYPOTHESIS else (lambda f: f)


def needs_hypothesis(f):
    if HAVE_HYPOTHESIS:
        return f

    def skipped():                      # no parameters: nothing for pytest to resolve
        pytest.skip("hypothesis not installed")
    skipped.__name__ = f.__name__
    return skipped


# ----------------------------------------------------------------------------------------------
# Helpers
# ----------------------------------------------------------------------------------------------

def rotation(axis, angle) -> np.ndarray:
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    Kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * Kx + (1 - np.cos(angle)) * Kx @ Kx


def pose(R=np.eye(3), t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


def quaternion_rotation(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def f32(a) -> np.ndarray:
    """a rounded to float32 and back: the exact input the float32 code sees."""
    return np.asarray(a, np.float64).astype(F32).astype(np.float64)


class Recorder:
    """Wraps an ONNX Runtime session: records every renderer feed and output."""

    def __init__(self, session):
        self.session = session
        self.calls = []

    def run(self, names, feed):
        out = self.session.run(names, feed)
        self.calls.append(({k: np.array(v) for k, v in feed.items()}, [np.array(o) for o in out]))
        return out

    def __getattr__(self, name):
        return getattr(self.session, name)


def recording_runtime(model_dir, **kwargs) -> tuple[IrisRuntime, Recorder]:
    rt = IrisRuntime(model_dir, threads=1, **kwargs)
    rec = Recorder(rt._session("renderer"))
    rt._sessions["renderer"] = rec
    return rt, rec


@pytest.fixture(scope="module")
def rt(model_dir) -> IrisRuntime:
    return IrisRuntime(model_dir, threads=1)


@pytest.fixture(scope="module")
def maps(rt) -> np.ndarray:
    """Real field maps of 32 noise images (the encoder's output, so of the model's statistics)."""
    rng = np.random.default_rng(5)
    scene = rt.encode([rng.integers(0, 256, (*rt.image_size, 3), dtype=np.uint8)
                       for _ in range(32)])
    return scene.field_maps


@pytest.fixture(scope="module", params=["tiny", "tiny-rgb"])
def stiff(request):
    """(model_dir, runtime, field maps, photos) of the 32 noise images of ``maps``: the tiny
    model (photos None: it never reads them) and its explicit-colour twin."""
    if request.param == "tiny":
        return (request.getfixturevalue("model_dir"), request.getfixturevalue("rt"),
                request.getfixturevalue("maps"), None)
    model_dir = request.getfixturevalue("rgb_model_dir")
    runtime = IrisRuntime(model_dir, threads=1)
    rng = np.random.default_rng(5)
    scene = runtime.encode([rng.integers(0, 256, (*runtime.image_size, 3), dtype=np.uint8)
                            for _ in range(32)])
    return model_dir, runtime, scene.field_maps, scene.reference_images


def make_scene(maps, poses, focal=(1.0, 1.0), size=(64, 64), images=None) -> Scene:
    poses = np.asarray(poses, float)
    focal = np.asarray(focal, float)
    return Scene(maps[:len(poses)], poses, focal, G.intrinsics_from_focal(focal, *size), size,
                 reference_images=None if images is None else images[:len(poses)])


# ----------------------------------------------------------------------------------------------
# Float64 reference of one render's geometry (docs/ARCHITECTURE.md, "Conventions", computed differently)
# ----------------------------------------------------------------------------------------------

def reference_geometry(scene: Scene, world_from_cam, K_out, height, width, near, far, S):
    """Float64: points [N, S, 3], camera coords Xk [V, N, S, 3], uv [V, N, S, 2], validity weights
    ``valid`` (geometry.validity's formula), cues
    [N, S, V, 4], and the per-point tolerances of points, uv and cues for the float32 runtime."""
    T = np.asarray(world_from_cam, float)
    Rt, o = T[:3, :3], T[:3, 3]
    j, i = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    uv_t = np.stack([j.ravel(), i.ravel()], -1)
    d_cam = np.stack([(uv_t[:, 0] - K_out[0, 2]) / K_out[0, 0],
                      (uv_t[:, 1] - K_out[1, 2]) / K_out[1, 1], np.ones(len(uv_t))], -1)
    d = d_cam @ Rt.T
    z = near + (np.arange(S) + 0.5) * (far - near) / S
    x = o + z[None, :, None] * d[:, None, :]                                  # [N, S, 3]
    dx = 16 * U32 * (np.abs(o).max() + z[None, :, None] * np.abs(d)[:, None, :].max(-1, keepdims=True)
                     * (1 + np.abs(d_cam[:, None, :2]).max(-1, keepdims=True)))[..., 0]
    Hm, Wm = scene.image_size
    Kr = scene.K
    uv, valid, Xs, du, dX_all = [], [], [], [], []
    for Tk in scene.world_from_cam:
        Rk, ck = Tk[:3, :3], Tk[:3, 3]
        X = (x - ck) @ Rk                                                     # R^T (x - c)
        dX = dx + 8 * U32 * (np.abs(x).max(-1) + np.abs(ck).max())
        Z = X[..., 2]
        Zs = np.where(np.abs(Z) > 0, np.abs(Z), np.inf)
        u = Kr[0, 0] * X[..., 0] / np.where(Z != 0, Z, 1) + Kr[0, 2]
        v = Kr[1, 1] * X[..., 1] / np.where(Z != 0, Z, 1) + Kr[1, 2]
        ratio = np.abs(X[..., :2]).max(-1) / Zs
        tol = max(Kr[0, 0], Kr[1, 1]) / Zs * dX * (1 + ratio) + 4 * U32 * (np.abs(u) + np.abs(v)
                                                                            + max(Hm, Wm))
        uv.append(np.stack([u, v], -1))
        outside = np.maximum.reduce([-u, u - Wm, -v, v - Hm, np.zeros_like(u)])   # pixels
        valid.append(np.where(Z > G.DEPTH_EPS, np.clip(1 - outside / G.EDGE_FADE, 0, 1), 0.0))
        Xs.append(X)
        du.append(tol)
        dX_all.append(dX)
    Xs, uv, valid, du, dX_all = map(np.stack, (Xs, uv, valid, du, dX_all))
    # Cues, docs/ARCHITECTURE.md: t = unit(o - x), s = unit(c - x): [(t - s) / max(|t - s|, CUE_EPS), t.s].
    tv = o - x
    nt = np.linalg.norm(tv, axis=-1, keepdims=True)
    t = tv / np.maximum(nt, G.NORM_EPS)
    sv = scene.world_from_cam[None, None, :, :3, 3] - x[:, :, None]
    ns = np.linalg.norm(sv, axis=-1, keepdims=True)
    s = sv / np.maximum(ns, G.NORM_EPS)
    diff = t[:, :, None] - s
    nd = np.linalg.norm(diff, axis=-1, keepdims=True)
    cue = np.concatenate([diff / np.maximum(nd, G.CUE_EPS), (t[:, :, None] * s).sum(-1,
                                                                                 keepdims=True)], -1)
    scale = np.abs(o).max() + np.abs(scene.world_from_cam[:, :3, 3]).max() + np.abs(x).max(-1)
    dt = 4 * (dx + 4 * U32 * scale)[..., None] / np.maximum(nt[..., 0], 1e-300)[..., None]
    ds = 4 * (dx + 4 * U32 * scale)[..., None] / np.maximum(ns[..., 0], 1e-300)
    dcue = 2 * (dt + ds) / np.maximum(nd[..., 0], G.CUE_EPS) + 8 * U32
    return dict(points=x, dpoints=dx, X=Xs, dX=dX_all, uv=uv, duv=du, valid=valid, cue=cue,
                dcue=np.minimum(dcue, np.inf), d=d)


def check_feed(rec: Recorder, ref: dict, scene: Scene, S: int):
    """The runtime's (cull=False: every call holds all views and samples, rays in order)
    renderer inputs against the float64 reference."""
    feeds = [c[0] for c in rec.calls]
    feed = {k: np.concatenate([f[k] for f in feeds], axis=0 if k in ("positions", "directions")
                              else 1) for k in feeds[0] if k != "field_maps"}
    rgb = np.concatenate([c[1][0] for c in rec.calls])
    weights = np.concatenate([c[1][1] for c in rec.calls])
    V = scene.num_views
    N = ref["points"].shape[0]
    assert feed["mask"].shape == (V, N, S)
    for k in ("grid", "cues", "positions", "directions"):
        assert np.all(np.isfinite(feed[k])), k
    assert np.all(np.isfinite(rgb)) and np.all(np.isfinite(weights))
    # Sample positions.
    err = np.abs(feed["positions"] - ref["points"]).max(-1)
    assert np.all(err <= ref["dpoints"] + 1e-30), (err.max(), ref["dpoints"].max())
    # Validity weights: continuous in (u, v) with slope 1 / EDGE_FADE, so within the projection's
    # tolerance over EDGE_FADE (+ float32 rounding of the weight) away from the depth epsilon.
    Hm, Wm = scene.image_size
    Z, dX, uv, duv = ref["X"][..., 2], ref["dX"], ref["uv"], ref["duv"]
    assert feed["mask"].dtype == np.float32
    clear = np.abs(Z - G.DEPTH_EPS) > dX
    werr = np.abs(feed["mask"] - ref["valid"])
    wtol = duv / G.EDGE_FADE + 4 * U32
    assert np.all(werr[clear] <= wtol[clear]), (werr[clear].max(), wtol[clear].min())
    # Grid where valid: |d grid| = 2 |d uv| / size.
    both = (ref["valid"] > 0) & (feed["mask"] > 0)
    grid_ref = np.stack([2 * uv[..., 0] / Wm - 1, 2 * uv[..., 1] / Hm - 1], -1)
    gerr = np.abs(feed["grid"] - grid_ref).max(-1)
    gtol = 2 * duv / min(Hm, Wm) + 4 * U32
    assert np.all(gerr[both] <= gtol[both]), (gerr[both].max(), gtol[both].min())
    assert np.all(np.abs(feed["grid"]) <= G.GRID_CLIP)
    if "colours" in feed:        # explicit colour: the photos at the projections, float64 reference
        photos = scene.reference_images[scene.image_index].astype(np.float64)
        assert feed["colours"].shape == (V, N, S, 3) and feed["colours"].dtype == np.float32
        assert np.all((feed["colours"] >= 0) & (feed["colours"] <= 1))
        want = G.sample_bilinear_views(photos, grid_ref)
        cerr = np.abs(feed["colours"] - want).max(-1)
        # Photos in [0, 1]: 1 per pixel per axis at most, times the position's error: the
        # projection's (duv) plus float32's grid -> pixel ((g + 1) * w - 1) / 2 (3 roundings of
        # values <= 2 max(H, W)); then the interpolation's own float32 rounding (8 roundings of
        # values <= 1: the weights, 4 products, 3 sums). A neighbouring pixel's colour is off
        # by up to 1.
        pos = duv + f32_tol(3, 2 * max(Hm, Wm))
        ctol = 2 * pos + f32_tol(8)
        assert np.all(cerr[both] <= ctol[both]), (cerr[both].max(), ctol[both].min())
    # Cues (view-major in the feed).
    cue = np.moveaxis(feed["cues"], 0, 2)
    cerr = np.abs(cue - ref["cue"]).max(-1)
    assert np.all(cerr <= ref["dcue"]), (cerr.max(), cerr[cerr > ref["dcue"]][:5])
    # Depth weights: a distribution over the valid samples of every ray that has one, else 0.
    live = (feed["mask"] > 0).any(0).any(-1)
    np.testing.assert_allclose(weights[live].sum(-1), 1.0, rtol=0, atol=1e-5)
    assert np.all(weights[~(feed["mask"] > 0).any(0)] == 0)
    return feed, rgb, weights


def render_and_check(model_dir, scene, target, K_out, hw, **kw):
    rt, rec = recording_runtime(model_dir, cull=False)
    H, W = hw
    # The exact march: its feed is what the float64 reference checks (two scales, the default
    # above the model's size, have tests of their own in tests/test_colour.py).
    res = rt.render(scene, target, height=H, width=W, intrinsics=K_out, depth=True,
                    quality="exact")
    assert np.all(np.isfinite(res.image_float)) and np.all(np.isfinite(res.depth))
    ref = reference_geometry(scene, target, K_out, H, W, rt.near, rt.far, rt.samples)
    feed, rgb, weights = check_feed(rec, ref, scene, rt.samples)
    # depth = sum(weights * z): weights summing to 1 up to the renderer's float32 rounding
    # (tests/tolerances.py), 1.7e-5 here; a depth outside [near, far] by a bin is off by 0.014.
    tol = render_tol(rt.manifest.config, scene.num_views, rt.far)
    assert np.all((res.depth == 0) | ((res.depth >= rt.near - tol) & (res.depth <= rt.far + tol)))
    # The culled render (the default) agrees with the unculled one up to the renderer's float32
    # rounding (culling drops masked samples and views: shorter sums); a dropped valid sample
    # moves pixels by > 1e-3.
    culled = IrisRuntime(model_dir, threads=1).render(scene, target, height=H, width=W,
                                                      intrinsics=K_out, depth=True,
                                                      quality="exact")
    np.testing.assert_allclose(culled.image_float, res.image_float, rtol=0, atol=tol)
    np.testing.assert_allclose(culled.depth, res.depth, rtol=0, atol=tol)
    return res, feed, ref


# ----------------------------------------------------------------------------------------------
# 1. Geometry, property-based: float32 (as the runtime runs it) vs a float64 reference
# ----------------------------------------------------------------------------------------------

if HAVE_HYPOTHESIS:
    finite = dict(allow_nan=False, allow_infinity=False)
    quats = st.lists(st.floats(-1, 1, **finite), min_size=4, max_size=4).filter(
        lambda q: np.linalg.norm(q) > 0.1)
    log_scale = st.floats(-6, 6)                 # translations of 1e-6 .. 1e6
    log_focal = st.floats(np.log10(0.05), np.log10(50.0))     # fx/W of 0.05 .. 50
    prop = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
else:                                            # placeholders so the decorators below parse

    class _St:
        def __getattr__(self, name):
            return lambda *a, **k: None
    st = _St()
    quats = log_scale = log_focal = None

    def prop(f):
        return f


@needs_hypothesis
@prop
@given(q=quats, centre=st.lists(st.floats(-1, 1), min_size=3, max_size=3), lscale=log_scale,
       lfx=log_focal, lfy=log_focal, hw=st.tuples(st.integers(1, 256), st.integers(1, 256)),
       cam=st.lists(st.tuples(st.floats(-1.3, 1.3), st.floats(-1.3, 1.3), st.floats(-3, 3)),
                    min_size=1, max_size=16))
def test_projection_float32_vs_float64(q, centre, lscale, lfx, lfy, hw, cam):
    """project_points in float32 at extreme focal lengths and scene scales: pixel positions within
    the conditioning bound, depths within 8u relative, mask equal away from its boundaries, and
    validity weights within the pixel bound over EDGE_FADE everywhere."""
    H, W = hw
    scale = 10.0 ** lscale
    Rw = quaternion_rotation(q)                               # world_from_cam rotation
    c = np.asarray(centre) * scale
    fx, fy = 10 ** lfx * W, 10 ** lfy * H
    K = np.array([[fx, 0, W / 2], [0, fy, H / 2], [0, 0, 1.0]])
    c_ = np.array(cam)
    Z = 10.0 ** c_[:, 2] * scale                              # depths 1e-3 .. 1e3 x scale
    Xc = np.stack([c_[:, 0] * Z * (W / 2) / fx, c_[:, 1] * Z * (H / 2) / fy, Z], -1)
    x = c + Xc @ Rw.T                                          # world points
    cfw = G.invert_pose(pose(Rw, c))
    x32, K32, cfw32 = x.astype(F32), K.astype(F32), cfw.astype(F32)
    uv, z, valid = G.project_points(x32, K32, cfw32[None], H, W)
    # Reference on exactly the float32 inputs, in float64.
    xr, Kr, cr = f32(x32), f32(K32), f32(cfw32)
    X = xr @ cr[:3, :3].T + cr[:3, 3]
    ref = np.stack([Kr[0, 0] * X[:, 0] / X[:, 2] + Kr[0, 2], Kr[1, 1] * X[:, 1] / X[:, 2] + Kr[1, 2]], -1)
    dX = 8 * U32 * (np.abs(xr).sum(-1) + np.abs(cr[:3, 3]).max())
    Zs = X[:, 2]
    amp = max(Kr[0, 0], Kr[1, 1]) / Zs * (1 + np.abs(X[:, :2]).max(-1) / Zs)
    tol = dX * amp + 4 * U32 * (np.abs(ref).max(-1) + max(W, H))
    assert np.all(np.isfinite(uv)) and np.all(np.isfinite(z))
    lim = G.GRID_CLIP * np.array([W, H])
    inside_clip = np.all(np.abs(ref) < lim - tol[:, None], axis=-1) & (Zs > G.DEPTH_EPS + dX)
    err = np.abs(uv[0] - ref).max(-1)
    assert np.all(err[inside_clip] <= tol[inside_clip]), (err, tol)
    assert np.all(np.abs(z[0] - Zs) <= dX)
    border = np.minimum.reduce([np.abs(ref[:, 0]), np.abs(ref[:, 0] - W), np.abs(ref[:, 1]),
                                np.abs(ref[:, 1] - H)])
    clear = (border > tol) & (np.abs(Zs - G.DEPTH_EPS) > dX)
    ref_valid = (Zs > G.DEPTH_EPS) & (ref[:, 0] >= 0) & (ref[:, 0] < W) & (ref[:, 1] >= 0) \
        & (ref[:, 1] < H)
    np.testing.assert_array_equal(valid[0][clear], ref_valid[clear])
    # The validity weight: continuous in (u, v), slope 1 / EDGE_FADE, so within tol / EDGE_FADE
    # everywhere away from the depth epsilon (no border exclusion needed).
    outside = np.maximum.reduce([-ref[:, 0], ref[:, 0] - W, -ref[:, 1], ref[:, 1] - H,
                                 np.zeros(len(ref))])
    ref_w = np.where(Zs > G.DEPTH_EPS, np.clip(1 - outside / G.EDGE_FADE, 0, 1), 0.0)
    weight = G.validity(uv, z, H, W)[0]
    assert weight.dtype == uv.dtype and np.all((weight >= 0) & (weight <= 1))
    near_z = np.abs(Zs - G.DEPTH_EPS) <= dX
    werr = np.abs(weight - ref_w)
    assert np.all(werr[~near_z & inside_clip] <= tol[~near_z & inside_clip] / G.EDGE_FADE
                  + 4 * U32), werr.max()


@needs_hypothesis
@prop
@given(q=quats, lscale=log_scale, lfx=log_focal, lfy=log_focal,
       hw=st.tuples(st.integers(1, 512), st.integers(1, 512)),
       centre=st.lists(st.floats(-1, 1), min_size=3, max_size=3))
def test_rays_float32_vs_float64(q, lscale, lfx, lfy, hw, centre):
    """rays_from_pixels in float32: directions within 8u (1 + |K^-1 uv|) of float64; the camera-z
    component of R^T d is 1 to the same bound."""
    H, W = hw
    T = pose(quaternion_rotation(q), np.asarray(centre) * 10.0 ** lscale)
    K = np.array([[10 ** lfx * W, 0, W / 2], [0, 10 ** lfy * H, H / 2], [0, 0, 1.0]])
    uv = NPG.pixel_centres(min(H, 8), min(W, 8)) * np.array([W / min(W, 8), H / min(H, 8)])
    o, d = G.rays_from_pixels(uv.astype(F32), K.astype(F32), T.astype(F32))
    Kr, Tr, uvr = f32(K.astype(F32)), f32(T.astype(F32)), f32(uv.astype(F32))
    dc = np.stack([(uvr[:, 0] - Kr[0, 2]) / Kr[0, 0], (uvr[:, 1] - Kr[1, 2]) / Kr[1, 1],
                   np.ones(len(uvr))], -1)
    ref = dc @ Tr[:3, :3].T
    tol = 8 * U32 * (1 + np.abs(dc).sum(-1))
    assert np.all(np.abs(d - ref).max(-1) <= tol)
    np.testing.assert_array_equal(o, np.broadcast_to(T[:3, 3].astype(F32), o.shape))


@needs_hypothesis
@prop
@given(lscale=log_scale, pts=st.lists(st.lists(st.floats(-1, 1), min_size=3, max_size=3),
                                       min_size=1, max_size=8),
       tgt=st.lists(st.floats(-1, 1), min_size=3, max_size=3),
       src=st.lists(st.lists(st.floats(-1, 1), min_size=3, max_size=3), min_size=1, max_size=4),
       coincide=st.booleans())
def test_cue_float32_vs_float64(lscale, pts, tgt, src, coincide):
    """geometric_cue in float32: |d t| <= 4u |x| / |o - x| (likewise s), and the cue moves by at
    most 2 (|dt| + |ds|) / max(|t - s|, CUE_EPS): bounded even where target and source centres
    coincide (the CUE_EPS floor)."""
    scale = 10.0 ** lscale
    x = np.array(pts) * scale
    o = np.array(tgt) * scale
    c = np.array(src) * scale
    if coincide:
        c[0] = o
    cue = G.geometric_cue(x.astype(F32), o.astype(F32), c.astype(F32))
    xr, orr, cr = f32(x.astype(F32)), f32(o.astype(F32)), f32(c.astype(F32))
    assert np.all(np.isfinite(cue))
    ref = G.geometric_cue(xr, orr, cr)                 # float64 run of the same formula
    nt = np.linalg.norm(orr - xr, axis=-1)[:, None]
    ns = np.linalg.norm(cr[None] - xr[:, None], axis=-1)
    mag = np.abs(xr).max(-1)[:, None] + max(np.abs(orr).max(), np.abs(cr).max())
    dt = 8 * U32 * mag / np.maximum(nt, 1e-300)
    ds = 8 * U32 * mag / np.maximum(ns, 1e-300)
    t = ref[..., :3]
    nd = np.linalg.norm((orr - xr)[:, None] / np.maximum(nt, G.NORM_EPS)[..., None]
                        - (cr[None] - xr[:, None]) / np.maximum(ns, G.NORM_EPS)[..., None], axis=-1)
    tol = 2 * (dt + ds) / np.maximum(nd, G.CUE_EPS) + 8 * U32
    ok = (nt > 1e3 * G.NORM_EPS * scale) & (ns > 1e3 * G.NORM_EPS * scale)   # away from 0/0
    err = np.abs(cue - ref).max(-1)
    assert np.all(err[ok] <= tol[ok]), (err[ok].max(), tol[ok].min())
    assert np.all(np.linalg.norm(t, axis=-1) <= 1 + 1e-12)


@needs_hypothesis
@prop
@given(a1=st.lists(st.floats(-1, 1), min_size=3, max_size=3),
       k=st.floats(-3, 3), lperp=st.floats(-14, 0), lscale=st.floats(-30, 30),
       perp=st.lists(st.floats(-1, 1), min_size=3, max_size=3))
def test_rotation_6d_near_degenerate_float32(a1, k, lperp, lscale, perp):
    """rotation_from_6d with a2 = k a1 + 10^lperp * (a part orthogonal to a1), any overall scale:
    float32 output is always a rotation (orthonormal, det +1, to ``ROTATION_TOL``); where a2's
    orthogonal part is well above the fallback threshold, it is within 16u |a2| / |a2_perp| of
    float64."""
    a1 = np.asarray(a1)
    p = np.asarray(perp)
    if np.linalg.norm(a1) < 1e-3 or np.linalg.norm(p - (p @ a1) / (a1 @ a1) * a1) < 1e-3:
        a1 = np.array([1.0, 0.2, -0.3])
        p = np.array([0.1, 1.0, 0.5])
    p = p - (p @ a1) / (a1 @ a1) * a1
    p /= np.linalg.norm(p)
    a2 = k * a1 + 10.0 ** lperp * p
    a = np.concatenate([a1, a2]) * 10.0 ** lscale
    r32 = NPG.rotation_from_6d(a.astype(F32))
    assert np.all(np.isfinite(r32))
    r = r32.astype(np.float64)
    assert np.abs(r.T @ r - np.eye(3)).max() < ROTATION_TOL
    assert abs(np.linalg.det(r) - 1) < ROTATION_TOL
    r64 = NPG.rotation_from_6d(f32(a.astype(F32)))
    a32 = f32(a.astype(F32))
    b1 = a32[:3] / np.linalg.norm(a32[:3])
    a2p = a32[3:] - (b1 @ a32[3:]) * b1
    rel_perp = np.linalg.norm(a2p) / np.abs(a32).max()
    if rel_perp > 1e3 * 64 * np.finfo(F32).eps:          # far above the fallback threshold
        tol = 16 * U32 * np.linalg.norm(a32[3:]) / np.linalg.norm(a2p) + 16 * U32
        assert np.abs(r - r64).max() <= tol, (np.abs(r - r64).max(), tol)


# ----------------------------------------------------------------------------------------------
# 2. Runtime renders of stiff scenes, renderer inputs vs the float64 reference
# ----------------------------------------------------------------------------------------------

def bin_centre(rt, m) -> float:
    return float(G.sample_depths(rt.near, rt.far, rt.samples, 1, dtype=F32)[0, m])


@pytest.mark.parametrize("offset", [0.0, 1e-12, -1e-12, "behind"])
def test_samples_on_in_front_of_and_behind_a_reference_camera_plane(stiff, offset):
    """View 1 sits on the central ray at the depth of sample 20 (then 1e-12 in front / behind,
    or past the far plane): samples on its camera plane (Z = 0, +-1e-12) and behind it are masked,
    everything stays finite, the inputs match the float64 reference."""
    model_dir, rt, maps, images = stiff
    zc = bin_centre(rt, 20) + (0.0 if offset == "behind" else offset)
    if offset == "behind":
        zc = 2.0 * rt.far
    scene = make_scene(maps, [np.eye(4), pose(t=(0.0, 0.0, zc))], images=images)
    K = G.intrinsics_from_focal(np.array([1.0, 1.0]), 5, 5)
    res, feed, ref = render_and_check(model_dir, scene, np.eye(4), K, (5, 5))
    Z1 = ref["X"][1, ..., 2]
    assert not feed["mask"][1][Z1 <= G.DEPTH_EPS].any()
    if offset != "behind":             # in float32 the sample lies on the plane in all three cases
        centre_ray = 2 * 5 + 2
        # Z1 is the float64 reference's depth (bin centre 20 in float64) minus zc, the float32
        # bin centre (one rounding, <= U32 * zc) plus the offset of 1e-12: f32_tol(1, zc) =
        # EPS32 * zc bounds both (the former literal 1e-7 held only for zc below ~1.7).
        assert (np.abs(Z1[centre_ray, 20]) <= f32_tol(1, max(1.0, zc))
                and not feed["mask"][1, centre_ray, 20])
        assert feed["mask"][1, centre_ray, 21:].all() and not feed["mask"][1, centre_ray, :20].any()


@pytest.mark.parametrize("shift", [0.0, 0.05])
def test_rays_grazing_a_reference_image_plane(stiff, shift):
    """The target looks along view 0's x axis: its central column of rays lies in view 0's
    camera plane (Z = 0, projections 0/0), its other columns just in front of / behind it."""
    model_dir, _, maps, images = stiff
    target = pose(rotation((0, 1, 0), np.pi / 2), (0.0, 0.0, shift))
    scene = make_scene(maps, [np.eye(4), pose(rotation((0, 1, 0), 0.3), (0.2, 0.0, -0.1))],
                       images=images)
    K = G.intrinsics_from_focal(np.array([1.0, 1.0]), 5, 5)
    render_and_check(model_dir, scene, target, K, (5, 5))


@pytest.mark.parametrize("nudge", [0.0, 1e-9, 1e-6])
def test_target_centre_equal_to_a_reference_centre(stiff, nudge):
    """Rendering at (or 1e-9 / 1e-6 from) a reference camera: t = s for every sample, the cue is
    [0, 0, 0, 1] up to the CUE_EPS-bounded rounding, and the image moves continuously."""
    model_dir, rt, maps, images = stiff
    views = [np.eye(4), pose(rotation((0.3, 1, 0), 0.1), (0.05, -0.02, 0.01))]
    scene = make_scene(maps, views, images=images)
    target = views[1].copy()
    target[:3, 3] += nudge
    K = scene.intrinsics(6, 6)
    res, feed, ref = render_and_check(model_dir, scene, target, K, (6, 6))
    cue1 = feed["cues"][1]
    if nudge == 0.0:
        # t and s / |s| are the same float32 vector (same difference, same norm), so t . s is
        # its squared norm: a norm (3 products, 2 sums, sqrt), the divisions, the dot product
        # (3 products, 2 sums): 12 roundings of values <= 1 (tests/tolerances.py, 1.0e-6).
        np.testing.assert_allclose(cue1[..., 3], 1.0, atol=f32_tol(12))
        assert np.abs(cue1[..., :3]).max() <= 8 * U32 / G.CUE_EPS * 4
    at = rt.render(scene, views[1], height=6, width=6, depth=True)
    # Lipschitz through the cue: |d cue| <= |d(t - s)| / CUE_EPS, |d(t - s)| <~ nudge / 0.1.
    bound = 1e-5 + 50 * nudge / 0.1 / G.CUE_EPS
    assert np.abs(res.image_float - at.image_float).max() <= bound


def test_points_projecting_exactly_onto_image_borders(stiff):
    """fx = 32 (a power of two) and a target principal point shifted by half a pixel: pixel (i, j)
    of the target projects exactly to (u, v) = (j, i) in view 0. The image is [0, 64] x [0, 64]
    with validity 1 (borders included), fading to 0 at EDGE_FADE = 1 pixel outside: u = 65 or
    v = 65 has weight 0. A 2 x 66 and a 66 x 2 render cover all four borders."""
    model_dir, _, maps, images = stiff
    assert G.EDGE_FADE == 1.0
    focal = np.array([0.5, 0.5])                     # fx = fy = 32 on the 64 x 64 model image
    scene = make_scene(maps, [np.eye(4)], focal=focal, images=images)
    Kr = scene.K
    for H, W, row0, col0 in ((2, 66, 0, 0), (66, 2, 0, 62)):
        K_out = np.array([[Kr[0, 0], 0, Kr[0, 2] + 0.5 - col0],
                          [0, Kr[1, 1], Kr[1, 2] + 0.5 - row0], [0, 0, 1.0]])
        res, feed, ref = render_and_check(model_dir, scene, np.eye(4), K_out, (H, W))
        mask = feed["mask"][0].reshape(H, W, -1)
        u = (np.arange(W) + col0)[None, :].repeat(H, 0)
        v = (np.arange(H) + row0)[:, None].repeat(W, 1)
        inside = (u <= 64) & (v <= 64)
        assert np.all(mask[inside] == 1.0) and np.all(mask[~inside] == 0.0)  # every depth alike
        grid = feed["grid"][0].reshape(H, W, -1, 2)
        assert np.all(grid[u == 0][..., 0] == -1.0) and np.all(grid[v == 0][..., 1] == -1.0)
        assert np.all(grid[u == 64][..., 0] == 1.0) and np.all(grid[v == 64][..., 1] == 1.0)


@pytest.mark.parametrize("focal", [0.05, 50.0])
def test_extreme_intrinsics(stiff, focal):
    """fx/W of 0.05 (a 170-degree view) and 50 (0.6 degrees), for the references and the target."""
    model_dir, _, maps, images = stiff
    views = [np.eye(4), pose(rotation((0, 1, 0), 0.02), (0.01, 0.0, 0.0))]
    scene = make_scene(maps, views, focal=(focal, focal), images=images)
    K = G.intrinsics_from_focal(np.array([focal, focal]), 6, 6)
    render_and_check(model_dir, scene, pose(rotation((1, 0, 0), 0.01), (0.0, 0.005, 0.02)), K,
                     (6, 6))


@pytest.mark.parametrize("scale", [1e-6, 1e6])
def test_extreme_scene_scales(stiff, scale):
    """Every camera translation scaled by 1e-6 / 1e6 (the depth range stays [near, far]): finite,
    and the float32 inputs within the conditioning bound, which at 1e6 is loose by necessity
    (float32 positions there are spaced 0.06 apart)."""
    views = [np.eye(4), pose(rotation((0, 1, 0), 0.05), np.array([0.3, 0.1, -0.2]) * scale),
             pose(rotation((1, 0, 0), -0.05), np.array([-0.2, 0.3, 0.1]) * scale)]
    model_dir, _, maps, images = stiff
    scene = make_scene(maps, views, images=images)
    target = pose(rotation((0, 1, 1), 0.03), np.array([0.1, -0.1, 0.05]) * scale)
    render_and_check(model_dir, scene, target, scene.intrinsics(5, 5), (5, 5))


@pytest.mark.parametrize("where, turn", [((0.0, 0.0, -90.0), 0.0), ((90.0, 0.0, 0.0), 0.0),
                                         ((0.0, 0.0, -3.0), np.pi)])
def test_pose_far_outside_the_depth_range(stiff, where, turn):
    """No sample of any ray sees a reference view (behind them, or 90 units off to the side,
    within ``limits.MAX_POSE_DISTANCE`` x 0.1 of them; farther is refused, tests/test_colour.py):
    every pixel is the empty-ray colour, depth 0, with and without culling (culling then skips
    every renderer call; the graph's answer to all-masked inputs is finite)."""
    model_dir, rt, maps, images = stiff
    scene = make_scene(maps, [np.eye(4), pose(t=(0.1, 0.0, 0.0))], images=images)
    target = pose(rotation((0, 1, 0), turn), where)
    res, feed, ref = render_and_check(model_dir, scene, target, scene.intrinsics(4, 4), (4, 4))
    assert not feed["mask"].any() and np.all(res.depth == 0)
    np.testing.assert_array_equal(res.image_float, np.broadcast_to(res.image_float[0, 0], (4, 4, 3)))


@pytest.mark.parametrize("V", [1, 32])
def test_one_and_32_reference_views(stiff, V):
    model_dir, _, maps, images = stiff
    rng = np.random.default_rng(V)
    views = [np.eye(4)] + [pose(rotation(rng.normal(size=3), 0.1 * rng.random()),
                                0.05 * rng.normal(size=3)) for _ in range(V - 1)]
    scene = make_scene(maps, views, images=images)
    render_and_check(model_dir, scene, pose(rotation((0, 1, 0), 0.05), (0.02, 0, 0)),
                     scene.intrinsics(4, 4), (4, 4))


@pytest.mark.parametrize("kind", ["black", "white", "constant", "noise"])
def test_constant_black_white_noise_images(stiff, kind):
    """Also the explicit-colour model's blend at exactly 0 and 1 (black, white photos): finite."""
    rt = stiff[1]
    H, W = rt.image_size
    rng = np.random.default_rng(0)
    make = {"black": lambda: np.zeros((H, W, 3), np.uint8),
            "white": lambda: np.full((H, W, 3), 255, np.uint8),
            "constant": lambda: np.full((H, W, 3), (90, 140, 30), np.uint8),
            "noise": lambda: rng.integers(0, 256, (H, W, 3), dtype=np.uint8)}[kind]
    scene = rt.encode([make() for _ in range(3)])
    assert np.all(np.isfinite(scene.field_maps))
    for T in scene.world_from_cam:
        assert G.is_rigid(T, atol=1e-5)
    res = rt.render(scene, 1, height=4, width=4, depth=True)
    assert np.all(np.isfinite(res.image_float)) and np.all(np.isfinite(res.depth))


# ----------------------------------------------------------------------------------------------
# 3. Determinism
# ----------------------------------------------------------------------------------------------

def test_bitwise_deterministic_across_calls(stiff):
    rt = stiff[1]
    rng = np.random.default_rng(8)
    images = [rng.integers(0, 256, (*rt.image_size, 3), dtype=np.uint8) for _ in range(3)]
    a, b = rt.encode(images), rt.encode(images)
    for k in ("field_maps", "world_from_cam", "focal"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    target = pose(rotation((0, 1, 0), 0.2), (0.05, 0, 0))
    r1 = rt.render(a, target, height=6, width=7, depth=True)
    r2 = rt.render(b, target, height=6, width=7, depth=True)
    np.testing.assert_array_equal(r1.image_float, r2.image_float)
    np.testing.assert_array_equal(r1.depth, r2.depth)


def test_thread_counts_agree(model_dir, rt):
    """1 vs 2 ONNX Runtime threads: the same scene and render up to float32 rounding (a thread
    split may change the order of a sum): the encoder's and the renderer's
    (tests/tolerances.py; ~3e-5 for poses, ~6e-5 for field maps of magnitude ~2, 1.7e-5 for the
    render). Another image or pose moves them by > 1e-2."""
    rng = np.random.default_rng(9)
    images = [rng.integers(0, 256, (*rt.image_size, 3), dtype=np.uint8) for _ in range(3)]
    two = IrisRuntime(model_dir, threads=2)
    a, b = rt.encode(images), two.encode(images)
    config = rt.manifest.config
    for k, output in (("field_maps", "field_maps"), ("world_from_cam", "cameras"),
                      ("focal", "focal")):
        want = getattr(a, k)
        tol = encoder_tol(config, len(images), output, max(1.0, float(np.abs(want).max())))
        np.testing.assert_allclose(getattr(b, k), want, rtol=0, atol=tol)
    target = pose(rotation((1, 1, 0), 0.1), (0.0, 0.03, 0.0))
    r1 = rt.render(a, target, height=6, width=6, depth=True)
    r2 = two.render(a, target, height=6, width=6, depth=True)
    tol = render_tol(config, a.num_views, rt.far)
    np.testing.assert_allclose(r1.image_float, r2.image_float, rtol=0, atol=tol)
    np.testing.assert_allclose(r1.depth, r2.depth, rtol=0, atol=tol)


# ----------------------------------------------------------------------------------------------
# 4. Under load: one runtime, 8 threads x 20 renders, against the same renders done serially
# ----------------------------------------------------------------------------------------------

def _rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="needs /proc for RSS")
def test_eight_threads_twenty_renders_each(model_dir):
    runtime = IrisRuntime(model_dir, threads=1)
    rng = np.random.default_rng(10)
    scenes = [runtime.encode([rng.integers(0, 256, (*runtime.image_size, 3), dtype=np.uint8)
                              for _ in range(V)]) for V in (2, 3)]
    poses = [1, pose(rotation((0, 1, 0), 0.3), (0.1, 0, 0)),
             pose(rotation((1, 0, 0), -0.2), (0, 0.05, -0.05)),
             pose(rotation((0, 1, 0), 0.6), (0.25, 0.0, -0.05)), 0]
    sizes = [(6, 6), (5, 7)]
    jobs = [(s, p, sizes[(s + p) % 2]) for s in range(2) for p in range(len(poses))]
    serial = {}
    for s, p, (h, w) in jobs:
        serial[s, p] = runtime.render(scenes[s], poses[p], height=h, width=w, depth=True)
    base = _rss()
    peak = [base]
    stop = threading.Event()

    def sample():
        while not stop.is_set():
            peak[0] = max(peak[0], _rss())
            time.sleep(0.002)

    results, errors = {}, []
    barrier = threading.Barrier(8)

    def work(i):
        try:
            barrier.wait()
            for r in range(20):
                s, p, (h, w) = jobs[(i * 3 + r) % len(jobs)]
                results[i, r] = (s, p, runtime.render(scenes[s], poses[p], height=h, width=w,
                                                      depth=True))
        except Exception as exc:          # pragma: no cover - reported below
            errors.append(exc)

    monitor = threading.Thread(target=sample)
    monitor.start()
    threads = [threading.Thread(target=work, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    stop.set()
    monitor.join()
    assert not errors, errors
    assert len(results) == 160
    for (s, p, res) in results.values():
        np.testing.assert_array_equal(res.image_float, serial[s, p].image_float)
        np.testing.assert_array_equal(res.depth, serial[s, p].depth)
    largest = max(h * w for h, w in sizes)
    bound = R.render_memory_bound(3, min(runtime.default_chunk_rays(3), largest), runtime.samples,
                                  concurrent=8)
    print(f"load test: peak RSS +{(peak[0] - base) / 2**20:.0f} MB, bound {bound / 2**20:.0f} MB")
    assert peak[0] - base <= bound, (peak[0] - base, bound)


# ----------------------------------------------------------------------------------------------
# 5. ONNX graphs vs the torch model in float64 (torch only)
# ----------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def torch_models(torch_export):
    torch = pytest.importorskip("torch")
    import copy
    model_dir, model = torch_export
    torch.set_num_threads(1)
    return model_dir, model, copy.deepcopy(model).double().eval()


@pytest.fixture(scope="module", params=["tiny", "tiny-rgb"])
def any_torch_models(request):
    """``torch_models`` and the same for the explicit-colour model (``torch_export_rgb``)."""
    if request.param == "tiny":
        return request.getfixturevalue("torch_models")
    import copy
    pytest.importorskip("torch")
    model_dir, model = request.getfixturevalue("torch_export_rgb")
    return model_dir, model, copy.deepcopy(model).double().eval()


def _ort(path):
    import onnxruntime as ort
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def _weights(u: np.ndarray) -> np.ndarray:
    """Validity weights from uniforms: 0 (40 %), fractional (an image edge, 20 %), 1."""
    return np.where(u < 0.4, 0.0, np.where(u < 0.6, (u - 0.4) * 5, 1.0)).astype(F32)


def _renderer_feed(V, R_, S, seed, cfg):
    rng = np.random.default_rng(seed)
    h, w = cfg.field_grid
    feed = {"field_maps": rng.normal(size=(V, cfg.field_channels, h, w)).astype(F32),
            "grid": rng.uniform(-1.2, 1.2, size=(V, R_, S, 2)).astype(F32),
            "cues": rng.normal(size=(V, R_, S, 4)).astype(F32),
            "mask": _weights(rng.random((V, R_, S))),
            "positions": rng.normal(size=(R_, S, 3)).astype(F32),
            "directions": rng.normal(size=(R_, 3)).astype(F32)}
    if cfg.explicit_rgb:     # ray 0 black, ray 1 white (the blend's clamp), the others random
        colours = rng.random((V, R_, S, 3)).astype(F32)
        colours[:, 0], colours[:, 1] = 0.0, 1.0
        feed["colours"] = colours
    return feed


def _torch64(model64, feed):
    import torch
    from export.graphs import RendererGraph
    args = {k: torch.from_numpy(v if v.dtype == bool else v.astype(np.float64))
            for k, v in feed.items()}
    with torch.no_grad():
        rgb, w = RendererGraph(model64)(**args)
    return rgb.numpy(), w.numpy()


@pytest.mark.torch
@pytest.mark.parametrize("case", ["borders", "large_logits", "masked", "one_view", "32_views"])
def test_renderer_graph_vs_float64_torch(any_torch_models, case):
    """ONNX renderer vs the torch renderer in float64. Tolerance 1e-4 (DESIGN's export
    tolerance; measured ~1e-7); for logits scaled by 1e4 the softmax amplifies float32's relative
    error u |logit| ~ 1e-3 in the exponent, hence 1e-2 there (measured below it). Both models
    (the explicit-colour one with black, white and random colours)."""
    model_dir, model, model64 = any_torch_models
    cfg = model.cfg
    V, R_, S = {"one_view": 1, "32_views": 32}.get(case, 3), 6, 9
    feed = _renderer_feed(V, R_, S, 11, cfg)
    tol = 1e-4
    if case == "borders":                # exactly on the image borders, corners, just outside
        vals = np.array([-1.0, 1.0, -1.0 + 1e-7, 1.0 - 1e-7, -1.0 - 1e-7, 1.0 + 1e-7, 0.0], F32)
        g = np.stack(np.meshgrid(vals, vals), -1).reshape(-1, 2)
        feed["grid"][:] = g[np.arange(R_ * S) % len(g)].reshape(R_, S, 2)
    elif case == "large_logits":         # view-attention logits x 1e4: keys/values of the maps
        feed["field_maps"][:, cfg.field_width:] *= 1e4
        tol = 1e-2
    elif case == "masked":               # some points in no view, a whole ray in no view
        feed["mask"][:, :, 2] = False
        feed["mask"][:, 3] = False
    rgb, weights = _ort(Path(model_dir) / "renderer.onnx").run(["rgb", "weights"], feed)
    rgb64, w64 = _torch64(model64, feed)
    assert np.all(np.isfinite(rgb)) and np.all(np.isfinite(weights))
    np.testing.assert_allclose(rgb, rgb64, rtol=0, atol=tol)
    np.testing.assert_allclose(weights, w64, rtol=0, atol=tol)
    live = (feed["mask"] > 0).any(0)
    np.testing.assert_allclose(weights[live.any(-1)].sum(-1), 1.0, rtol=0, atol=1e-5)
    assert np.all(weights[~live] == 0)


@pytest.mark.torch
@pytest.mark.parametrize("kind", ["black", "white", "constant", "noise"])
def test_encoder_graph_vs_float64_torch(torch_models, kind):
    """Constant images make every patch token equal (zero variance inside LayerNorm: its eps
    keeps it finite). ONNX encoder vs torch float64 within 1e-4 relative to the output scale."""
    import torch
    from export.graphs import EncoderGraph
    model_dir, model, model64 = torch_models
    H, W = model.cfg.image_height, model.cfg.image_width
    rng = np.random.default_rng(1)
    images = {"black": np.zeros((3, 3, H, W)), "white": np.ones((3, 3, H, W)),
              "constant": np.broadcast_to(np.array([0.35, 0.55, 0.12])[None, :, None, None],
                                          (3, 3, H, W)),
              "noise": rng.random((3, 3, H, W))}[kind].astype(F32)
    is_reference = np.array([True, True, False])          # a query too: the mask's both kinds
    out = _ort(Path(model_dir) / "encoder.onnx").run(["field_maps", "world_from_cam", "focal"],
                                                     {"images": images, "is_reference": is_reference})
    with torch.no_grad():
        ref = [t.numpy() for t in EncoderGraph(model64)(torch.from_numpy(images.astype(np.float64)),
                                                        torch.from_numpy(is_reference))]
    for a, b in zip(out, ref):
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-4 * max(1.0, np.abs(b).max()))


@pytest.mark.torch
@pytest.mark.parametrize("case", ["a1_zero", "a1_tiny", "a2_parallel", "a2_zero", "both_zero",
                                  "a2_nearly_parallel"])
def test_camera_head_near_degenerate_6d(torch_models, case):
    """The camera head's 6D output forced to (near-)degenerate values: poses stay rigid (finite,
    orthonormal, det +1, to ``ROTATION_TOL``), gradients finite; exactly degenerate cases equal
    the float64 numpy rotation_from_6d (same fallback) up to float32's rounding of the same
    chain (``ROTATION_TOL``)."""
    import copy
    import torch
    _, model, _ = torch_models
    head = copy.deepcopy(model.camera_head).float()
    six = {"a1_zero": [0, 0, 0, 0, 1, 0], "a1_tiny": [1e-30, 0, 0, 0, 1, 0],
           "a2_parallel": [1, 0, 0, 2, 0, 0], "a2_zero": [0.3, 0.4, 0, 0, 0, 0],
           "both_zero": [0, 0, 0, 0, 0, 0], "a2_nearly_parallel": [1, 0, 0, 1, 1e-9, 0]}[case]
    target = torch.tensor(six, dtype=torch.float32)
    last = head.pose_mlp[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias[:6] = target - head.identity_6d
        last.bias[6:] = 0.0
    tokens = torch.randn(1, 3, model.cfg.encoder_width, generator=torch.Generator().manual_seed(0),
                         requires_grad=True)
    world_from_cam, focal = head(tokens)
    T = world_from_cam[0].detach().double().numpy()
    assert np.all(np.isfinite(T))
    for Ti in T:
        Rm = Ti[:3, :3]
        assert np.abs(Rm.T @ Rm - np.eye(3)).max() < ROTATION_TOL
        assert abs(np.linalg.det(Rm) - 1) < ROTATION_TOL
    if case != "a2_nearly_parallel":
        a6 = (head.identity_6d + last.bias[:6]).detach().double().numpy()
        np.testing.assert_allclose(T[1, :3, :3], NPG.rotation_from_6d(a6), atol=ROTATION_TOL)
    (world_from_cam.sum() + focal.sum()).backward()
    assert torch.all(torch.isfinite(tokens.grad))
    assert all(torch.all(torch.isfinite(p.grad)) for p in head.parameters() if p.grad is not None)


@pytest.mark.torch
def test_ray_attention_large_logits_torch(torch_models):
    """The ray transformer's input is layer-normed, so scaled features cannot blow up its logits;
    scaling its query/key weights by 100 (logits x 1e4) does: float32 stays finite, masked rows
    stay 0, weights sum to 1 within 1e-5, and both attention paths (explicit masked softmax,
    fused SDPA with the finite -1e30 bias) agree with float64 within 1e-2."""
    import copy
    import torch
    _, model, _ = torch_models
    m32 = copy.deepcopy(model).float()
    W_ = model.cfg.field_width
    with torch.no_grad():
        for blk in m32.renderer.ray_transformer.blocks:
            blk.qkv.weight[:2 * W_] *= 100.0
            blk.qkv.bias[:2 * W_] *= 100.0
    m64 = copy.deepcopy(m32).double()
    g = torch.Generator().manual_seed(4)
    Rr, S = 5, 12
    f = torch.randn(Rr, S, W_, generator=g) * 1e4
    pos = torch.randn(Rr, S, 3, generator=g)
    dirs = torch.randn(Rr, 3, generator=g)
    mask = torch.rand(Rr, S, generator=g) > 0.3
    mask[1] = False
    mask[2, :] = False
    mask[2, 5] = True
    with torch.no_grad():
        rgb, w = m32.renderer(f, pos, dirs, mask)
        rgb_fast, _ = m32.renderer(f, pos, dirs, mask, need_weights=False)
        rgb64, w64 = m64.renderer(f.double(), pos.double(), dirs.double(), mask)
    for t in (rgb, w, rgb_fast):
        assert torch.all(torch.isfinite(t))
    assert torch.all(w[~mask] == 0)
    torch.testing.assert_close(w[mask.any(-1)].sum(-1), torch.ones(int(mask.any(-1).sum())),
                               atol=1e-5, rtol=0)
    torch.testing.assert_close(rgb.double(), rgb64, atol=1e-2, rtol=0)
    torch.testing.assert_close(rgb_fast.double(), rgb64, atol=1e-2, rtol=0)
    torch.testing.assert_close(w.double(), w64, atol=1e-2, rtol=0)
