"""The ray march of one render: target camera -> renderer calls -> rgb and depth (numpy + ONNX
Runtime; no torch).

    plan = MarchPlan.build(scene, world_from_cam, K, height, width, samples=..., ...)
    result = march(plan, session, workers=1, progress=None)      # rgb [N, 3], depth [N]

``MarchPlan`` holds what every block of pixels needs, computed once per render. The pixels (all
of the render, or the subset ``plan.pixel_index`` a coarse-to-fine render refines,
``iris_runtime.adaptive``) are marched in blocks of ``plan.block_rays`` (``trace_block``): rays
through the pixel centres (``geometry.rays_from_pixels``), samples ``x = o + z d`` at the
bin-centre depths ``plan.z_bins`` (or each ray's ``plan.sample_window`` of them), their
projection into every reference view (pixel positions and validity), the views that see the
block and the geometric cue of every sample (target centre = the ray origin). With ``top_k`` the
views are chosen by the cue's t.s (rules in ``iris_runtime.quality``). ``plan_calls`` splits a
block into renderer calls by (rays, views); ``call_feed`` packs each call's inputs, which
``session.run`` turns into rgb and per-sample weights; depth = sum(weights * z). With
``plan.mode_radius`` the march also keeps, per ray, the depth of the largest weight (the soft
depth's mode) and the weight within ``mode_radius`` of it (how concentrated the ray is).

The renderer graph samples the field maps itself at ``grid`` (bilinear, align_corners=False,
border-clamped; how is the exporter's choice: a dense bilinear matmul for small feature grids,
``GridSample`` above, see export/graphs.py). Explicit-colour models (``config.explicit_rgb``) also
get ``colours`` [V', R, S, 3]: each call's views' reference photos sampled in numpy at the same
``grid``, from the level of each photo's pyramid that matches the plan's focal in pixels
(``plan.colours``, an ``iris_runtime.colour.ColourSource`` built once per plan: the photos as
given for a large output, the model-resolution images, bit for bit as
``geometry.sample_bilinear_views``, at the model's size). Masked (view, sample) pairs carry
colours too (ignored by the graph), so every culling, top_k, samples, scale, int8 and workers path
feeds the graph exactly what it feeds without explicit colour, plus the colours of the same
samples.

Culling (``plan.cull``, exact): samples that project validly into no reference view, views into
which no sample of the block projects, and rays without any valid sample carry no information —
the renderer masks them out of every attention, pool and weight (see iris_train/ray_renderer.py),
so dropping them changes nothing but the float rounding of sums. Each call is therefore packed to
the valid samples of each ray (in depth order, padded to the call's longest ray with masked
samples), the views that see its rays, and the rays that see anything; an empty ray gets the
renderer's answer to an empty ray (``plan.empty_rgb``: rgb = head(0), zero weights, depth 0).
Rays whose every sample has full weight get calls of their own (``plan_calls``), in which the
graph skips its ray attentions' key-bias Add (export/fast_renderer.py). A sample window is the
same masking: samples outside a ray's window are dropped as if they projected nowhere.
"""
from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import geometry as G
from . import quality as Q
from .colour import ColourSource, blend_residual, mean_colour
from .io_spec import COLOURS, CUES, DIRECTIONS, FIELD_MAPS, GRID, MASK, POSITIONS, RGB, WEIGHTS
from .point_views import select_point_views
from .scene import Scene

__all__ = ["MarchPlan", "focal_ratio", "Block", "Call", "MarchStats", "MarchResult", "march",
           "trace_block", "plan_calls", "call_feed"]

f32 = np.float32


@dataclass(frozen=True, eq=False)
class MarchPlan:
    """Everything the ray march of one render needs (arrays read-only; V = the scene's views,
    S = samples per ray, H x W = the model's resolution).

    Target camera, in pixels of the render (after ``scale``):
      height, width:  int                  the render's pixel grid, row-major
      world_from_cam: float32 [4, 4]       target pose
      K:              float32 [3, 3]       target intrinsics
    Samples:
      z_bins:         float32 [S]          camera depths: bin centres of S equal bins in [near, far]
    Reference views:
      image_size:     (H, W)               the model's resolution (the views' pixels)
      ref_K:          float32 [3, 3]       the views' intrinsics (shared focal)
      cam_from_world: float32 [V, 4, 4]    inverted in float64, then rounded
      centres:        float32 [V, 3]       camera centres in world
      field_maps:     float32 [V, C', h, w]
      colours:        ``colour.ColourSource`` or None: each view's reference photo (explicit
                                           colour) at the level of this render's scale
      blend_angle:    float                the model's angular view weighting of the colours
                                           (``colour.mean_colour``; 0: the plain mean)
    View sets:
      top_k:          int or None          views kept per sample point (None: every valid view)
      by_ray:         bool                 top_k chosen per ray (calls then shrink to top_k views)
                                           rather than per point
      cull:           bool                 drop samples, views and rays that see nothing (exact)
      empty_rgb:      float32 [3] or None  the renderer's colour of a ray without valid samples
                                           (with ``cull``)
    Chunks:
      chunk_rays:     int                  most rays per renderer call (culled calls; see
                                           ``block_rays``)
      block_rays:     int                  pixels per block traced at once: ``chunk_rays``, times
                                           V // top_k with per-ray view sets (a block then spans
                                           several calls, same numpy memory as one all-view call)
    Subsets (coarse-to-fine renders, ``iris_runtime.adaptive``; None: off), N = the rays marched:
      pixel_index:    int64 [N] or None    the render's pixels to march (row-major indices into
                                           height x width, any order; None: every pixel, N = H*W)
      sample_window:  int64 [N, 2] or None per marched ray, the samples kept: ``z_bins[lo:hi]``
                                           (0 <= lo < hi <= S; the others are masked out)
      mode_radius:    float or None        also return each ray's weight mode and the weight
                                           within this depth distance of it (``MarchResult``)
    Two scales (``iris_runtime.detail``):
      keep_weights:   bool                 also return each ray's weights over the S depth bins
                                           and its colour residual (``MarchResult``; explicit
                                           colour, not with ``select_views``)
    """
    height: int
    width: int
    world_from_cam: np.ndarray
    K: np.ndarray
    z_bins: np.ndarray
    image_size: tuple[int, int]
    ref_K: np.ndarray
    cam_from_world: np.ndarray
    centres: np.ndarray
    field_maps: np.ndarray
    colours: ColourSource | None
    top_k: int | None
    by_ray: bool
    cull: bool
    empty_rgb: np.ndarray | None
    chunk_rays: int
    block_rays: int
    pixel_index: np.ndarray | None = None
    sample_window: np.ndarray | None = None
    mode_radius: float | None = None
    select_views: bool = False
    keep_weights: bool = False
    blend_angle: float = 0.0

    @classmethod
    def build(cls, scene: Scene, world_from_cam: np.ndarray, K: np.ndarray, height: int,
              width: int, *, samples: int, near: float, far: float, top_k: int | None,
              top_k_by: str, chunk_rays: int, cull: bool, empty_rgb: np.ndarray | None,
              photos: np.ndarray | None, kept_photos: tuple | None = None,
              levels: dict | None = None, pixel_index: np.ndarray | None = None,
              sample_window: np.ndarray | None = None,
              mode_radius: float | None = None, select_views: bool = False,
              keep_weights: bool = False, blend_angle: float = 0.0) -> "MarchPlan":
        """The plan of rendering ``scene`` from ``world_from_cam`` (checked, float64 4x4) with
        intrinsics ``K`` (pixels of the ``height`` x ``width`` render); ``pixel_index``,
        ``sample_window``, ``mode_radius``: see the class (built by ``iris_runtime.adaptive``,
        which owns their contract). ``select_views``: feed the renderer on per-point
        pre-selected views (``io_spec.RENDERER_VIEWS``, ``select_point_views``) with per-point
        ``top_k``. ``photos`` float32 [V, 3, H, W] (explicit colour: each view's photo at the
        model's resolution) and ``kept_photos`` (per view uint8 [h, w, 3] or None, with the
        pyramid cache ``levels``): the colour source, ``colour.ColourSource``."""
        V = scene.num_views
        by_ray = top_k is not None and top_k_by == "ray" and top_k < V
        return cls(height=int(height), width=int(width),
                   world_from_cam=_frozen(world_from_cam.astype(f32)), K=_frozen(K.astype(f32)),
                   z_bins=_frozen(G.sample_depths(near, far, samples, 1, dtype=f32)[0]),
                   image_size=tuple(scene.image_size), ref_K=_frozen(scene.K.astype(f32)),
                   cam_from_world=_frozen(G.invert_pose(scene.world_from_cam).astype(f32)),
                   centres=_frozen(scene.world_from_cam[:, :3, 3].astype(f32)),
                   field_maps=scene.field_maps,
                   colours=None if photos is None else ColourSource.build(
                       photos, kept_photos, focal_ratio(K, scene.K), levels),
                   top_k=top_k if top_k is not None and top_k < V else None, by_ray=by_ray,
                   cull=bool(cull), empty_rgb=empty_rgb if cull else None,
                   chunk_rays=int(chunk_rays),
                   block_rays=int(chunk_rays) * max(1, V // top_k) if by_ray else int(chunk_rays),
                   pixel_index=None if pixel_index is None else _frozen(
                       np.asarray(pixel_index, np.int64)),
                   sample_window=None if sample_window is None else _frozen(
                       np.asarray(sample_window, np.int64)),
                   mode_radius=None if mode_radius is None else float(mode_radius),
                   select_views=bool(select_views), keep_weights=bool(keep_weights),
                   blend_angle=float(blend_angle))

    @property
    def pixels(self) -> int:
        return self.height * self.width

    @property
    def rays(self) -> int:
        """N: the rays marched (the pixels of ``pixel_index``, else every pixel)."""
        return self.pixels if self.pixel_index is None else len(self.pixel_index)

    @property
    def samples(self) -> int:
        return self.z_bins.shape[0]

    @property
    def num_views(self) -> int:
        return self.centres.shape[0]


@dataclass(frozen=True, eq=False)
class Block:
    """One block of R pixels traced through the V'' reference views that see it (all V without
    culling), S' samples per ray (S, or the block's widest ``sample_window``).

    rows:       int64   [R]              output rows (indices into the march's N rays; the
                                         row-major pixel indices when every pixel is marched)
    directions: float32 [R, 3]           ray directions (camera-z component 1)
    z:          float32 [R, S']          camera depths of the samples (rows of ``plan.z_bins``)
    points:     float32 [R, S', 3]       sample points o + z d
    views:      int64   [V'']            the scene's views that see the block
    uv:         float32 [V'', R, S', 2]  pixel positions of the samples in those views
    weight:     float32 [V'', R, S']     each sample's validity weight in each view
                                         (``geometry.validity``; 0 where its ray's window or
                                         ``top_k`` drops it): the renderer's ``mask``
    cue:        float32 [V'', R, S', 4]  geometric cue of each sample in each view (view-major)
    ray_views:  bool    [V'', R] or None the views each ray keeps (``top_k`` by ray, else None)
    """
    rows: np.ndarray
    directions: np.ndarray
    z: np.ndarray
    points: np.ndarray
    views: np.ndarray
    uv: np.ndarray
    weight: np.ndarray
    cue: np.ndarray
    ray_views: np.ndarray | None

    @property
    def valid(self) -> np.ndarray:
        """bool [V'', R, S']: the sample projects validly and is kept (``weight > 0``)."""
        return self.weight > 0


@dataclass(frozen=True, eq=False)
class Call:
    """One renderer call: index arrays into a ``Block``'s rays (``rays`` [r]) and its ``views``
    (``views`` [v]; the scene's views are ``block.views[views]``)."""
    rays: np.ndarray
    views: np.ndarray


@dataclass
class MarchStats:
    """Seconds and work of a march (summed over blocks; thread time when workers > 1).

    rays_s, renderer_s: numpy geometry and packing / ONNX Runtime
    calls, rays, points, point_views, ray_pairs: renderer calls, and over them the sums of R,
    R*S, R*S*V' and R*S^2 (R/S/V' the rays, samples and views of a call)
    """
    rays_s: float = 0.0
    renderer_s: float = 0.0
    calls: int = 0
    rays: int = 0
    points: int = 0
    point_views: int = 0
    ray_pairs: int = 0

    def add(self, other: "MarchStats") -> None:
        for f in dataclasses.fields(self):
            setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))

    def count_call(self, views: int, rays: int, samples: int) -> None:
        self.calls += 1
        self.rays += rays
        self.points += rays * samples
        self.point_views += rays * samples * views
        self.ray_pairs += rays * samples * samples

    def work(self) -> dict[str, int]:
        """``RenderResult.work``: the work counts by name."""
        return {k: getattr(self, k) for k in ("calls", "rays", "points", "point_views",
                                              "ray_pairs")}


@dataclass(frozen=True, eq=False)
class MarchResult:
    """rgb float32 [N, 3], depth float32 [N] of the N rays marched (row-major pixels, or in the
    order of ``plan.pixel_index``) and the stats. With ``plan.mode_radius``: ``mode`` float32 [N],
    the depth of each ray's largest weight, and ``mass`` float32 [N], its weight within
    ``mode_radius`` of that depth (both 0 for a ray without valid samples); else None. With
    ``plan.keep_weights``: ``weights`` float32 [N, S], each ray's blend weights over the depth
    bins ``plan.z_bins`` (0 where a sample was culled), and ``residual`` float32 [N, 3], what the
    renderer's colour head added to the blend's logit (``colour.blend_residual``); else None."""
    rgb: np.ndarray
    depth: np.ndarray
    stats: MarchStats
    mode: np.ndarray | None = None
    mass: np.ndarray | None = None
    weights: np.ndarray | None = None
    residual: np.ndarray | None = None


def focal_ratio(K: np.ndarray, ref_K: np.ndarray) -> float:
    """The render's focal in its pixels over the references' in the model's (geometric mean of
    x and y): how many model pixels one output pixel spans, inverted."""
    return float(np.sqrt(abs(float(K[0, 0]) * float(K[1, 1]))
                         / (float(ref_K[0, 0]) * float(ref_K[1, 1]))))


def _frozen(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


# ----------------------------------------------------------------------------------------------
# The march
# ----------------------------------------------------------------------------------------------

def march(plan: MarchPlan, session, *, workers: int = 1,
          progress: Callable[[int, int], None] | None = None) -> MarchResult:
    """Render the rays of ``plan`` (every pixel, or ``plan.pixel_index``) with the renderer
    ``session`` (an ONNX Runtime session or anything with its ``run``), block by block on
    ``workers`` threads (each block writes its own rows); ``progress(rays_done, rays_total)``
    after each block."""
    n, block = plan.rays, plan.block_rays
    rgb, depth = np.empty((n, 3), f32), np.zeros(n, f32)
    modes = None if plan.mode_radius is None else (np.zeros(n, f32), np.zeros(n, f32))
    kept = None
    if plan.keep_weights:
        if plan.select_views or plan.colours is None:
            raise ValueError("keep_weights: needs explicit colour and the view-major feed")
        # Rays no call renders keep zero weights and the residual of the empty colour.
        kept = (np.zeros((n, plan.samples), f32),
                np.broadcast_to(blend_residual(plan.empty_rgb, np.zeros(3, f32)), (n, 3)).copy()
                if plan.empty_rgb is not None else np.zeros((n, 3), f32))
    stats = MarchStats()
    starts = range(0, n, block)

    def one(start: int) -> MarchStats:
        return _march_block(plan, session, start, rgb, depth, modes, kept)

    def done(start: int, part: MarchStats) -> None:
        stats.add(part)
        if progress is not None:
            progress(min(n, start + block), n)

    if workers == 1 or len(starts) == 1:
        for start in starts:
            done(start, one(start))
    else:
        from concurrent.futures import ThreadPoolExecutor
        with ThreadPoolExecutor(workers, thread_name_prefix="iris-render") as pool:
            for start, part in zip(starts, pool.map(one, starts)):
                done(start, part)
    return MarchResult(rgb, depth, stats, *(modes or (None, None)), *(kept or (None, None)))


def _march_block(plan: MarchPlan, session, start: int, rgb: np.ndarray, depth: np.ndarray,
                 modes: tuple[np.ndarray, np.ndarray] | None,
                 kept: tuple[np.ndarray, np.ndarray] | None = None) -> MarchStats:
    """Trace the block of rays from ``start``, run its renderer calls, write its rows of
    ``rgb`` and ``depth`` (and of ``modes`` = (mode, mass) with ``plan.mode_radius``, of
    ``kept`` = (weights, residual) with ``plan.keep_weights``)."""
    stats = MarchStats()
    t0 = time.perf_counter()
    block = trace_block(plan, start)
    if plan.cull:
        rgb[block.rows] = plan.empty_rgb              # rays that no call renders
    calls = plan_calls(plan, block)
    stats.rays_s += time.perf_counter() - t0
    maps_views, maps = None, None
    for call in calls:
        t0 = time.perf_counter()
        views = block.views[call.views]
        if maps is None or not np.array_equal(views, maps_views):   # neighbours share views
            maps_views = views
            maps = plan.field_maps if np.array_equal(views, np.arange(plan.num_views)) \
                else np.ascontiguousarray(plan.field_maps[views])
        feed, z = call_feed(plan, block, call, maps)
        t1 = time.perf_counter()
        out_rgb, weights = session.run([RGB, WEIGHTS], feed)
        t2 = time.perf_counter()
        rows = block.rows[call.rays]
        rgb[rows] = out_rgb
        depth[rows] = (weights * z).sum(axis=1)
        if modes is not None:
            z_mode = np.take_along_axis(z, weights.argmax(axis=1)[:, None], axis=1)
            modes[0][rows] = z_mode[:, 0]
            modes[1][rows] = np.where(np.abs(z - z_mode) <= plan.mode_radius, weights,
                                      f32(0)).sum(axis=1)
        if kept is not None:
            # The packed samples back on their bins (z is a bin centre, bit for bit).
            dense = np.zeros((len(rows), plan.samples), f32)
            np.put_along_axis(dense, np.searchsorted(plan.z_bins, z), weights, axis=1)
            kept[0][rows] = dense
            mean = mean_colour(feed[COLOURS], feed[MASK], feed[CUES][..., 3],
                               plan.blend_angle)                                # [r, s, 3]
            kept[1][rows] = blend_residual(out_rgb, np.einsum("rs,rsc->rc", weights, mean))
        t3 = time.perf_counter()
        stats.rays_s += (t1 - t0) + (t3 - t2)
        stats.renderer_s += t2 - t1
        stats.count_call(*feed[MASK].shape)
    return stats


def trace_block(plan: MarchPlan, start: int) -> Block:
    """Rays, samples, projection, cue and view selection of rays ``start .. start +
    plan.block_rays`` (of the N marched, clipped to N)."""
    H, W = plan.image_size
    V = plan.num_views
    rows = np.arange(start, min(plan.rays, start + plan.block_rays))
    pixels = rows if plan.pixel_index is None else plan.pixel_index[rows]
    # Pixel centres (u, v) = (j + 0.5, i + 0.5) of the block's pixels.
    uv = np.stack([pixels % plan.width, pixels // plan.width], axis=-1).astype(f32) + f32(0.5)
    origins, directions = G.rays_from_pixels(uv, plan.K, plan.world_from_cam)   # [R, 3] each
    if plan.sample_window is None:
        z = np.broadcast_to(plan.z_bins, (len(rows), plan.samples))
        inside = None
    else:
        # Each ray's run z_bins[lo:hi], padded to the block's widest run (masked below): only
        # the kept samples are traced, so the numpy work shrinks with the windows too.
        lo, hi = plan.sample_window[rows].T
        index = lo[:, None] + np.arange(max(1, int((hi - lo).max())))
        inside = index < hi[:, None]                                            # [R, S']
        z = plan.z_bins[np.minimum(index, plan.samples - 1)]
    points = origins[:, None, :] + z[:, :, None] * directions[:, None, :]
    uv_ref, z_ref, _ = G.project_points(points, plan.ref_K, plan.cam_from_world, H, W)
    weight = G.validity(uv_ref, z_ref, H, W)                                   # [V, R, S']
    valid = weight > 0
    if inside is not None:
        valid = valid & inside[None]
    views = np.arange(V)                                                        # [V, R, S'] above
    if plan.cull:
        views = np.flatnonzero(valid.reshape(V, -1).any(axis=1))                # views seeing it
        uv_ref, valid, weight = uv_ref[views], valid[views], weight[views]
    t, s, s_norm = G.cue_vectors(points, origins[:, None, :], plan.centres[views])
    cue = np.moveaxis(G.cue_from_vectors(t, s, s_norm), 2, 0)                   # [V'', R, S, 4]
    ray_views = None
    if plan.top_k is not None and len(views) > plan.top_k:
        # t.s of the same vectors, rounded as the selection always was (geometry.cue_alignment).
        score = np.ascontiguousarray(np.moveaxis(G.cue_alignment(t, s, s_norm), 2, 0))
        if plan.by_ray:
            ray_views = Q.ray_view_sets(valid, score, plan.top_k)              # [V'', R]
            valid = valid & ray_views[:, :, None]
        else:
            valid = valid & Q.top_k_mask(valid, score, plan.top_k)
    weight = np.where(valid, weight, f32(0))              # the windows' and top_k's drops too
    return Block(rows, directions, z, points, views, uv_ref, weight, cue, ray_views)


def plan_calls(plan: MarchPlan, block: Block) -> list[Call]:
    """The renderer calls of ``block``: without culling one call of every ray and view; with it
    only the rays that see anything, with the views that see them (per-ray view sets: grouped by
    ``quality.group_rays``, at most ``plan.chunk_rays`` rays and ``top_k`` views per call).

    With culling, the rays whose every sample has full weight in its best view go to calls of
    their own: such a call has no masked or fading key, so the renderer graph skips its ray
    attentions' key-bias Add (``export.fast_renderer._key_softmax``). Most rays of a render are
    such rays (docs/PERFORMANCE.md, "The fast renderer graph")."""
    if not plan.cull:
        return [Call(np.arange(len(block.rows)), np.arange(len(block.views)))]
    if len(block.views) == 0:                            # nothing of the scene on these rays
        return []
    best = block.weight.max(axis=0)                      # [R, S']: each sample's best view
    live = np.flatnonzero((best > 0).any(axis=1))
    if live.size == 0:
        return []
    full = (best[live] == 1).all(axis=1)
    parts = [rays for rays in (live[full], live[~full]) if rays.size]
    if block.ray_views is not None:
        return [Call(rays[r], v) for rays in parts
                for r, v in Q.group_rays(block.ray_views[:, rays], plan.top_k, plan.chunk_rays)]
    V = len(block.views)
    return [Call(rays, np.flatnonzero(block.valid[:, rays].reshape(V, -1).any(axis=1)))
            for rays in parts]


def call_feed(plan: MarchPlan, block: Block, call: Call,
              field_maps: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The renderer inputs of ``call`` (``field_maps``: the maps of its views, [v, C', h, w]) and
    the depths of its samples, float32 [r, s]. With culling the samples are packed: each ray's
    valid samples first, in depth order, cut to the call's longest ray."""
    H, W = plan.image_size
    ix = np.ix_(call.views, call.rays)
    mask = block.weight[ix]                                                  # [v, r, S']
    uv = block.uv[ix]                                                        # [v, r, S', 2]
    cue = block.cue[ix]                                                      # [v, r, S', 4]
    points = block.points[call.rays]                                         # [r, S', 3]
    z = block.z[call.rays]                                                   # [r, S']
    if plan.cull:
        sample_valid = (mask > 0).any(axis=0)                                # [r, S']
        s_max = int(sample_valid.sum(axis=1).max())
        if s_max < points.shape[1]:
            order = np.argsort(~sample_valid, axis=1, kind="stable")[:, :s_max]   # stable
            points = np.take_along_axis(points, order[..., None], axis=1)
            uv = np.take_along_axis(uv, order[None, ..., None], axis=2)
            cue = np.take_along_axis(cue, order[None, ..., None], axis=2)
            mask = np.take_along_axis(mask, order[None], axis=2)
            z = np.take_along_axis(z, order, axis=1)
    grid = G.pixels_to_grid(uv, H, W)
    feed = {FIELD_MAPS: field_maps, GRID: grid, CUES: np.ascontiguousarray(cue),
            MASK: np.ascontiguousarray(mask), POSITIONS: points,
            DIRECTIONS: block.directions[call.rays]}
    if plan.colours is not None:       # explicit colour: the photos at the same grid
        feed[COLOURS] = plan.colours.sample(grid, block.views[call.views])
    return (select_point_views(feed) if plan.select_views else feed), z
