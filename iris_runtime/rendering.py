"""The renderer graph's half of ``IrisRuntime``: ``render``, a ``Scene`` and a pose -> an image.

``Rendering`` is a mixin of ``iris_runtime.runtime.IrisRuntime``, not a class of its own: it reads
the runtime's ``manifest``, ``image_size``, ``near``, ``far``, ``samples``, ``cull``, ``workers``
and ``default_quality``, runs graphs through its ``_session(name)`` and uses its checks
(``_renderer_graph``, ``check_output_size``, ``_check_scene``); images given instead of a Scene
are encoded by the other half (``iris_runtime.encoding``, ``_encode``). Those stay outside this
module, so a test or a benchmark that replaces one of them on an instance is obeyed here too.

The steps of a render: ``_render_job`` checks every argument and derives what the march needs
once (a ``RenderJob``); the ray march is ``iris_runtime.raymarch`` (``_march_at`` builds a
``MarchPlan`` and runs ``raymarch.march``), refined where the settings ask by
``iris_runtime.adaptive`` or composed at two scales by ``iris_runtime.detail``
(``_two_scales``); ``_to_output_size`` resizes a march below the output's size.
"""
from __future__ import annotations

import dataclasses
import functools
import time
from typing import Callable

import numpy as np

from . import adaptive, detail
from . import geometry as G
from . import limits as L
from . import quality as Q
from . import raymarch
from .colour import ColourSource
from .errors import InputError
from .io_spec import COLOURS, CUES, DIRECTIONS, FIELD_MAPS, GRID, MASK, POSITIONS, RGB
from .quality import RenderSettings
from .scene import RenderJob, RenderResult, Scene, check_pose
from .validation import check_intrinsics

__all__ = ["Rendering"]


class Rendering:
    """``IrisRuntime``'s ``render`` and the steps behind it (module docstring: what it needs of
    the runtime)."""

    def render(self, images_or_scene, pose, *, height: int | None = None, width: int | None = None,
               intrinsics=None, depth: bool = False, chunk_rays: int | None = None,
               progress: Callable[[int, int], None] | None = None,
               quality: "str | RenderSettings | None" = None, **knobs):
        """Render one view.

        images_or_scene: a ``Scene`` from ``encode`` or the reference images (encoded first).
        pose:       ``world_from_cam`` 4x4 in the canonical frame (view 0's camera; OpenCV axes),
                    rigid (orthonormal rotation with det +1, last row [0, 0, 0, 1]); or an int i,
                    the predicted pose of input view i.
        height, width: output size (default the model's; one alone keeps the model's aspect).
                    Intrinsics are the scene's shared focal at the output size
                    (``Scene.intrinsics(height, width)``) unless ``intrinsics`` (3x3, pixels of
                    the output) is given.
        depth:      return a ``RenderResult`` (image, float image, depth, timings) instead of the
                    uint8 image alone.
        chunk_rays: rays per renderer call (default ``default_chunk_rays`` of the views a call
                    feeds); peak memory is bounded by it whatever the output size.
        progress:   called as ``progress(rays_done, rays_total)`` after each chunk.

        Speed/quality (``iris_runtime.quality``; measured error and time in docs/PERFORMANCE.md):
        quality:    a preset, "auto" (explicit-colour models' default: two scales above the
                    model's resolution), "exact" (other models' default: the full render),
                    "balanced", "fast" or "adaptive" (``QUALITY_PRESETS``), or a
                    ``RenderSettings``, passed whole. None: ``default_quality``.
        **knobs:    single ``RenderSettings`` fields overriding the preset's (documented there):
                    ``samples``, ``top_k``, ``top_k_by``, ``scale``, ``upsample``, ``precision``
                    (default: the runtime's), ``coarse``, ``refine``, ``refine_budget``,
                    ``depth_window``, ``depth_mass``, ``field_scale``, ``colour_samples``,
                    ``depth_search``; any other name is an ``InputError``.

        Returns uint8 [H, W, 3] RGB, or a ``RenderResult`` with ``depth=True``.
        """
        t_start = time.perf_counter()
        timings: dict[str, float] = {}
        settings = Q.resolve_settings(quality, self.default_quality, **knobs)
        if settings.field_scale is not None and not self.manifest.explicit_rgb:
            if knobs.get("field_scale") is not None or isinstance(quality, RenderSettings):
                raise InputError("field_scale: two scales need an explicit-colour model (the "
                                 "colour from the photos); this model's colour comes from its "
                                 "field")
            if knobs.get("depth_search"):
                raise InputError("depth_search: the search reads the photos' colours; this "
                                 "model's colour comes from its field")
            settings = dataclasses.replace(settings, field_scale=None,   # a preset: adapts
                                           depth_search=0)
        job = self._render_job(images_or_scene, pose, settings,
                               height, width, intrinsics, chunk_rays, progress, timings)
        march = functools.partial(self._march_at, job)
        if job.settings.two_scales(job.size, self.image_size):
            marched, work = self._two_scales(job, progress, timings)
        elif job.settings.refine is None and job.settings.depth_window is None:
            marched, work = march(*job.march_size, progress=progress), {}
        else:
            marched = adaptive.render(job.settings, march, *job.march_size, near=self.near,
                                      far=self.far, samples=job.samples, progress=progress)
            timings["coarse"], work = marched.coarse_s, marched.work
        timings["rays"] = marched.stats.rays_s        # summed over blocks (thread time)
        timings["renderer"] = marched.stats.renderer_s
        image_float, z = self._to_output_size(job, marched, timings)
        image = np.rint(np.clip(image_float, 0.0, 1.0) * 255.0).astype(np.uint8)
        timings["total"] = time.perf_counter() - t_start
        if not depth:
            return image
        return RenderResult(image, image_float, z, timings, {**marched.stats.work(), **work},
                            job.settings)

    def _render_job(self, images_or_scene, pose, settings: RenderSettings, height, width,
                    intrinsics, chunk_rays, progress, timings: dict) -> "RenderJob":
        """Every argument of ``render`` checked, in the order its errors are documented (size and
        limits before encoding or allocating), and what the march needs derived once."""
        graph = self._renderer_graph(settings.precision or self.precision)
        size = self.check_output_size(height, width)
        if progress is not None and not callable(progress):
            raise InputError(f"progress: expected a callable progress(done, total) or None, got "
                             f"{type(progress).__name__}")
        if isinstance(images_or_scene, Scene):
            scene = images_or_scene
            self._check_scene(scene)
        else:
            scene = self._encode(images_or_scene, timings, self.default_cameras)
        photos = self._view_images(scene)             # explicit colour: the photos are there
        kept_photos = (None if photos is None or scene.photos is None
                       else tuple(scene.photos[i] for i in scene.image_index.tolist()))
        world_from_cam = self._check_pose(pose, scene)
        K = self._check_intrinsics(intrinsics, scene, *size)
        samples = settings.samples or self.samples
        V = scene.num_views
        # Per-point top-k on the renderer that takes each point's own views (float32 only).
        select_views = (settings.top_k is not None and settings.top_k < V
                        and settings.top_k_by == "point" and graph == "renderer"
                        and "renderer_views" in self.manifest.graphs)
        # A call's work and memory grow with the views it feeds per point: top_k of them when
        # the calls shrink to them (by ray, or per point on renderer_views).
        shrinks = settings.top_k is not None and (settings.top_k_by == "ray" or select_views)
        chunk_rays = L.chunk_rays_for(chunk_rays, pixels=size[0] * size[1], samples=samples,
                                      num_views=V,
                                      views_per_call=min(V, settings.top_k) if shrinks else V)
        # Two scales compose the colour at the output's size; the field's grid is their own.
        march_size = (size if settings.two_scales(size, self.image_size)
                      else settings.march_size(*size))
        if march_size != size:
            K = G.scale_intrinsics(K, size, march_size)
        return RenderJob(scene=scene, world_from_cam=world_from_cam, K=K, size=size,
                          march_size=march_size, settings=settings, samples=samples,
                          chunk_rays=chunk_rays, graph=graph, select_views=select_views,
                          photos=photos, kept_photos=kept_photos)

    def _march_at(self, job: "RenderJob", mh: int, mw: int, progress=None,
                  **subset) -> raymarch.MarchResult:
        """The ray march of ``job`` at mh x mw pixels (``job.march_size``, or the coarse pass's),
        on ``subset`` (``MarchPlan``'s pixel_index, sample_window, mode_radius)."""
        K = job.K if (mh, mw) == job.march_size else G.scale_intrinsics(job.K, job.march_size,
                                                                          (mh, mw))
        plan = raymarch.MarchPlan.build(
            job.scene, job.world_from_cam, K, mh, mw, samples=job.samples, near=self.near,
            far=self.far, top_k=job.settings.top_k, top_k_by=job.settings.top_k_by,
            chunk_rays=job.chunk_rays, cull=self.cull, photos=job.photos,
            kept_photos=job.kept_photos, levels=job.scene._levels,
            empty_rgb=self._empty_ray_rgb(job.scene, job.graph) if self.cull else None,
            select_views=job.select_views, blend_angle=self.manifest.blend_angle, **subset)
        session = self._session("renderer_views" if job.select_views else job.graph)
        return raymarch.march(plan, session, workers=self.workers, progress=progress)

    def _two_scales(self, job: "RenderJob", progress, timings: dict):
        """``field_scale``: the field marched at the coarse size, the colour of every pixel of
        ``job.march_size`` composed from the photos through it (``iris_runtime.detail``) ->
        (``raymarch.MarchResult`` at ``job.march_size``, work counts)."""
        h, w = job.march_size
        hc = max(1, int(round(h * job.settings.field_scale)))
        wc = max(1, int(round(w * job.settings.field_scale)))
        coarse = self._march_at(job, hc, wc, progress=progress, keep_weights=True)
        t0 = time.perf_counter()
        scene = job.scene
        colours = ColourSource.build(job.photos, job.kept_photos,
                                     raymarch.focal_ratio(job.K, scene.K), scene._levels)
        with self._opencv_threads():          # the photos are read with cv2.remap
            rgb, depth = detail.compose_fine(
                detail.CoarseField((hc, wc), coarse.weights, coarse.residual, coarse.depth),
                h, w, job.K, job.world_from_cam,
                G.sample_depths(self.near, self.far, job.samples, 1, dtype=np.float32)[0],
                scene.K.astype(np.float32),
                G.invert_pose(scene.world_from_cam).astype(np.float32),
                scene.image_size, colours, job.settings.colour_samples,
                blend_angle=self.manifest.blend_angle, depth_search=job.settings.depth_search)
        timings["colour"] = time.perf_counter() - t0
        work = {"coarse_rays": hc * wc, "pixels": h * w}
        return raymarch.MarchResult(rgb, depth, coarse.stats), work

    @staticmethod
    def _to_output_size(job: "RenderJob", marched, timings: dict):
        """The march's colour and depth at the output size: float32 [H, W, 3] and [H, W] (resized
        with OpenCV when ``scale`` < 1: ``upsample`` for the colour, linear for the depth)."""
        h, w = job.march_size
        image_float = marched.rgb.reshape(h, w, 3)
        z = marched.depth.reshape(h, w)
        if job.march_size != job.size:
            t0 = time.perf_counter()
            import cv2                         # only needed for scale < 1
            height, width = job.size
            interp = cv2.INTER_CUBIC if job.settings.upsample == "cubic" else cv2.INTER_LINEAR
            image_float = np.clip(cv2.resize(image_float, (width, height), interpolation=interp),
                                  0.0, 1.0)
            z = cv2.resize(z, (width, height), interpolation=cv2.INTER_LINEAR)
            timings["upsample"] = time.perf_counter() - t0
        return image_float, z

    # .. render's argument checks ..............................................................
    def _view_images(self, scene: Scene, name: str = "images_or_scene") -> np.ndarray | None:
        """Explicit-colour models: each view's reference photo, float32 [V, 3, H, W] in [0, 1]
        (``scene.reference_images[scene.image_index]``), or ``InputError`` when the Scene does not
        say which photo each view is. None for other models (they never read the photos)."""
        if not self.manifest.explicit_rgb:
            return None
        if scene.reference_images is None or scene.image_index is None:
            have = ("no reference_images" if scene.reference_images is None else
                    f"{scene.reference_images.shape[0]} reference_images for {scene.num_views} "
                    f"views and no image_index")
            raise InputError(f"{name}: this model (explicit colour) renders from the reference "
                             f"photos, and this Scene has {have}; use a Scene from "
                             f"IrisRuntime.encode (or its subset), or pass reference_images "
                             f"[and image_index]")
        return np.ascontiguousarray(scene.reference_images[scene.image_index])

    @staticmethod
    def _check_pose(pose, scene: Scene) -> np.ndarray:
        """``pose`` (a view index or a rigid 4x4) as float64 ``world_from_cam``, or
        ``InputError``: out of range, not rigid (``check_pose``), or a camera centre farther
        than ``limits.MAX_POSE_DISTANCE`` x the references' spread from them."""
        if isinstance(pose, (int, np.integer)) and not isinstance(pose, (bool, np.bool_)):
            V = scene.num_views
            if not 0 <= pose < V:
                raise InputError(f"pose: view index {int(pose)} out of range 0..{V - 1} "
                                 f"(the scene has {V} views)")
            return scene.world_from_cam[int(pose)].copy()
        pose = check_pose(pose)
        # A camera far beyond the references sees none of the scene (it lies within ``far`` of
        # them) and its ray arithmetic overflows float32: refused, not a frame of empty rays.
        centres = scene.world_from_cam[:, :3, 3]
        reach = L.MAX_POSE_DISTANCE * max(1.0, float(np.ptp(centres, axis=0).max()))
        distance = float(np.hypot.reduce(pose[:3, 3] - centres.mean(axis=0)))  # no overflow
        if not distance <= reach:
            raise InputError(f"pose: camera centre {distance:.3g} from the references' cameras; "
                             f"at most {reach:.3g} (MAX_POSE_DISTANCE = {L.MAX_POSE_DISTANCE:g} "
                             f"times the references' spread, at least 1: the scene lies within "
                             f"the depth range of them)")
        return pose

    @staticmethod
    def _check_intrinsics(intrinsics, scene: Scene, height: int, width: int) -> np.ndarray:
        if intrinsics is None:
            return scene.intrinsics(height, width)
        return check_intrinsics(intrinsics, "intrinsics", height, width)

    # .. the renderer's constants ..............................................................
    def _empty_ray_rgb(self, scene: Scene, graph: str) -> np.ndarray:
        """The renderer's colour for a ray with no valid sample (``empty_ray_rgb``), asked of
        each graph once."""
        rgb = self._empty_rgb.get(graph)
        if rgb is None:
            rgb = empty_ray_rgb(self._session(graph), scene.field_maps.shape,
                                self.manifest.explicit_rgb)
            self._empty_rgb[graph] = rgb       # idempotent: a race computes the same value twice
        return rgb


def empty_ray_rgb(session, field_maps_shape: tuple[int, ...], explicit_rgb: bool) -> np.ndarray:
    """The renderer's colour for a ray with no valid sample, float32 [3], read-only (a constant
    of the model: every input is masked, so nothing of the scene reaches it)."""
    _, C, h, w = field_maps_shape
    f32 = np.float32
    feed = {FIELD_MAPS: np.zeros((1, C, h, w), f32), GRID: np.zeros((1, 1, 1, 2), f32),
            CUES: np.zeros((1, 1, 1, 4), f32), MASK: np.zeros((1, 1, 1), f32),
            POSITIONS: np.zeros((1, 1, 3), f32), DIRECTIONS: np.array([[0, 0, 1]], f32)}
    if explicit_rgb:                   # masked: the blend of nothing, whatever colour
        feed[COLOURS] = np.zeros((1, 1, 1, 3), f32)
    rgb = session.run([RGB], feed)[0][0]
    rgb.setflags(write=False)
    return rgb
