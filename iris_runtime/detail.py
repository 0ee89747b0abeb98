"""Two scales: the field decides the geometry at a coarse resolution, the photos give the colour
at the output's (numpy; no renderer call).

An explicit-colour renderer's colour is ``sigmoid(logit(sum_s w_s mean_s) + r)``: blend weights
``w`` over the ray's depth bins and a residual ``r`` from the field, ``mean_s`` the references'
colours where sample ``s`` projects (``iris_runtime.colour``). The expensive part, the field, is
what decides ``w`` and ``r``; the colours are a projection and a bilinear read. So a render at
``field_scale`` marches the field on a coarse grid (``raymarch.MarchPlan(keep_weights=True)``:
each coarse ray's ``w`` over the bins and ``r``), and ``compose_fine`` makes every output pixel
from its own ray:

1. **Geometry from the coarse rays around it.** Each of the (up to) four coarse rays whose
   centres surround the pixel is a candidate: its weights pooled into windows of consecutive
   depth bins (``ray_windows``), its ``colour_samples`` heaviest windows (rescaled to its total
   weight), and its residual.
2. **Colour through that geometry.** The pixel's own ray is sampled once per window its
   candidates keep, at their centre of mass there, every sample projected into every reference
   view and read from the photos at the output's scale (``colour.ColourSource``), averaged over
   the views as the renderer averages them.
3. **Edges by agreement.** Across a depth edge the candidates disagree: the wrong one puts the
   pixel's samples where the views see different things. Each candidate is weighted by its
   bilinear weight times ``exp(-spread / CONSISTENCY)``, ``spread`` the weighted variance of the
   views' colours over its samples (photo-consistency). Where candidates agree this is the
   bilinear upsampling of the coarse colour formula; at edges it follows the candidate whose
   depth the photos confirm, without a guide image of the target.
4. **Depth from the photos, near the field's** (``depth_search`` bins, 0: off). A coarse ray's
   window holds one depth for the 8 x 8 output pixels around it (at ``auto``'s eighth), and
   the field's weights are soft: the photos, read at the output's scale, are sharp. Each sample
   whose views disagree (spread at least ``SEARCH_SPREAD``) is moved, within ``depth_search``
   bins of where step 2 put it, to where they agree best (``search_depth``: a plane sweep
   along the pixel's own ray, bounded by the field's geometry; samples under ``SEARCH_SHARE``
   of the pixel's weight stay). Where the views already agree the sample stays; a textureless
   wall gives no reason to move and no colour to gain. The
   field's prior keeps the search local: a wide sweep of the photos alone finds repeated
   textures (docs/TRAINING.md, "What the photos alone say of the depth").

With ``field_scale`` 1 and ``colour_samples`` = every bin the result is the exact march's, up to
float rounding (tested). What the lossy steps cost in ground-truth PSNR and what they save in
time is measured by ``benchmarks/two_scale.py`` (docs/PERFORMANCE.md, "Two scales").
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import geometry as G
from .colour import ColourSource, compose, mean_colour

__all__ = ["CONSISTENCY", "FINE_BLOCK", "SEARCH_PRIOR", "SEARCH_SHARE", "SEARCH_SPREAD",
           "SEARCH_STEPS", "WINDOW_FLOOR", "CoarseField", "compose_fine", "ray_windows",
           "search_depth"]

f32 = np.float32

#: Colour variance (summed over RGB, colours in [0, 1]) at which a candidate geometry's weight
#: drops by 1/e: photo noise and texture within a pixel stay well below it, two different
#: surfaces seen by the views well above it.
CONSISTENCY = 0.003
#: Of a coarse ray's M heaviest windows (when M is less than all of them), those holding less
#: than this share of its weight are left out (the others rescaled to its total): most rays put
#: their weight in a few windows, and each window left out saves a sample per output pixel and
#: view. ``benchmarks/two_scale.py`` measures the error against the exact march with it.
WINDOW_FLOOR = 0.02
#: ``depth_search`` leaves a sample where the field put it when its views' colour spread (as
#: ``CONSISTENCY``'s) is below ``SEARCH_SPREAD`` -- they already agree, so moving it changes
#: little of its colour -- or when it holds less than ``SEARCH_SHARE`` of its pixel's weight.
#: Together they cut the search's time sixfold for 0.04 dB (docs/PERFORMANCE.md, "Depth from
#: the photos").
SEARCH_SPREAD = 5e-4
SEARCH_SHARE = 0.05
#: ``depth_search``'s tie-break towards the field's depth: spread added per squared bin moved
#: (two depths the views agree on equally well: the nearer to the field's wins).
SEARCH_PRIOR = 1e-5
#: ``depth_search``'s steps, in depth bins: every multiple of the first within the search's
#: span, then one step of each next on either side of the best so far.
SEARCH_STEPS = (1.0, 0.5)
#: Output rays composed at once: bounds the (ray, bin, view) arrays of a block to ~100 MB.
FINE_BLOCK = 8192


@dataclass(frozen=True, eq=False)
class CoarseField:
    """What the coarse march leaves for the fine pass (``raymarch.MarchResult`` with weights).

    size:     (h, w)               the coarse grid, row-major
    weights:  float32 [h*w, S]     blend weights over the depth bins
    residual: float32 [h*w, 3]     the colour head's residual
    depth:    float32 [h*w]        soft depth
    """
    size: tuple[int, int]
    weights: np.ndarray
    residual: np.ndarray
    depth: np.ndarray


def compose_fine(coarse: CoarseField, height: int, width: int, K: np.ndarray,
                 world_from_cam: np.ndarray, z_bins: np.ndarray, ref_K: np.ndarray,
                 cam_from_world: np.ndarray, image_size: tuple[int, int],
                 colours: ColourSource, colour_samples: int,
                 consistency: float | None = None, blend_angle: float = 0.0,
                 depth_search: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The ``height`` x ``width`` render (intrinsics ``K`` in its pixels, pose
    ``world_from_cam``) from ``coarse``: rgb float32 [H*W, 3] and depth float32 [H*W].
    ``z_bins [S]``: the march's depth bins; ``ref_K``, ``cam_from_world [V, 4, 4]``,
    ``image_size``: the references (model pixels); ``colours``: their photos at the output's
    scale; ``colour_samples``: depth windows kept per coarse ray (``ray_windows``);
    ``consistency``: the spread scale of the candidates' weights (None: ``CONSISTENCY``);
    ``blend_angle``: the model's angular weighting of the views (``colour.mean_colour``);
    ``depth_search``: bins each sample may move to where its views agree (0: off;
    ``search_depth``)."""
    tau = f32(CONSISTENCY if consistency is None else consistency)
    hc, wc = coarse.size
    pooled, centre = ray_windows(coarse.weights, z_bins, colour_samples)      # [Nc, nW] each
    M = min(max(1, int(colour_samples)), pooled.shape[1])
    win = np.argpartition(-pooled, M - 1, axis=1)[:, :M] if M < pooled.shape[1] else \
        np.broadcast_to(np.arange(M), (len(pooled), M))
    top = np.take_along_axis(pooled, win, axis=1)
    total = pooled.sum(axis=1, keepdims=True)
    if M < pooled.shape[1]:           # already lossy: every window kept stays exact
        top = np.where(top >= f32(WINDOW_FLOOR) * total, top, f32(0))
    kept = top.sum(axis=1, keepdims=True)
    top = top * np.where(kept > 0, total / np.where(kept > 0, kept, 1), 0).astype(f32)
    n_win = pooled.shape[1]

    n = height * width
    rgb, depth = np.empty((n, 3), f32), np.empty(n, f32)
    K32, pose32 = K.astype(f32), world_from_cam.astype(f32)
    for start in range(0, n, FINE_BLOCK):
        rows = np.arange(start, min(n, start + FINE_BLOCK))
        R = len(rows)
        cand, bilinear = _candidates(rows, height, width, hc, wc)              # [R, 4] each
        uv = np.stack([rows % width, rows // width], axis=-1).astype(f32) + f32(0.5)
        origins, directions = G.rays_from_pixels(uv, K32, pose32)
        # One sample per (ray, window) in the union of its candidates' kept windows, at the
        # candidates' centre of mass in that window (their bilinear weights times their mass).
        cand_win, cand_w = win[cand], top[cand]                                # [R, 4, M]
        marks = np.zeros((R, n_win), bool)
        used = cand_w.reshape(-1) > 0
        marks[np.repeat(np.arange(R), cand_w[0].size)[used], cand_win.reshape(-1)[used]] = True
        ray, j = np.nonzero(marks)                                             # P samples
        mass = pooled[cand[ray], j[:, None]] * (bilinear[ray] + f32(1e-6))     # [P, 4]
        z = ((mass * centre[cand[ray], j[:, None]]).sum(axis=1)
             / np.maximum(mass.sum(axis=1), f32(1e-30)))
        points = origins[ray] + z[:, None] * directions[ray]                   # [P, 3]
        mean, spread = _sample_colours(points, ref_K, cam_from_world, image_size, colours,
                                       pose32[:3, 3], blend_angle)
        if depth_search:
            weight = mass.sum(axis=1)                    # the sample's share of its pixel
            share = weight / np.maximum(np.bincount(ray, weight, R)[ray], f32(1e-30))
            search = np.nonzero((spread >= f32(SEARCH_SPREAD)) & (share >= f32(SEARCH_SHARE)))[0]
            found = search_depth(origins[ray[search]], directions[ray[search]], z[search],
                                 spread[search], z_bins, depth_search, ref_K, cam_from_world,
                                 image_size, colours)
            changed = found != z[search]
            moved = search[changed]
            if len(moved):
                points = origins[ray[moved]] + found[changed, None] * directions[ray[moved]]
                mean[moved], spread[moved] = _sample_colours(
                    points, ref_K, cam_from_world, image_size, colours, pose32[:3, 3], blend_angle)
        slot = np.zeros((R, n_win), np.intp)
        slot[ray, j] = np.arange(len(ray))
        p = slot[np.arange(R)[:, None, None], cand_win]                        # [R, 4, M]
        blend = np.einsum("rkm,rkmc->rkc", cand_w, mean[p])                   # [R, 4, 3]
        weight = cand_w.sum(axis=2)                                            # [R, 4]
        disagreement = (cand_w * spread[p]).sum(axis=2) / np.maximum(weight, f32(1e-12))
        colour = compose(blend, coarse.residual[cand])                         # [R, 4, 3]
        alpha = bilinear * np.exp(-disagreement / tau)
        norm = alpha.sum(axis=1, keepdims=True)
        alpha = np.where(norm > 1e-30, alpha / np.where(norm > 1e-30, norm, 1), bilinear)
        rgb[rows] = np.einsum("rk,rkc->rc", alpha, colour)
        depth[rows] = (alpha * coarse.depth[cand]).sum(axis=1)
    return rgb, depth


def search_depth(origins: np.ndarray, directions: np.ndarray, z: np.ndarray,
                 spread: np.ndarray, z_bins: np.ndarray, bins: int, ref_K: np.ndarray,
                 cam_from_world: np.ndarray, image_size: tuple[int, int],
                 colours: ColourSource) -> np.ndarray:
    """Depths float32 [Q] along rays ``origins``, ``directions [Q, 3]`` within ``bins`` depth bins
    of ``z [Q]`` (whose views' spread is ``spread [Q]``) where the views' colours agree best:
    the least spread plus ``SEARCH_PRIOR`` per squared bin from ``z``, over the steps of
    ``SEARCH_STEPS``, clipped to the bins' span. ``z`` itself where nothing does better.
    Along a ray each view's camera coordinates are ``a + z b``: the projection of a candidate
    depth is one multiply-add."""
    best_z = z.astype(f32)
    if len(z) == 0 or bins < 1:
        return best_z
    rot, shift = cam_from_world[:, :3, :3], cam_from_world[:, :3, 3]
    a = np.matmul(origins, np.swapaxes(rot, -1, -2)) + shift[:, None, :]         # [V, Q, 3]
    b = np.matmul(directions, np.swapaxes(rot, -1, -2))                           # [V, Q, 3]
    dz = f32(z_bins[1] - z_bins[0]) if len(z_bins) > 1 else f32(1)
    lo, hi = f32(z_bins[0]), f32(z_bins[-1])
    best = spread.astype(f32)
    for i, step in enumerate(SEARCH_STEPS):
        n = int(bins / step) if i == 0 else 1
        centre = best_z
        for k in [*range(1, n + 1), *range(-1, -n - 1, -1)]:
            depth = np.clip(centre + f32(k * step) * dz, lo, hi)
            score = (_spread(a + depth[None, :, None] * b, ref_K, image_size, colours)
                     + f32(SEARCH_PRIOR) * ((depth - z) / dz) ** 2)
            better = score < best
            best = np.where(better, score, best)
            best_z = np.where(better, depth, best_z)
    return best_z


def _spread(cam: np.ndarray, ref_K: np.ndarray, image_size: tuple[int, int],
            colours: ColourSource) -> np.ndarray:
    """``_sample_colours``' spread float32 [P] of points given in each view's camera coordinates
    ``cam [V, P, 3]`` (to float32 rounding): the variance as the mean square less the squared
    mean, in one pass over the views."""
    weight, sampled = _read_views(cam, ref_K, image_size, colours)
    weight = weight[..., None]                                                 # [V, P, 1]
    count = weight.sum(axis=0)                                                 # [P, 1]
    inv = f32(1) / np.maximum(count, f32(1e-12))
    mean = (sampled * weight).sum(axis=0) * inv
    var = _sum3((sampled * sampled * weight).sum(axis=0) * inv - mean * mean)
    return np.where(count[:, 0] > 1.0, np.maximum(var, f32(0)), f32(0))


def ray_windows(weights: np.ndarray, z_bins: np.ndarray, colour_samples: int):
    """Each ray's weights ``[N, S]`` pooled into windows of ``max(1, S // (2 M))`` consecutive
    bins (M = ``colour_samples``; the last window may be shorter): the summed weight and the
    centre of mass of each window (its bins' mean depth where it has no weight) ->
    float32 [N, nW] each. A model that spreads its weights along the ray loses less of them to
    the M heaviest windows than to the M heaviest bins (``benchmarks/two_scale.py`` measures
    what either costs against the exact march)."""
    S = z_bins.shape[0]
    size = max(1, S // (2 * max(1, int(colour_samples))))
    starts = np.arange(0, S, size)
    w = weights.astype(f32)
    pooled = np.add.reduceat(w, starts, axis=1)
    moment = np.add.reduceat(w * z_bins.astype(f32)[None], starts, axis=1)
    middle = np.add.reduceat(z_bins.astype(f32), starts) / np.diff(np.append(starts, S))
    centre = np.where(pooled > 0, moment / np.where(pooled > 0, pooled, 1), middle[None])
    return pooled, centre.astype(f32)


def _candidates(rows: np.ndarray, height: int, width: int, hc: int, wc: int):
    """For output pixels ``rows`` (row-major), the four coarse pixels whose centres surround
    each one's centre (border-clamped) and their bilinear weights: int [R, 4], float32 [R, 4]."""
    i, j = rows // width, rows % width
    cy = np.clip((i + 0.5) * (hc / height) - 0.5, 0.0, hc - 1.0)
    cx = np.clip((j + 0.5) * (wc / width) - 0.5, 0.0, wc - 1.0)
    y0, x0 = np.floor(cy).astype(np.intp), np.floor(cx).astype(np.intp)
    y1, x1 = np.minimum(y0 + 1, hc - 1), np.minimum(x0 + 1, wc - 1)
    fy, fx = (cy - y0).astype(f32), (cx - x0).astype(f32)
    cand = np.stack([y0 * wc + x0, y0 * wc + x1, y1 * wc + x0, y1 * wc + x1], axis=1)
    bilinear = np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], axis=1)
    return cand, bilinear


def _sample_colours(points: np.ndarray, ref_K: np.ndarray, cam_from_world: np.ndarray,
                    image_size: tuple[int, int], colours: ColourSource,
                    target_centre: np.ndarray, blend_angle: float):
    """The references' colour float32 [P, 3] at world ``points [P, 3]``, blended over the views
    as the renderer blends them (``colour.mean_colour``: validity, and the angle to the ray from
    ``target_centre`` with ``blend_angle``), and its spread float32 [P]: the validity-weighted
    variance of the views' colours, summed over RGB (0 where fewer than two views see the
    point).

    The projection, validity and cue cosine are those of ``geometry.project_points``,
    ``geometry.validity`` and ``geometry.cue_cosine``, fused for the many samples of a large
    output (to float32 rounding): the distance from a view's centre is the norm of the point in
    that camera's coordinates, which the projection computes anyway."""
    rot, shift = cam_from_world[:, :3, :3], cam_from_world[:, :3, 3]
    cam = np.matmul(points, np.swapaxes(rot, -1, -2)) + shift[:, None, :]      # [V, P, 3]
    weight, sampled = _read_views(cam, ref_K, image_size, colours)
    plain = mean_colour(sampled, weight)
    mean = plain
    if blend_angle:
        # cos between unit(target - x) and unit(c_v - x) = (t . c_v - t . x) / |R (x - c_v)|
        t = target_centre.astype(f32) - points
        t /= np.maximum(np.sqrt(_sum3(t * t))[:, None], f32(G.NORM_EPS))
        centres = -np.matmul(np.swapaxes(rot, -1, -2), shift[..., None])[..., 0]   # [V, 3]
        along = (t @ centres.T).T - _sum3(t * points)                          # [V, P]
        cos = along / np.maximum(np.sqrt(_sum3(cam * cam)), f32(G.NORM_EPS))
        mean = mean_colour(sampled, weight, cos, blend_angle)
    count = weight.sum(axis=0)                                                 # [P]
    var = (_sum3((sampled - plain) ** 2) * weight).sum(axis=0) / np.maximum(count, f32(1e-12))
    spread = np.where(count > 1.0, var, f32(0))
    return mean.astype(f32, copy=False), spread.astype(f32, copy=False)


def _read_views(cam: np.ndarray, ref_K: np.ndarray, image_size: tuple[int, int],
                colours: ColourSource) -> tuple[np.ndarray, np.ndarray]:
    """Points in each view's camera coordinates ``cam [V, P, 3]`` projected with ``ref_K``: their
    validity float32 [V, P] (``geometry.edge_validity``) and the views' colours there float32
    [V, P, 3] (``ColourSource.read``)."""
    H, W = image_size
    z = cam[..., 2]
    z_safe = np.maximum(z, f32(G.DEPTH_EPS))
    u = ref_K[0, 0] * cam[..., 0] / z_safe + ref_K[0, 2]
    v = ref_K[1, 1] * cam[..., 1] / z_safe + ref_K[1, 2]
    return G.edge_validity(u, v, z, H, W), colours.read(u, v)


def _sum3(x: np.ndarray) -> np.ndarray:
    """``x.sum(axis=-1)`` over a last axis of 3, as three adds (numpy's reduction over a short
    last axis is several times slower)."""
    return x[..., 0] + x[..., 1] + x[..., 2]
