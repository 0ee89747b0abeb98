"""Tests of the runtime's speed/quality knobs (iris_runtime.quality, IrisRuntime.render keywords).

- exact knobs (culling, the Scene cache, data-parallel workers, chunking, top_k >= views) leave the
  output unchanged up to the renderer's float32 rounding (``tol`` below) of the full render;
- lossy knobs (top_k, samples, scale, int8) give finite output of the right shape, and the error
  against the full render shrinks as k / samples grow;
- the presets exist and map to their documented settings.

Model: ``IRIS_TEST_MODEL_DIR`` (an iris-export output; how these run without torch) or, with torch
installed, a random tiny model exported once per session (with its int8 renderer); every test
runs again on an explicit-colour model (``IRIS_TEST_RGB_MODEL_DIR`` or the random ``tiny-rgb``
export with its int8 renderer), whose renderer calls also carry the reference RGB. Renders are
small (16x16 or 24x24 pixels).
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from iris_runtime import InputError, IrisRuntime

from .conftest import resolve_model_dir
from .tolerances import render_tol
from iris_runtime import quality as Q
from iris_runtime.runtime import QUALITY_PRESETS, RenderSettings


@pytest.fixture(scope="session", params=["tiny", "tiny-rgb"])
def model_dir(request) -> Path:
    """The knobs need the int8 renderer: a model exported with it (or IRIS_TEST_MODEL_DIR), and
    the explicit-colour model (exported with it too, or IRIS_TEST_RGB_MODEL_DIR)."""
    if request.param == "tiny":
        return resolve_model_dir(request, "torch_export_int8")
    return resolve_model_dir(request, "torch_export_rgb", "IRIS_TEST_RGB_MODEL_DIR")


@pytest.fixture(scope="session")
def rt(model_dir) -> IrisRuntime:
    return IrisRuntime(model_dir, threads=1)


@pytest.fixture(scope="session")
def scene(rt):
    """A 6-view scene of smooth random images (so that views disagree but not wildly)."""
    import cv2
    rng = np.random.default_rng(3)
    H, W = rt.image_size
    images = [cv2.resize(rng.integers(0, 256, (8, 8, 3), dtype=np.uint8), (W, H),
                         interpolation=cv2.INTER_CUBIC) for _ in range(6)]
    return rt.encode(images)


def _pose(scene):
    """A target between views 0 and 1 (so that every view matters)."""
    T = scene.world_from_cam[0].copy()
    T[:3, 3] = 0.5 * (scene.world_from_cam[0, :3, 3] + scene.world_from_cam[1, :3, 3]) + 0.01
    return T


@pytest.fixture(scope="session")
def tol(rt, scene):
    """Two renders whose renderer calls differ only in packing (other rays beside a ray, other
    chunks, culled masked samples and views, workers at another thread count): the renderer's
    float32 rounding, which depends on the CPU's kernels and the thread count
    (tests/tolerances.py ``render_tol``: 1.7e-5 for the tiny configs; measured <= 1e-6 here).
    rgb in [0, 1]; a sample or view that should have been kept moves pixels by > 1e-3 (the
    lossy knobs' errors below)."""
    return render_tol(rt.manifest.config, scene.num_views, rt.far)


@pytest.fixture(scope="session")
def full(rt, scene):
    return rt.render(scene, _pose(scene), height=16, width=16, depth=True)


def _err(a, b) -> float:
    return float(np.abs(a.image_float - b.image_float).max())


def _is_exact(s: RenderSettings) -> bool:
    """No lossy knob set (was ``RenderSettings.is_exact``, which only the tests used)."""
    return (s.samples is None and s.top_k is None and s.scale == 1.0
            and s.precision in (None, "float32") and s.refine is None and s.depth_window is None
            and s.field_scale is None)


# ----------------------------------------------------------------------------------------------
# Settings and presets (no model)
# ----------------------------------------------------------------------------------------------

def test_presets_exist_and_map_to_documented_settings():
    assert set(QUALITY_PRESETS) == {"auto", "exact", "balanced", "fast", "adaptive"}
    assert QUALITY_PRESETS["exact"] == RenderSettings() and _is_exact(QUALITY_PRESETS["exact"])
    assert QUALITY_PRESETS["auto"] == RenderSettings(field_scale=0.125, colour_samples=8,
                                                     depth_search=4)
    assert QUALITY_PRESETS["balanced"] == RenderSettings(samples=32, top_k=8, top_k_by="ray")
    assert QUALITY_PRESETS["fast"] == RenderSettings(samples=16, top_k=2, top_k_by="ray",
                                                     scale=0.5, upsample="cubic",
                                                     field_scale=0.125, colour_samples=4)
    assert Q.TWO_SCALE_PRESETS == ("auto", "fast")
    assert QUALITY_PRESETS["adaptive"] == RenderSettings(upsample="cubic", coarse=0.25, refine=0.1,
                                                         refine_budget=0.12)
    for name in ("auto", "balanced", "fast", "adaptive"):
        assert not _is_exact(QUALITY_PRESETS[name])
        assert name in (Q.__doc__ or "") or name in (IrisRuntime.render.__doc__ or "")


def test_resolve_settings_overrides_and_rejects():
    assert Q.resolve_settings() == RenderSettings()
    s = Q.resolve_settings("balanced", samples=48)
    assert s.samples == 48 and s.top_k == QUALITY_PRESETS["balanced"].top_k
    assert Q.resolve_settings("fast", scale=None) == QUALITY_PRESETS["fast"]
    for bad in (dict(quality="fastest"), dict(samples=0), dict(top_k=-1), dict(top_k=2.5),
                dict(top_k_by="pixel"), dict(scale=0.0), dict(scale=1.5), dict(scale=float("nan")),
                dict(upsample="lanczos"), dict(precision="fp16"), dict(samples=True),
                dict(refine=-1.0), dict(coarse=0.0), dict(depth_window=-2)):
        quality = bad.pop("quality", None)
        with pytest.raises(InputError):
            Q.resolve_settings(quality, **bad)


def test_top_k_mask_keeps_the_k_best_valid_views():
    rng = np.random.default_rng(0)
    valid = rng.random((6, 50, 7)) > 0.3
    score = rng.uniform(-1, 1, (6, 50, 7))
    for k in (1, 2, 4, 6, 9):
        m = Q.top_k_mask(valid, score, k)
        assert not (m & ~valid).any()
        np.testing.assert_array_equal(m.sum(0), np.minimum(valid.sum(0), k))
        # every kept view scores at least as high as every valid dropped one
        kept_min = np.where(m, score, np.inf).min(0)
        dropped_max = np.where(valid & ~m, score, -np.inf).max(0)
        assert (kept_min >= dropped_max).all()


def test_ray_view_sets_and_grouping_cover_every_ray_once():
    rng = np.random.default_rng(1)
    valid = rng.random((8, 300, 5)) > 0.4
    score = rng.uniform(-1, 1, valid.shape)
    for k in (1, 2, 3):
        sets = Q.ray_view_sets(valid, score, k)
        assert (sets.sum(0) <= k).all()
        assert not (sets & ~valid.any(2)).any()
        assert (sets.any(0) == valid.any((0, 2))).all()
        calls = Q.group_rays(sets, k, 64)
        rays = np.concatenate([r for r, _ in calls])
        np.testing.assert_array_equal(np.sort(rays), np.arange(300))
        for r, v in calls:
            assert len(r) <= 64 and len(v) <= k
            assert not (sets[:, r] & ~np.isin(np.arange(8), v)[:, None]).any()


# ----------------------------------------------------------------------------------------------
# Exact knobs: unchanged up to float32 rounding
# ----------------------------------------------------------------------------------------------

def test_culling_is_exact(model_dir, scene, full, tol):
    nocull = IrisRuntime(model_dir, threads=1, cull=False)
    res = nocull.render(scene, _pose(scene), height=16, width=16, depth=True)
    assert _err(res, full) <= tol
    assert np.abs(res.depth - full.depth).max() <= tol


def test_full_weight_rays_get_calls_of_their_own(rt, scene):
    """``raymarch.plan_calls`` with culling: every ray that sees anything is in exactly one call;
    the rays whose every sample has full weight in its best view are in calls whose mask needs
    no key bias (the renderer graph's Add-free branch), the others are not mixed into them."""
    from iris_runtime import raymarch
    # Cameras of our own (a row 3 cm apart, looking down +z), not the model's, which on random
    # photos may spread the views so far that no ray stays inside one.
    rig = np.tile(np.eye(4), (scene.num_views, 1, 1))
    rig[:, 0, 3] = 0.03 * np.arange(scene.num_views)
    scene = dataclasses.replace(scene, world_from_cam=rig)
    h = w = 16
    T = _pose(scene)
    c, s = np.cos(0.4), np.sin(0.4)                      # turned away: some rays leave the views
    T[:3, :3] = T[:3, :3] @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    plan = raymarch.MarchPlan.build(
        scene, T, scene.intrinsics(h, w), h, w, samples=rt.samples, near=rt.near,
        far=rt.far, top_k=None, top_k_by="ray", chunk_rays=64, cull=True,
        photos=rt._view_images(scene), empty_rgb=rt._empty_ray_rgb(scene, "renderer"))
    kinds = set()
    for start in range(0, plan.rays, plan.block_rays):
        block = raymarch.trace_block(plan, start)
        best = block.weight.max(axis=0)                                     # [R, S]
        calls = raymarch.plan_calls(plan, block)
        rays = np.concatenate([c.rays for c in calls]) if calls else np.zeros(0, int)
        np.testing.assert_array_equal(np.sort(rays), np.flatnonzero((best > 0).any(axis=1)))
        for c in calls:
            full = (best[c.rays] == 1).all(axis=1)
            assert full.all() or not full.any()
            kinds.add(bool(full[0]))
            mask = block.weight[np.ix_(c.views, c.rays)]
            assert (mask.max(axis=0) == 1).all() == bool(full[0])
    assert kinds == {True, False}                       # the scene has both kinds of rays


def test_culling_skips_work_off_the_views(rt, scene):
    # Looking away from the scene: nothing projects anywhere -> no renderer call at all.
    T = scene.world_from_cam[0].copy()
    T[:3, :3] = T[:3, :3] @ np.diag([-1.0, 1.0, -1.0])
    res = rt.render(scene, T, height=8, width=8, depth=True)
    assert res.work["calls"] == 0 and np.isfinite(res.image_float).all()
    assert (res.depth == 0).all()


def test_workers_chunking_and_scene_cache_are_exact(model_dir, rt, scene, full, tol):
    par = IrisRuntime(model_dir, threads=2, workers=2)
    assert _err(par.render(scene, _pose(scene), height=16, width=16, depth=True,
                           chunk_rays=40), full) <= tol
    assert _err(rt.render(scene, _pose(scene), height=16, width=16, depth=True, chunk_rays=7),
                full) <= tol
    assert _err(rt.render(scene, _pose(scene), height=16, width=16, depth=True,
                          quality="exact"), full) <= tol
    # top_k not below the number of views keeps every view: the full render
    for by in ("point", "ray"):
        res = rt.render(scene, _pose(scene), height=16, width=16, depth=True,
                        top_k=scene.num_views, top_k_by=by)
        assert _err(res, full) <= tol


@pytest.mark.parametrize("by", ["point", "ray"])
def test_dropping_views_under_top_k_is_exact(model_dir, rt, scene, by, tol):
    """With top_k, the views/samples/rays a call drops are exactly the masked ones."""
    nocull = IrisRuntime(model_dir, threads=1, cull=False)
    a = rt.render(scene, _pose(scene), height=16, width=16, depth=True, top_k=2, top_k_by=by)
    b = nocull.render(scene, _pose(scene), height=16, width=16, depth=True, top_k=2, top_k_by=by)
    assert _err(a, b) <= tol
    if by == "ray":
        assert a.work["point_views"] <= 2 * a.work["points"]


def test_select_point_views_keeps_exactly_the_masked_pairs():
    """point_views.select_point_views: every kept (view, point) pair sits once in a group of its
    view, each point's kept views fill its first slots in view order, and nothing else is
    referenced."""
    from iris_runtime.point_views import select_point_views
    rng = np.random.default_rng(3)
    v, r, s = 5, 4, 7
    mask = rng.random((v, r, s)) < 0.5
    mask[:, 0, 0] = False                                       # a point with no view
    feed = {"field_maps": np.zeros((v, 2, 2, 2), np.float32),
            "grid": rng.random((v, r, s, 2)).astype(np.float32),
            "cues": rng.random((v, r, s, 4)).astype(np.float32), "mask": mask,
            "positions": np.zeros((r, s, 3), np.float32), "directions": np.ones((r, 3), np.float32),
            "colours": rng.random((v, r, s, 3)).astype(np.float32)}
    out = select_point_views(feed, group=4)
    K, P, G = out["pairs"].shape[0], *out["grid"].shape[:2]
    counts = mask.reshape(v, -1).sum(1)
    assert K == mask.sum(0).max() and G == 4
    np.testing.assert_array_equal(out["groups"], np.repeat(np.arange(v), -(-counts // 4)))
    assert out["pairs"].dtype == np.int64 and out["mask"].shape == (K, r, s)
    np.testing.assert_array_equal(out["mask"].sum(0), mask.sum(0))
    for i in range(r):
        for j in range(s):
            views = np.flatnonzero(mask[:, i, j])
            held = out["pairs"][:len(views), i, j]
            np.testing.assert_array_equal(out["groups"][held // G], views)   # in view order
            assert not out["mask"][len(views):, i, j].any()
            for name in ("grid", "cues", "colours"):
                got = out[name].reshape(P * G, -1)[held]
                np.testing.assert_array_equal(got, feed[name][views, i, j])


def test_point_top_k_on_selected_views_equals_masking(model_dir, rt, scene, tmp_path):
    """Per-point top-k renders on the renderer that takes each point's own views
    (``renderer_views``): the same image as the view-major renderer with the other views masked
    (a copy of the model without that graph), with fewer (point, view) pairs fed."""
    import json
    import shutil
    if "renderer_views" not in rt.manifest.graphs:
        pytest.skip("this export has no renderer_views graph")
    plain = tmp_path / "plain"
    shutil.copytree(model_dir, plain)
    doc = json.loads((plain / "iris.json").read_text())
    (plain / doc["graphs"].pop("renderer_views")["file"]).unlink()
    (plain / "iris.json").write_text(json.dumps(doc))
    masked = IrisRuntime(plain, threads=1)
    for k in (1, 2):
        a = rt.render(scene, _pose(scene), height=16, width=16, depth=True, top_k=k,
                      top_k_by="point")
        b = masked.render(scene, _pose(scene), height=16, width=16, depth=True, top_k=k,
                          top_k_by="point")
        assert _err(a, b) <= 1e-5
        assert a.work["point_views"] <= k * a.work["points"] < b.work["point_views"]


# ----------------------------------------------------------------------------------------------
# Lossy knobs
# ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kw", [
    dict(samples=16), dict(samples=33), dict(top_k=1, top_k_by="point"), dict(top_k=2),
    dict(scale=0.5), dict(scale=0.5, upsample="cubic"), dict(scale=0.3),
    dict(quality="balanced"), dict(quality="fast"), dict(quality="fast", samples=8),
    dict(quality="adaptive"), dict(quality="adaptive", scale=0.5, top_k=2),
    dict(depth_window=4, depth_mass=0.0), dict(refine=0.0, refine_budget=0.3, depth_window=2)])
def test_lossy_knobs_give_finite_output_of_the_right_shape(rt, scene, kw):
    res = rt.render(scene, _pose(scene), height=16, width=24, depth=True, **kw)
    assert res.image.shape == (16, 24, 3) and res.image.dtype == np.uint8
    assert res.image_float.shape == (16, 24, 3) and np.isfinite(res.image_float).all()
    assert res.depth.shape == (16, 24) and np.isfinite(res.depth).all()
    assert (res.image_float >= 0).all() and (res.image_float <= 1).all()
    want = Q.resolve_settings(kw.pop("quality", None), rt.default_quality, **kw)
    if not rt.manifest.explicit_rgb:                  # presets' two scales: explicit colour only
        want = dataclasses.replace(want, field_scale=None, depth_search=0)
    assert res.settings == want
    img = rt.render(scene, _pose(scene), height=16, width=24, **res.settings.__dict__)
    assert img.shape == (16, 24, 3)


def test_error_shrinks_with_more_views_per_point(rt, scene, full, tol):
    errs = [_err(rt.render(scene, _pose(scene), height=16, width=16, depth=True, top_k=k), full)
            for k in (1, 3, scene.num_views)]
    assert errs[0] > errs[1] > errs[2] and errs[2] <= tol
    calls = [rt.render(scene, _pose(scene), height=16, width=16, depth=True, top_k=k).work
             for k in (1, 3)]
    assert calls[0]["point_views"] < calls[1]["point_views"] < full.work["point_views"]


def test_error_shrinks_with_more_samples(rt, scene, full, tol):
    errs = [_err(rt.render(scene, _pose(scene), height=16, width=16, depth=True, samples=s), full)
            for s in (4, 16, rt.samples)]
    assert errs[0] > errs[1] > errs[2] and errs[2] <= tol


def test_int8_precision_per_call(rt, scene, full):
    if "renderer_int8" not in rt.manifest.graphs:
        pytest.skip("model exported without --quantize int8")
    res = rt.render(scene, _pose(scene), height=16, width=16, depth=True, precision="int8")
    assert np.isfinite(res.image_float).all()
    assert 0 < _err(res, full) < 0.1


# ----------------------------------------------------------------------------------------------
# Against torch
# ----------------------------------------------------------------------------------------------

@pytest.mark.torch
@pytest.mark.parametrize("export", ["torch_export_int8", "torch_export_rgb"])
def test_exact_parallel_path_matches_torch(request, export):
    import torch
    model_dir, model = request.getfixturevalue(export)
    rt = IrisRuntime(model_dir, threads=2, workers=2)
    rng = np.random.default_rng(5)
    images = rng.integers(0, 256, (4, 64, 64, 3), dtype=np.uint8)
    scene = rt.encode(list(images))
    res = rt.render(scene, 1, height=16, width=16, depth=True)
    with torch.no_grad():
        ts = model.encode(torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255.0)
        rgb, depth = model.render(ts, ts.world_from_cam[[1]], 16, 16)
    assert np.abs(res.image_float - rgb[0].numpy()).max() <= 1e-4
    assert np.abs(res.depth - depth[0].numpy()).max() <= 1e-4
