"""Tests of the coarse-to-fine knobs (``RenderSettings.refine`` / ``depth_window``,
iris_runtime.adaptive) and of the subset march they rest on (``MarchPlan.pixel_index``,
``sample_window``, ``mode_radius``).

The contract: what is rendered is rendered exactly. The pixels ``refine`` marches again equal
the same pixels of the render without it (up to float32 rounding: they share renderer calls with
other pixels; the ``tol`` fixture below), ``refine=0`` equals the full render, a depth-guided
ray that keeps every sample equals the full render's ray, and a windowed ray is the renderer's
answer to its window's samples alone (the same as masking the others: ``cull=False``). The
pixels ``refine`` leaves are the coarse pass, upsampled.

Same models as tests/test_speed_knobs.py (a random tiny and a random explicit-colour export, or
``IRIS_TEST_MODEL_DIR`` / ``IRIS_TEST_RGB_MODEL_DIR``); renders of at most 24 x 20 pixels.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from iris_runtime import InputError, IrisRuntime, adaptive, raymarch
from iris_runtime import quality as Q
from iris_runtime.runtime import QUALITY_PRESETS

# The knob tests' models (int8 renderer, both renderer kinds) and runtime, shared with them.
from .test_speed_knobs import model_dir, rt  # noqa: F401  (pytest fixtures)
from .tolerances import f32_tol, render_tol

H, W = 24, 20


@pytest.fixture(scope="session")
def tol(rt):
    """Two renders of the same pixels whose renderer calls differ (other rays packed beside them,
    other chunks, dropped masked samples): the renderer's float32 rounding, which depends on the
    CPU's kernels and the thread count (tests/tolerances.py ``render_tol``: 1.7e-5 for the tiny
    configs, 5 views; measured <= 1e-6 here). rgb in [0, 1], depth in [near, far]; a wrong pixel,
    window or sample moves them by > 1e-3 (the windows' own effect, asserted below)."""
    return render_tol(rt.manifest.config, 5, rt.far)


@pytest.fixture(scope="session")
def scene(rt):
    """5 views of smooth random images with one sharp square (edges for ``refine`` to find)."""
    import cv2
    rng = np.random.default_rng(7)
    h, w = rt.image_size
    images = []
    for _ in range(5):
        img = cv2.resize(rng.integers(0, 256, (6, 6, 3), dtype=np.uint8), (w, h),
                         interpolation=cv2.INTER_CUBIC)
        img[h // 3:2 * h // 3, w // 3:2 * w // 3] = rng.integers(0, 256, 3, dtype=np.uint8)
        images.append(img)
    return rt.encode(images)


def _pose(scene):
    T = scene.world_from_cam[0].copy()
    T[:3, 3] = 0.5 * (scene.world_from_cam[0, :3, 3] + scene.world_from_cam[1, :3, 3]) + 0.01
    return T


@pytest.fixture(scope="session")
def full(rt, scene):
    return rt.render(scene, _pose(scene), height=H, width=W, depth=True)


@pytest.fixture
def marches(monkeypatch):
    """Every (plan, result) of ``raymarch.march`` during the test, in call order."""
    seen = []
    real = raymarch.march

    def spy(plan, session, **kw):
        out = real(plan, session, **kw)
        seen.append((plan, out))
        return out

    monkeypatch.setattr(raymarch, "march", spy)
    return seen


def _rows(a: np.ndarray) -> np.ndarray:
    return a.reshape(H * W, -1)


# ----------------------------------------------------------------------------------------------
# Settings (no model)
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("bad", [
    dict(coarse=0.0), dict(coarse=1.5), dict(coarse="half"), dict(refine=-0.1),
    dict(refine=float("inf")), dict(refine=True), dict(refine_budget=0.0),
    dict(refine_budget=1.01), dict(depth_window=-1), dict(depth_window=2.0),
    dict(depth_window=True), dict(depth_mass=-0.1), dict(depth_mass=1.5),
    dict(depth_mass=float("nan"))])
def test_new_settings_are_checked_naming_the_field(bad):
    (name, _), = bad.items()
    with pytest.raises(InputError, match=f"^{name}: "):
        Q.RenderSettings(**bad)
    with pytest.raises(InputError, match=f"^{name}: "):
        Q.resolve_settings("adaptive", **bad)


def test_adaptive_preset():
    s = QUALITY_PRESETS["adaptive"]
    assert s == Q.RenderSettings(upsample="cubic", coarse=0.25, refine=0.1, refine_budget=0.12)
    assert s.depth_window is None and s.samples is None and s.scale == 1.0
    assert Q.resolve_settings("adaptive", refine_budget=0.5).refine_budget == 0.5


def test_coarse_size_and_interpolation_footprint():
    assert adaptive.coarse_size(64, 64, 0.25) == (16, 16)
    assert adaptive.coarse_size(3, 5, 0.1) == (1, 1)
    # cv2.resize INTER_LINEAR reads, per output pixel, the input pixels floor and floor + 1
    # (clamped) of _bilinear_floor.
    import cv2
    for n_out, n_in in ((24, 6), (20, 5), (7, 3), (5, 5)):
        f = adaptive._bilinear_floor(n_out, n_in)
        i0, i1 = np.clip(f, 0, n_in - 1), np.clip(f + 1, 0, n_in - 1)
        for j in range(n_in):
            row = np.zeros((1, n_in), np.float32)
            row[0, j] = 1.0
            touched = np.flatnonzero(cv2.resize(row, (n_out, 1), interpolation=cv2.INTER_LINEAR)[0])
            assert set(touched) <= set(np.flatnonzero((i0 == j) | (i1 == j)))


def test_untrusted_flags_edges_not_flat_regions():
    rgb = np.full((8, 8, 3), 0.5, np.float32)
    rgb[:, 4:] = 0.9                                  # a vertical colour edge between cols 3, 4
    depth = np.full((8, 8), 0.5, np.float32)
    depth[6:, :] = 0.95                               # a depth edge between rows 5, 6
    score = adaptive.untrusted(rgb, depth, 32, 32, 0.9)
    assert score.shape == (32, 32)
    # Max / min / subtraction of these float32 values are exact (Sterbenz); the constants' own
    # rounding and the division by 0.9 are at most 4 roundings of values <= 1 (strict bound).
    atol = f32_tol(4)
    np.testing.assert_allclose(score[:8, 14:18], 0.4, atol=atol)    # next to the colour edge
    np.testing.assert_allclose(score[:8, :8], 0.0)                  # flat
    np.testing.assert_allclose(score[21:27, :8], 0.5, atol=atol)    # next to the depth edge


@pytest.mark.parametrize("kw", [dict(refine=0.1, refine_budget=0.12), dict(refine=0.0),
                                dict(depth_window=8, depth_mass=0.5),
                                dict(refine=0.0, refine_budget=0.5, depth_window=8,
                                     depth_mass=0.5)])
def test_memory_per_pixel_is_bounded(kw):
    """``adaptive.BYTES_PER_PIXEL``, measured with a stand-in march that returns what the real
    one returns (its own per-call memory is ``limits.render_memory_bound``'s)."""
    import tracemalloc
    rng = np.random.default_rng(0)
    z = np.linspace(0.1, 1.0, 64, dtype=np.float32)

    def march_at(h, w, pixel_index=None, sample_window=None, mode_radius=None, progress=None):
        n = h * w if pixel_index is None else len(pixel_index)
        rgb, depth = rng.random((n, 3), dtype=np.float32), rng.random(n, dtype=np.float32)
        if mode_radius is None:
            return raymarch.MarchResult(rgb, depth, raymarch.MarchStats())
        return raymarch.MarchResult(rgb, depth, raymarch.MarchStats(),
                                    z[rng.integers(0, 64, n)], rng.random(n, dtype=np.float32))

    n = 512 * 512
    tracemalloc.start()
    try:
        adaptive.render(Q.RenderSettings(**kw), march_at, 512, 512, near=0.1, far=1.0,
                        samples=64)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak <= adaptive.BYTES_PER_PIXEL * n


def test_depth_windows():
    z = ((np.arange(16) + 0.5) / 16).astype(np.float32)
    mode = np.full((2, 2), z[8], np.float32)
    mass = np.ones((2, 2), np.float32)
    win = adaptive.depth_windows(mode, mass, 4, 4, z, 2, 0.9)
    assert win.shape == (16, 2) and (win == [6, 11]).all()          # bins 6..10 around 8
    mode[1, 1] = z[12]                                               # a depth edge: wider windows
    win = adaptive.depth_windows(mode, mass, 4, 4, z, 2, 0.9).reshape(4, 4, 2)
    assert (win[0, 0] == [6, 11]).all() and (win[3, 3] == [10, 15]).all()
    assert (win[1, 1] == [6, 15]).all()                              # between both modes
    mass[0, 0] = 0.5                                                 # spread: every sample
    win = adaptive.depth_windows(mode, mass, 4, 4, z, 2, 0.9).reshape(4, 4, 2)
    assert (win[0, 0] == [0, 16]).all() and (win[3, 3] == [10, 15]).all()
    assert (adaptive.depth_windows(mode, mass, 4, 4, z, 0, 0.0)[:, 1] > 0).all()


# ----------------------------------------------------------------------------------------------
# The subset march
# ----------------------------------------------------------------------------------------------

def _plan(rt, scene, h=H, w=W, **subset):
    return raymarch.MarchPlan.build(
        scene, _pose(scene), scene.intrinsics(h, w), h, w, samples=rt.samples, near=rt.near,
        far=rt.far, top_k=None, top_k_by="ray", chunk_rays=37, cull=rt.cull,
        photos=rt._view_images(scene), empty_rgb=rt._empty_ray_rgb(scene, "renderer"), **subset)


def test_marching_a_pixel_subset_equals_the_full_march(rt, scene, full, tol):
    pixels = np.random.default_rng(0).permutation(H * W)[:101]
    out = raymarch.march(_plan(rt, scene, pixel_index=pixels), rt._session("renderer"))
    assert out.rgb.shape == (101, 3) and out.depth.shape == (101,)
    assert np.abs(out.rgb - _rows(full.image_float)[pixels]).max() <= tol
    assert np.abs(out.depth - full.depth.reshape(-1)[pixels]).max() <= tol


def test_a_sample_window_is_masking_the_other_samples(rt, scene, full, tol):
    S = rt.samples
    rng = np.random.default_rng(1)
    lo = rng.integers(0, S, H * W)
    win = np.stack([lo, np.minimum(S, lo + rng.integers(1, S // 2, H * W))], axis=1)
    win[::7] = [0, S]                                   # some rays keep every sample
    plan = _plan(rt, scene, sample_window=win, mode_radius=rt.far - rt.near)   # mass: sum of w
    a = raymarch.march(plan, rt._session("renderer"))
    b = raymarch.march(dataclasses.replace(plan, cull=False, empty_rgb=None),
                       rt._session("renderer"))
    assert np.abs(a.rgb - b.rgb).max() <= tol and np.abs(a.depth - b.depth).max() <= tol
    assert np.abs(a.rgb[::7] - _rows(full.image_float)[::7]).max() <= tol
    assert np.abs(a.rgb - _rows(full.image_float)).max() > 1e-3      # the windows do something
    # depth within each window: sum of weights x z over the window's samples only (the weights
    # sum to one, or to less on a ray seen only at an image edge: ``mass``)
    z, live, m = plan.z_bins, a.depth > 0, a.mass
    assert (a.depth[live] >= z[win[live, 0]] * m[live] - 1e-5).all()
    assert (a.depth[live] <= z[win[live, 1] - 1] * m[live] + 1e-5).all()


def test_weight_mode_and_mass(rt, scene, full, tol):
    plan = _plan(rt, scene, mode_radius=rt.far - rt.near)           # every sample within reach
    out = raymarch.march(plan, rt._session("renderer"))
    seen = out.depth > 0
    # Weights sum to one on rays with a fully valid sample, to less on rays seen only at an
    # image edge (validity weights < 1).
    assert (out.mass[seen] <= 1 + 1e-5).all() and (out.mass[seen] > 0).all()
    assert np.mean(np.abs(out.mass[seen] - 1) <= 1e-5) >= 0.9
    assert (out.mass[~seen] == 0).all() and (out.mode[~seen] == 0).all()
    assert np.isin(out.mode[seen], plan.z_bins).all()
    assert np.abs(out.rgb - _rows(full.image_float)).max() <= tol   # nothing else changes
    narrow = raymarch.march(dataclasses.replace(plan, mode_radius=0.0), rt._session("renderer"))
    # The same weights summed over a sub-window in float32: at most S terms of rounding.
    assert (narrow.mass <= out.mass + f32_tol(rt.samples)).all() and (narrow.mass[seen] > 0).all()
    assert (narrow.mass[seen] < out.mass[seen] - 1e-3).any()
    np.testing.assert_array_equal(narrow.mode, out.mode)


# ----------------------------------------------------------------------------------------------
# Adaptive refinement
# ----------------------------------------------------------------------------------------------

def test_refine_everything_is_the_full_render(rt, scene, full, tol):
    res = rt.render(scene, _pose(scene), height=H, width=W, depth=True, refine=0.0)
    assert np.abs(res.image_float - full.image_float).max() <= tol
    assert np.abs(res.depth - full.depth).max() <= tol
    assert res.work["refined_rays"] == res.work["pixels"] == H * W
    assert res.work["coarse_rays"] == math.prod(adaptive.coarse_size(H, W, 0.25))
    assert res.timings["coarse"] <= res.timings["total"]


@pytest.mark.parametrize("kw", [dict(refine="median"), dict(refine=0.0, refine_budget=0.2),
                                dict(quality="adaptive"),
                                dict(refine="median", coarse=0.5, upsample="linear")])
def test_refined_pixels_are_exact_and_the_rest_is_the_coarse_pass(rt, scene, full, marches, kw,
                                                                  tol):
    import cv2
    if kw.get("refine") == "median":       # a threshold that some pixels pass and some do not
        coarse = kw.get("coarse", 0.25)
        rt.render(scene, _pose(scene), height=H, width=W, coarse=coarse, refine=0.0,
                  refine_budget=0.01)
        (plan, out), _ = marches
        score = adaptive.untrusted(out.rgb.reshape(plan.height, plan.width, 3),
                                   out.depth.reshape(plan.height, plan.width), H, W,
                                   rt.far - rt.near)
        kw = {**kw, "refine": float(np.median(score))}
        marches.clear()
    res = rt.render(scene, _pose(scene), height=H, width=W, depth=True, **kw)
    s = res.settings
    (coarse_plan, coarse), (fine_plan, _) = marches
    h, w = adaptive.coarse_size(H, W, s.coarse)
    assert (coarse_plan.height, coarse_plan.width) == (h, w) and coarse_plan.pixel_index is None
    refined = fine_plan.pixel_index
    # The pixels chosen: score >= refine, at most the budget, the least trusted first.
    rgb_c, depth_c = coarse.rgb.reshape(h, w, 3), coarse.depth.reshape(h, w)
    score = adaptive.untrusted(rgb_c, depth_c, H, W, rt.far - rt.near).reshape(-1)
    flagged = np.flatnonzero(score >= s.refine)
    budget = int(s.refine_budget * (H * W) + 0.5)
    assert len(refined) == min(len(flagged), budget) == res.work["refined_rays"]
    assert set(refined) <= set(flagged)
    if len(flagged) > budget:
        rest = np.setdiff1d(np.arange(H * W), refined)
        assert score[refined].min() >= score[rest].max()
    assert 0 < len(refined) < H * W                    # the scene has edges and flat parts
    # Refined: the full render's pixels. The rest: the coarse pass upsampled.
    got, got_z = _rows(res.image_float), res.depth.reshape(-1)
    assert np.abs(got[refined] - _rows(full.image_float)[refined]).max() <= tol
    assert np.abs(got_z[refined] - full.depth.reshape(-1)[refined]).max() <= tol
    interp = cv2.INTER_CUBIC if s.upsample == "cubic" else cv2.INTER_LINEAR
    up = _rows(np.clip(cv2.resize(rgb_c, (W, H), interpolation=interp), 0, 1))
    up_z = cv2.resize(depth_c, (W, H), interpolation=cv2.INTER_LINEAR).reshape(-1)
    rest = np.setdiff1d(np.arange(H * W), refined)
    np.testing.assert_array_equal(got[rest], up[rest])
    np.testing.assert_array_equal(got_z[rest], up_z[rest])


def test_refine_error_shrinks_with_the_budget(rt, scene, full, tol):
    errs = [np.abs(rt.render(scene, _pose(scene), height=H, width=W, depth=True, refine=0.0,
                             refine_budget=b).image_float - full.image_float).mean()
            for b in (0.05, 0.3, 1.0)]
    assert errs[0] > errs[1] > errs[2] and errs[2] <= tol


def test_refine_with_scale_workers_and_a_pose_that_sees_nothing(model_dir, rt, scene, full, tol):
    res = rt.render(scene, _pose(scene), height=H, width=W, depth=True, quality="adaptive",
                    scale=0.5)
    assert res.image.shape == (H, W, 3) and res.work["pixels"] == (H // 2) * (W // 2)
    par = IrisRuntime(model_dir, threads=2, workers=2)
    a = par.render(scene, _pose(scene), height=H, width=W, depth=True, refine=0.0, chunk_rays=16)
    assert np.abs(a.image_float - full.image_float).max() <= tol
    away = scene.world_from_cam[0].copy()
    away[:3, :3] = away[:3, :3] @ np.diag([-1.0, 1.0, -1.0])
    res = rt.render(scene, away, height=8, width=8, depth=True, quality="adaptive",
                    depth_window=2)
    assert res.work["calls"] == 0 and (res.depth == 0).all()
    assert np.isfinite(res.image_float).all()


def test_progress_covers_both_passes(rt, scene):
    calls = []
    rt.render(scene, _pose(scene), height=H, width=W, quality="adaptive",
              progress=lambda d, t: calls.append((d, t)))
    done = [d for d, _ in calls]
    assert done == sorted(done) and calls[-1][0] == calls[-1][1]
    assert all(d <= t for d, t in calls)


# ----------------------------------------------------------------------------------------------
# Depth-guided samples
# ----------------------------------------------------------------------------------------------

def test_depth_guided_keeps_exact_rays_exact(rt, scene, full, marches, tol):
    rt.render(scene, _pose(scene), height=H, width=W, depth_window=3, depth_mass=0.0)
    # A fallback threshold that some coarse rays pass and some do not.
    mass = marches[0][1].mass
    cut = float(np.median(mass[mass > 0]))
    res = rt.render(scene, _pose(scene), height=H, width=W, depth=True, depth_window=3,
                    depth_mass=cut)
    (coarse_plan, coarse), (fine_plan, _) = marches[2:]
    assert coarse_plan.mode_radius == pytest.approx(3.5 * (rt.far - rt.near) / rt.samples)
    win = np.empty((H * W, 2), np.int64)
    win[fine_plan.pixel_index] = fine_plan.sample_window
    h, w = adaptive.coarse_size(H, W, 0.25)
    z_bins = coarse_plan.z_bins
    expected = adaptive.depth_windows(coarse.mode.reshape(h, w), coarse.mass.reshape(h, w), H, W,
                                      z_bins, 3, cut)
    np.testing.assert_array_equal(win, expected)
    every = (win[:, 0] == 0) & (win[:, 1] == rt.samples)
    windowed = int((~every).sum())
    assert res.work["windowed_rays"] == windowed and res.work["refined_rays"] == H * W
    assert res.work["kept_samples"] == int((win[:, 1] - win[:, 0]).sum())
    assert every.any() and windowed > 0
    assert np.abs(_rows(res.image_float)[every] - _rows(full.image_float)[every]).max() <= tol
    assert np.abs(res.depth.reshape(-1)[every] - full.depth.reshape(-1)[every]).max() <= tol
    assert res.work["kept_samples"] < H * W * rt.samples


def test_a_window_of_every_sample_is_the_full_render(rt, scene, full, tol):
    res = rt.render(scene, _pose(scene), height=H, width=W, depth=True, depth_window=rt.samples,
                    depth_mass=0.0)
    assert res.work["windowed_rays"] == 0
    assert np.abs(res.image_float - full.image_float).max() <= tol
    assert np.abs(res.depth - full.depth).max() <= tol


def test_depth_guided_with_refine_marches_the_refined_pixels_windowed(rt, scene, marches):
    res = rt.render(scene, _pose(scene), height=H, width=W, depth=True, refine=0.0,
                    refine_budget=0.3, depth_window=2, depth_mass=0.0)
    (_, _), (fine_plan, _) = marches
    assert fine_plan.sample_window is not None
    assert len(fine_plan.pixel_index) == res.work["refined_rays"] == 144
    assert 0 < res.work["windowed_rays"] <= res.work["refined_rays"]
