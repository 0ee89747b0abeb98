"""Colours from the photos at their own resolution (iris_runtime.colour) and the two-scale render
(iris_runtime.detail): the pyramid and its choice, sampling against a float64 reference, the
model-size render unchanged bit for bit, and two scales against the exact march."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from iris_runtime import IrisRuntime
from iris_runtime import geometry as G
from iris_runtime.colour import (MAX_PHOTO_SIDE, ColourSource, blend_residual, choose_level,
                                 compose, keep_photo, level_sizes, mean_colour)
from iris_runtime.errors import InputError
from iris_runtime.quality import RenderSettings
from iris_runtime.scene import Scene

F32_EPS = float(np.finfo(np.float32).eps)


def _photos(n: int, size: int, seed: int = 0) -> list[np.ndarray]:
    """Smooth random photos with fine stripes: detail above a 64x64 model's resolution."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] / size
    out = []
    for i in range(n):
        base = rng.uniform(0.2, 0.8, 3)
        stripes = 0.5 + 0.5 * np.sin(2 * np.pi * (xx * (size / 6) + yy * (i + 1)))
        img = base[None, None, :] * 0.6 + 0.4 * stripes[..., None] * rng.uniform(0.5, 1.0, 3)
        out.append(np.clip(img * 255, 0, 255).astype(np.uint8))
    return out


# -- the pyramid ------------------------------------------------------------------------------

def test_keep_photo_crops_to_the_model_aspect_and_caps_the_side():
    wide = np.zeros((300, 500, 3), np.uint8)
    wide[:, 100:400] = 200                       # the centre square the model sees
    kept = keep_photo(wide, (64, 64))
    assert kept.shape == (300, 300, 3) and not kept.flags.writeable and (kept == 200).all()
    big = np.full((3000, 2000, 3), 7, np.uint8)
    kept = keep_photo(big, (64, 64))
    assert kept.shape == (MAX_PHOTO_SIDE, MAX_PHOTO_SIDE, 3) and (kept == 7).all()
    small = np.full((40, 40, 3), 9, np.uint8)     # smaller than the model: kept as is
    assert keep_photo(small, (64, 64)).shape == (40, 40, 3)


def test_level_sizes_and_choice():
    assert level_sizes((256, 256), (64, 64)) == [(256, 256), (128, 128), (64, 64)]
    assert level_sizes((480, 480), (64, 64)) == [(480, 480), (240, 240), (120, 120), (64, 64)]
    assert level_sizes((64, 64), (64, 64)) == [(64, 64)]
    assert level_sizes((40, 40), (64, 64)) == [(64, 64)]
    sizes = level_sizes((480, 480), (64, 64))
    assert sizes[choose_level(sizes, (64, 64), 1.0)] == (64, 64)      # the model's own size
    assert sizes[choose_level(sizes, (64, 64), 4.0)] == (240, 240)    # 256 wanted: 240 nearest
    assert sizes[choose_level(sizes, (64, 64), 8.0)] == (480, 480)
    assert sizes[choose_level(sizes, (64, 64), 0.25)] == (64, 64)     # never below the model's


def _bilinear_f64(image: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """Reference: grid_sample(align_corners=False, border) of ``image [h, w, C]`` in float64."""
    h, w = image.shape[:2]
    gx = np.clip(((grid[..., 0] + 1) * w - 1) / 2, 0, w - 1)
    gy = np.clip(((grid[..., 1] + 1) * h - 1) / 2, 0, h - 1)
    x0, y0 = np.floor(gx).astype(int), np.floor(gy).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (gx - x0)[..., None], (gy - y0)[..., None]
    im = image.astype(np.float64)
    return ((im[y0, x0] * (1 - fx) + im[y0, x1] * fx) * (1 - fy)
            + (im[y1, x0] * (1 - fx) + im[y1, x1] * fx) * fy)


def test_colour_source_samples_each_views_level():
    photos = [keep_photo(p, (64, 64)) for p in _photos(2, 256)]
    model = np.stack([cv2.resize(p, (64, 64), interpolation=cv2.INTER_AREA)
                      for p in photos]).transpose(0, 3, 1, 2).astype(np.float32) / 255
    rng = np.random.default_rng(1)
    grid = rng.uniform(-1.1, 1.1, (2, 50, 7, 2)).astype(np.float32)
    # At the model's focal: the model-resolution images, bit for bit as before.
    at_model = ColourSource.build(model, tuple(photos), 1.0)
    assert at_model.sizes == [(64, 64), (64, 64)]
    np.testing.assert_array_equal(at_model.sample(grid, np.arange(2)),
                                  G.sample_bilinear_views(model, grid))
    # At 4x: the 256 photos themselves, against a float64 bilinear reference. The float32
    # interpolation of values <= 255 errs by a few ulps of 255 before the 1/255 scale.
    fine = ColourSource.build(model, tuple(photos), 4.0)
    assert fine.sizes == [(256, 256), (256, 256)]
    got = fine.sample(grid, np.arange(2))
    want = np.stack([_bilinear_f64(p, g) for p, g in zip(photos, grid)]) / 255
    np.testing.assert_allclose(got, want, rtol=0, atol=16 * F32_EPS)
    # Views in another order read their own photos.
    np.testing.assert_array_equal(fine.sample(grid[::-1], np.array([1, 0])), got[::-1])
    # The two-scale reader (cv2.remap, model pixels) reads the same values: against the same
    # float64 reference at both levels, to the same few ulps.
    uv = (grid.reshape(2, -1, 2) + 1) * np.float32(32)                     # model pixels
    for source, images in ((at_model, model.transpose(0, 2, 3, 1)), (fine, np.stack(photos) / 255)):
        read = source.read(uv[..., 0], uv[..., 1])
        want = np.stack([_bilinear_f64(im, g.reshape(-1, 2)) for im, g in zip(images, grid)])
        assert read.shape == (2, 350, 3) and read.dtype == np.float32
        np.testing.assert_allclose(read, want, rtol=0, atol=16 * F32_EPS)


def test_fine_pass_samples_as_the_march_does():
    """The two-scale pass's fused sampler (``detail._sample_colours``: projection, validity, cue
    cosine and the photos read with cv2.remap) against the same quantities computed in float64
    from their definitions: the views' blend and the spread, points in front of, beside and
    behind the views."""
    from iris_runtime.detail import _sample_colours
    rng = np.random.default_rng(3)
    photos = [keep_photo(p, (64, 64)) for p in _photos(3, 256)]
    model = np.stack([cv2.resize(p, (64, 64), interpolation=cv2.INTER_AREA)
                      for p in photos]).transpose(0, 3, 1, 2).astype(np.float32) / 255
    source = ColourSource.build(model, tuple(photos), 4.0)
    K = np.array([[70.0, 0, 32], [0, 70.0, 32], [0, 0, 1]])
    world_from_cam = np.stack([np.eye(4)] * 3)
    for v, angle in enumerate((0.0, 0.15, -0.2)):
        c, s_ = np.cos(angle), np.sin(angle)
        world_from_cam[v, :3, :3] = [[c, 0, s_], [0, 1, 0], [-s_, 0, c]]
        world_from_cam[v, :3, 3] = [0.3 * v, 0.05 * v, -0.1 * v]
    cam_from_world = np.linalg.inv(world_from_cam)
    points = rng.uniform([-1.5, -1.5, -0.5], [1.5, 1.5, 3.0], (500, 3))
    target = np.array([0.1, -0.05, -0.2])
    for angle in (0.0, 0.02):
        mean, spread = _sample_colours(points.astype(np.float32), K.astype(np.float32),
                                       cam_from_world.astype(np.float32), (64, 64), source,
                                       target.astype(np.float32), angle)
        # float64 from the definitions: geometry.project_points / validity / cue_cosine, and
        # the photos read by the float64 bilinear reference.
        uv, z, _ = G.project_points(points, K, cam_from_world, 64, 64)
        weight = G.validity(uv, z, 64, 64)
        grid = G.pixels_to_grid(uv, 64, 64)
        colours = np.stack([_bilinear_f64(p, g) for p, g in zip(photos, grid)]) / 255
        cos = G.cue_cosine(points, target, world_from_cam[:, :3, 3])
        want = mean_colour(colours, weight, cos, angle) if angle else mean_colour(colours, weight)
        m = weight[..., None]
        count = m.sum(axis=0)
        plain = (colours * m).sum(axis=0) / np.maximum(count, 1)
        var = (m * (colours - plain) ** 2).sum(axis=(0, 2)) / np.maximum(count[:, 0], 1e-12)
        want_spread = np.where(count[:, 0] > 1, var, 0)
        assert 0 < (count[:, 0] > 1).mean() < 1            # seen by several views, and not
        # float32 positions: a projection of points O(1) through a focal of 70 px rounds to a
        # few ulps of 70 px, read at 4 level pixels a model pixel on stripes of slope < 2.
        tol = 70 * 8 * F32_EPS
        np.testing.assert_allclose(mean, want, rtol=0, atol=tol)
        np.testing.assert_allclose(spread, want_spread, rtol=0, atol=2 * tol)


def _plane_photos(centres: np.ndarray, K: np.ndarray, size: int, plane_z: float) -> list:
    """Photos ``size`` x ``size`` of a textured plane at world z = ``plane_z`` seen by cameras at
    ``centres [V, 3]`` looking along +z (``K`` in the model's 64x64 pixels): a sum of
    incommensurate waves, period several model pixels, so the views agree at the plane's depth
    and nowhere near it."""
    out = []
    scale = size / 64
    px = (np.arange(size) + 0.5) / scale                                   # model pixels
    u, v = np.meshgrid(px, px)
    for c in centres:
        x = c[0] + (u - K[0, 2]) / K[0, 0] * (plane_z - c[2])
        y = c[1] + (v - K[1, 2]) / K[1, 1] * (plane_z - c[2])
        tex = np.stack([np.sin(41 * x + 3 * y), np.sin(29 * y - 7 * x + 1), np.sin(37 * (x + y))])
        out.append(np.clip((0.5 + 0.4 * tex.transpose(1, 2, 0)) * 255, 0, 255).astype(np.uint8))
    return out


def test_depth_search_finds_the_plane_the_views_agree_on():
    """``detail.search_depth`` on three views of a textured plane: samples put up to 3.7 bins off
    the plane (either side) come back to it, to the search's finest step; a sample on the
    plane stays; the spread at the found depth is the least among its neighbours, and the
    one-pass spread is the fine pass's."""
    from iris_runtime import detail
    from iris_runtime.detail import SEARCH_STEPS, _sample_colours, _spread, search_depth
    K = np.array([[70.0, 0, 32], [0, 70.0, 32], [0, 0, 1]], np.float32)
    centres = np.array([[-0.2, 0.0, 0.0], [0.0, 0.05, 0.0], [0.2, 0.0, 0.0]])
    plane = 1.0
    photos = _plane_photos(centres, K, 256, plane)
    model = np.stack([cv2.resize(p, (64, 64), interpolation=cv2.INTER_AREA)
                      for p in photos]).transpose(0, 3, 1, 2).astype(np.float32) / 255
    source = ColourSource.build(model, tuple(photos), 4.0)
    world_from_cam = np.stack([np.eye(4)] * 3).astype(np.float32)
    world_from_cam[:, :3, 3] = centres
    cam_from_world = np.linalg.inv(world_from_cam).astype(np.float32)
    target = np.eye(4, dtype=np.float32)
    target[:3, 3] = [0.1, 0.02, 0.0]
    rng = np.random.default_rng(5)
    uv = rng.uniform(22, 42, (200, 2)).astype(np.float32)           # seen whole by every view
    origins, directions = G.rays_from_pixels(uv, K, target)
    z_bins = G.sample_depths(0.1, 1.9, 128, 1, dtype=np.float32)[0]        # bins of 1/71
    dz = float(z_bins[1] - z_bins[0])
    offset = rng.uniform(-3.7, 3.7, 200).astype(np.float32) * dz
    offset[:20] = 0.0                                                     # already on the plane
    z = (plane + offset).astype(np.float32)
    _, spread = _sample_colours(origins + z[:, None] * directions, K, cam_from_world, (64, 64),
                                source, target[:3, 3], 0.0)

    def search(bins=4):
        return search_depth(origins, directions, z, spread, z_bins, bins, K, cam_from_world,
                            (64, 64), source)
    # Without the tie-break towards the given depth: the plane, to the finest step.
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(detail, "SEARCH_PRIOR", 0.0)
        found = search()
    assert found.dtype == np.float32 and found.shape == (200,)
    assert (np.abs(found - plane) <= SEARCH_STEPS[-1] * dz + 1e-6).all()
    np.testing.assert_array_equal(found[:20], z[:20])
    # With it, a ray whose views agree almost as well a bin off may stop short of the plane
    # (where its texture runs along the baselines); by less than a bin.
    found = search()
    assert (np.abs(found - plane) < dz).all() and np.median(np.abs(found - plane)) < dz / 4
    np.testing.assert_array_equal(found[:20], z[:20])
    # No step of the finest size does better, and _spread is the fine pass's spread.
    rot, shift = cam_from_world[:, :3, :3], cam_from_world[:, :3, 3]

    def cam(depth):
        points = origins + depth[:, None] * directions
        return np.matmul(points, np.swapaxes(rot, -1, -2)) + shift[:, None, :], points

    def score(depth):
        return (_spread(cam(depth)[0], K, (64, 64), source)
                + detail.SEARCH_PRIOR * ((depth - z) / dz) ** 2)
    at_found = _spread(cam(found)[0], K, (64, 64), source)
    np.testing.assert_allclose(
        at_found, _sample_colours(cam(found)[1], K, cam_from_world, (64, 64), source,
                                  target[:3, 3], 0.0)[1], rtol=0, atol=1e-5)
    step = SEARCH_STEPS[-1] * dz
    for k in (-1, 1):
        assert (score(found) <= score(found + k * step) + 1e-7).all()
    # Nothing to search, or no bins to move: the depths as given.
    assert search_depth(origins[:0], directions[:0], z[:0], spread[:0], z_bins, 4, K,
                        cam_from_world, (64, 64), source).shape == (0,)
    np.testing.assert_array_equal(search(0), z)


def test_blend_residual_composes_back():
    rng = np.random.default_rng(2)
    rgb = rng.uniform(0.01, 0.99, (100, 3)).astype(np.float32)
    blend = rng.uniform(0.0, 1.0, (100, 3)).astype(np.float32)
    r = blend_residual(rgb, blend)
    # sigmoid(logit(b) + r) = rgb: float32 logit/sigmoid round trip, a few ulps of O(1) values.
    np.testing.assert_allclose(compose(blend, r), rgb, rtol=0, atol=64 * F32_EPS)
    assert np.isfinite(blend_residual(np.array([0.0, 1.0, 0.5], np.float32),
                                      np.array([0.0, 1.0, 1.0], np.float32))).all()
    colours = rng.uniform(0, 1, (3, 10, 3)).astype(np.float32)
    mask = np.array([1.0, 0.5, 0.0], np.float32)[:, None].repeat(10, 1)
    want = (colours[0] + 0.5 * colours[1]) / 1.5
    np.testing.assert_allclose(mean_colour(colours, mask), want, rtol=0, atol=4 * F32_EPS)


def test_mean_colour_weights_views_by_angle():
    """blend_angle: the views looking along the target ray lead; fades, extremes and the plain
    limit as documented (against the formula written out in float64)."""
    rng = np.random.default_rng(4)
    V, P = 4, 50
    colours = rng.uniform(0, 1, (V, P, 3)).astype(np.float32)
    mask = rng.choice([0.0, 0.3, 1.0], (V, P)).astype(np.float32)
    cos = rng.uniform(-1, 1, (V, P)).astype(np.float32)
    for angle in (0.3, 0.02):
        a = mask * np.exp((cos.astype(np.float64) - 1) / angle)
        want = ((colours * a[..., None]).sum(0) / np.maximum(a.sum(0), 1e-300)[..., None]
                * np.minimum(mask.sum(0), 1)[..., None])
        np.testing.assert_allclose(mean_colour(colours, mask, cos, angle), want, rtol=0,
                                   atol=16 * F32_EPS)
    # A very wide angle is the plain mean; the view along the ray takes over a narrow one.
    np.testing.assert_allclose(mean_colour(colours, mask, cos, 1e6), mean_colour(colours, mask),
                               rtol=0, atol=16 * F32_EPS)
    full = np.ones((V, P), np.float32)
    along = np.where(np.arange(V)[:, None] == 2, 1.0, 0.5).astype(np.float32) * full
    np.testing.assert_allclose(mean_colour(colours, full, along, 1e-3), colours[2], rtol=0,
                               atol=16 * F32_EPS)
    # One view at half validity fades to half its colour, as in the plain mean.
    half = np.zeros((V, P), np.float32)
    half[1] = 0.5
    np.testing.assert_allclose(mean_colour(colours, half, cos, 0.01), 0.5 * colours[1], rtol=0,
                               atol=4 * F32_EPS)
    # Far angles beside an unseeing view along the ray: no underflow to 0/0, no warning.
    far = np.full((V, P), -1.0, np.float32)
    far[0] = 1.0
    seen = np.ones((V, P), np.float32)
    seen[0] = 0.0
    with np.errstate(all="raise"):
        out = mean_colour(colours, seen, far, 1e-4)
    np.testing.assert_allclose(out, mean_colour(colours, seen), rtol=0, atol=16 * F32_EPS)
    nobody = mean_colour(colours, np.zeros((V, P), np.float32), cos, 0.01)
    assert np.isfinite(nobody).all() and not nobody.any()


def test_settings_of_two_scales_are_checked():
    RenderSettings(field_scale=0.25, colour_samples=4)
    for bad in (0.0, 1.5, float("nan"), "x"):
        with pytest.raises(InputError, match="field_scale"):
            RenderSettings(field_scale=bad)
    with pytest.raises(InputError, match="colour_samples"):
        RenderSettings(field_scale=0.5, colour_samples=0)
    with pytest.raises(InputError, match="field_scale"):
        RenderSettings(field_scale=0.5, refine=0.1)
    for bad in (-1, 1.5, True, None):
        with pytest.raises(InputError, match="depth_search"):
            RenderSettings(field_scale=0.5, depth_search=bad)
    with pytest.raises(InputError, match="depth_search"):
        RenderSettings(depth_search=2)                      # moves two scales' samples only
    # A coarse-to-fine march asked of the default preset drops its two scales and the search.
    from iris_runtime.quality import resolve_settings
    assert resolve_settings(None, "auto").depth_search > 0
    assert resolve_settings(None, "auto", refine=0.1).depth_search == 0


# -- the runtime ------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def rt(rgb_model_dir):
    return IrisRuntime(rgb_model_dir, threads=1)


@pytest.fixture(scope="module")
def scenes(rt):
    """The same four views encoded from 256x256 photos and from their 64x64 copies."""
    photos = _photos(4, 256, seed=3)
    large = rt.encode(photos, cameras="model")
    small = rt.encode([cv2.resize(p, (64, 64), interpolation=cv2.INTER_AREA) for p in photos],
                      cameras="model")
    return large, small


def test_encode_keeps_the_photos(rt, scenes):
    large, small = scenes
    assert [p.shape for p in large.photos] == [(256, 256, 3)] * 4
    assert [p.shape for p in small.photos] == [(64, 64, 3)] * 4
    np.testing.assert_array_equal(large.reference_images, small.reference_images)
    sub = large.subset([2, 0])
    assert all(a is b for a, b in zip(sub.photos, large.photos))   # not copied again


def test_model_size_render_reads_the_model_images(rt, scenes):
    """At the model's size the 256 photos change nothing: the same bits as 64x64 photos."""
    large, small = scenes
    for kw in ({}, {"quality": "fast"}, {"height": 48, "width": 48}):
        np.testing.assert_array_equal(rt.render(large, 1, **kw), rt.render(small, 1, **kw))


def test_large_renders_read_the_photos(rt, scenes):
    """At 128x128 the colours come from the 256 photos: the fine stripes reach the render."""
    large, small = scenes
    kw = dict(height=128, width=128, depth=True, field_scale=0.25, colour_samples=4)
    a = rt.render(large, 1, **kw).image_float
    b = rt.render(small, 1, **kw).image_float
    assert np.isfinite(a).all() and np.abs(a - b).max() > 0.05
    # High frequencies: the 128 render from 256 photos has more energy above the 64 grid's
    # Nyquist than the one from 64x64 photos.
    def high(x):
        return np.abs(x - cv2.GaussianBlur(x, (0, 0), 1.5)).mean()
    assert high(a) > 1.5 * high(b)


def test_two_scales_at_full_scale_with_every_bin_is_the_exact_march(rt, scenes):
    large, _ = scenes
    pose = large.world_from_cam[1]
    exact = rt.render(large, pose, height=72, width=72, depth=True, quality="exact")
    two = rt.render(large, pose, height=72, width=72, depth=True, field_scale=1.0,
                    colour_samples=rt.samples, depth_search=0)
    assert two.work["coarse_rays"] == 72 * 72            # marched at two scales
    # The same weights, colours and residual recomposed in float32: a blend of 64 samples and a
    # logit/sigmoid round trip, each a few ulps of O(1) values.
    np.testing.assert_allclose(two.image_float, exact.image_float, rtol=0, atol=256 * F32_EPS)
    np.testing.assert_allclose(two.depth, exact.depth, rtol=0, atol=64 * F32_EPS)


def test_two_scales_are_close_and_finite(rt, scenes):
    large, _ = scenes
    pose = large.world_from_cam[2]
    exact = rt.render(large, pose, height=80, width=80, depth=True, quality="exact")
    two = rt.render(large, pose, height=80, width=80, depth=True, field_scale=0.5,
                    colour_samples=8)
    assert two.image.shape == (80, 80, 3) and np.isfinite(two.depth).all()
    assert two.work["coarse_rays"] == 40 * 40 and "colour" in two.timings
    # At or below the model's resolution two scales do not apply: the exact march, bit for bit.
    np.testing.assert_array_equal(rt.render(large, pose, height=64, width=64, field_scale=0.5),
                                  rt.render(large, pose, height=64, width=64))
    # Lossy, but close on a smooth random scene: mean error well under a grey level of 8/255.
    assert np.abs(two.image_float - exact.image_float).mean() < 8 / 255


def test_depth_search_moves_only_where_the_views_disagree(rt, scenes):
    """The default's depth search changes a render of textured photos, finite, and not one of
    photos of one flat colour: its views agree at every depth, so no sample moves."""
    large, _ = scenes
    pose = large.world_from_cam[2]
    kw = dict(height=96, width=96, depth=True)
    searched, plain = rt.render(large, pose, **kw), rt.render(large, pose, depth_search=0, **kw)
    assert searched.settings.depth_search > 0 and np.isfinite(searched.image_float).all()
    assert np.abs(searched.image_float - plain.image_float).max() > 1 / 255
    flat = rt.encode([np.full((256, 256, 3), 120, np.uint8)] * 3, cameras="model")
    np.testing.assert_array_equal(rt.render(flat, 1, **kw).image,
                                  rt.render(flat, 1, depth_search=0, **kw).image)


def test_two_scales_need_explicit_colour(model_dir):
    """Asked for by name on a model whose colour comes from its field: an error. In a preset:
    the preset without it ("auto" is then "exact")."""
    rt = IrisRuntime(model_dir, threads=1)
    scene = rt.encode(_photos(2, 64), cameras="model")
    with pytest.raises(InputError, match="field_scale"):
        rt.render(scene, 0, field_scale=0.5)
    with pytest.raises(InputError, match="field_scale"):
        rt.render(scene, 0, quality=RenderSettings(field_scale=0.5))
    with pytest.raises(InputError, match="depth_search"):
        rt.render(scene, 0, depth_search=2)
    kw = dict(height=72, width=72, depth=True)
    auto = rt.render(scene, 0, **kw)
    assert auto.settings.field_scale is None
    np.testing.assert_array_equal(auto.image, rt.render(scene, 0, quality="exact", **kw).image)
    assert rt.render(scene, 0, quality="fast", **kw).settings.field_scale is None


def test_scene_photos_are_checked(scenes):
    large, _ = scenes
    args = (large.field_maps, large.world_from_cam, large.focal, large.K, large.image_size)
    refs = large.reference_images
    with pytest.raises(InputError, match="photos"):
        Scene(*args, reference_images=refs, photos=large.photos[:2])
    with pytest.raises(InputError, match=r"photos\[0\]"):
        Scene(*args, reference_images=refs, photos=(np.zeros((10, 20, 3), np.uint8),) * 4)
    with pytest.raises(InputError, match=r"photos\[1\]"):
        Scene(*args, reference_images=refs,
              photos=(large.photos[0], np.zeros((64, 64, 3), np.float32)) + large.photos[2:])
    with pytest.raises(InputError, match="photos"):
        Scene(*args, photos=large.photos)


# -- poses and sizes ---------------------------------------------------------------------------

def test_a_far_pose_is_refused_not_a_black_frame(rt, scenes):
    large, _ = scenes
    pose = np.eye(4)
    for far in (1e300, 1e6):
        pose[0, 3] = far
        with pytest.raises(InputError, match=r"pose: camera centre .*MAX_POSE_DISTANCE"):
            rt.render(large, pose)
    pose[0, 3] = 5.0                                   # far but within reach: a finite frame
    assert np.isfinite(rt.render(large, pose, depth=True).image_float).all()


def test_a_wide_output_widens_the_view(rt, scenes):
    """A 48x96 output keeps the square render's focal in pixels: its centre 48x48 is the 48x48
    render (the same rays; only the blocks' float rounding differs)."""
    large, _ = scenes
    pose = large.world_from_cam[1]
    wide = rt.render(large, pose, height=48, width=96, quality="exact", depth=True)
    square = rt.render(large, pose, height=48, width=48, quality="exact", depth=True)
    K_wide, K_square = large.intrinsics(48, 96), large.intrinsics(48, 48)
    assert K_wide[0, 0] == K_square[0, 0] and K_wide[1, 1] == K_square[1, 1]
    np.testing.assert_allclose(wide.image_float[:, 24:72], square.image_float, rtol=0,
                               atol=64 * F32_EPS)
