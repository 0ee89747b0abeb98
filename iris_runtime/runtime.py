"""IrisRuntime: run an exported IRIS model (encoder.onnx + renderer.onnx + iris.json) with
ONNX Runtime on the CPU, torch-free.

    rt = IrisRuntime("out/")                      # checks the manifest and the graphs' sha256
    image = rt.render(images, pose)               # one shot: encode, then render one pose
    scene = rt.encode(images)                     # run the encoder once (the expensive half) ...
    result = rt.render(scene, 2, depth=True)      # ... and render many poses from it
    pose = rt.locate(scene, photo)                # a new photo's world_from_cam; scene unchanged

A thin facade: this module holds the sessions, the encoder and the argument checks of the public
calls; the ray march is ``iris_runtime.raymarch`` (``render`` checks its arguments, builds a
``MarchPlan`` and runs ``raymarch.march``), the value types are ``iris_runtime.scene``
(``Scene``, ``RenderResult``), the request limits and the memory model ``iris_runtime.limits``,
the speed/quality knobs ``iris_runtime.quality``. Every name of those that was importable from
here still is.

References and queries: ``encode`` runs the encoder graph with every image a reference.
``locate`` runs it again on the scene's reference images (kept, read-only, in the ``Scene``)
followed by the photos as queries (``is_reference = [True] * V + [False] * Q``): a reference's
tokens attend to references only, a query's to the references and itself, so the references'
features and cameras are those of the scene (bitwise, in ONNX Runtime) and the query's pose comes
out in the scene's frame. The scene is not changed and queries never see each other.

Cameras follow docs/ARCHITECTURE.md: OpenCV axes, ``world_from_cam`` 4x4, canonical frame = view 0's camera,
intrinsics in pixels with pixel centres at (j + 0.5, i + 0.5).
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import os
import threading
import time
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import onnxruntime as ort

from . import adaptive, detail
from . import geometry as G
from . import limits as L
from . import quality as Q
from . import raymarch
from .errors import InputError, ManifestError, ModelFileError
from .colour import ColourSource, keep_photo
from .images import fit_to_model, load_image
from .io_spec import FIELD_MAPS, FOCAL, IMAGES, IS_REFERENCE, WORLD_FROM_CAM
from .limits import (MAX_CHUNK_RAYS, MAX_CHUNK_SAMPLES, MAX_ENCODER_TOKENS, MAX_LOCATE_CALLS,
                     MAX_OUTPUT_PIXELS, RENDER_BUDGET, render_memory_bound)
from .manifest import (CAMERAS, MANIFEST_NAME, Manifest, camera_name, read_graph_bytes,
                       read_manifest)
from .quality import PRECISIONS, QUALITY_PRESETS, RenderSettings
from .scene import CAMERA_SOURCES, RenderJob, RenderResult, Scene, check_pose
from .validation import check_intrinsics

__all__ = ["IrisRuntime", "Scene", "RenderResult", "check_pose", "CAMERAS", "CAMERA_SOURCES",
           "RENDER_BUDGET", "MAX_CHUNK_RAYS",
           "MAX_OUTPUT_PIXELS", "MAX_ENCODER_TOKENS", "MAX_CHUNK_SAMPLES", "MAX_LOCATE_CALLS",
           "render_memory_bound",
           "PRECISIONS", "RenderSettings", "QUALITY_PRESETS"]


def _check_providers(providers) -> tuple[str, ...]:
    """``IrisRuntime``'s ``providers`` as a tuple of names this onnxruntime build has (None: the
    CPU's), or ``InputError``."""
    if providers is None:
        return ("CPUExecutionProvider",)
    available = ort.get_available_providers()
    if isinstance(providers, (str, bytes)) or not isinstance(providers, (list, tuple)) \
            or not providers or any(not isinstance(p, str) or p not in available
                                    for p in providers) or len(set(providers)) != len(providers):
        raise InputError(f"providers: expected a non-empty list of distinct ONNX Runtime execution "
                         f"providers among this onnxruntime's {available}, got {providers!r}")
    return tuple(providers)


def _is_single_image(x) -> bool:
    """One image (a path, a PIL image, an HxW(xC) array) rather than a sequence of images."""
    return (isinstance(x, (str, os.PathLike, bytes)) or hasattr(x, "getpixel")
            or (isinstance(x, np.ndarray) and x.ndim != 4))


class IrisRuntime:
    """An exported IRIS model, run with ONNX Runtime (see the module docstring).

    ``threads``: intra-op threads of each ONNX Runtime session, and numpy's BLAS threads while
    ``encode`` and ``locate`` find cameras (None: ORT's and the BLAS's defaults, one per core).
    ``precision``: "float32" (default) or "int8" (the quantised renderer, when the model was
    exported with ``--quantize int8``). ``cull``: skip samples, views and rays
    that see no reference view (exact, see ``iris_runtime.raymarch``; False only to check that).
    ``workers``: renderer calls in flight at once within one render (Python threads over blocks of
    rays, exact: the same calls, only concurrent); with ``workers > 1`` each renderer session
    runs ``max(1, threads // workers)`` intra-op threads (``threads`` None: the usable CPUs), so
    ``workers=2`` on 2 cores is data-parallel instead of ORT's op-parallel threading.
    ``providers``: ONNX Runtime execution providers of both graphs in priority order, e.g.
    ``["CUDAExecutionProvider", "CPUExecutionProvider"]`` with onnxruntime-gpu (None: the CPU);
    the numpy geometry stays on the CPU. A name this onnxruntime does not have, or a first
    provider that fails to start, is an ``InputError``.
    Construction reads and checks ``iris.json`` and the sha256 of both graphs; sessions are
    created on first use (and the graph bytes hashed again, so the graph that runs is the one
    that was checked). Safe to share between threads.
    """

    def __init__(self, model_dir: str | os.PathLike, threads: int | None = None, *,
                 precision: str = "float32", cull: bool = True, workers: int = 1,
                 providers: Sequence[str] | None = None):
        if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
            raise InputError(f"workers: expected a positive integer, got {workers!r}")
        if not isinstance(precision, str) or precision not in PRECISIONS:
            raise InputError(f"precision: expected one of {list(PRECISIONS)}, got {precision!r}")
        if threads is not None and (isinstance(threads, bool)
                                    or not isinstance(threads, (int, np.integer)) or threads < 1):
            raise InputError(f"threads: expected a positive integer or None, got {threads!r}")
        if not isinstance(model_dir, (str, os.PathLike)):
            raise InputError(f"model_dir: expected a path to an iris-export output directory, got "
                             f"{type(model_dir).__name__}")
        providers = _check_providers(providers)
        self.manifest: Manifest = read_manifest(model_dir)
        self.model_dir: Path = self.manifest.model_dir
        self.providers: tuple[str, ...] = providers
        self.threads = None if threads is None else int(threads)
        self.precision = precision
        self._renderer_graph(precision)                 # the model has that renderer
        self.cull = bool(cull)
        self.workers = int(workers)
        self._sessions: dict[str, ort.InferenceSession] = {}
        self._lock = threading.Lock()
        self._empty_rgb: dict[str, np.ndarray] = {}       # per renderer graph
        self._blas = None                                 # threadpoolctl, on the first solve

    # -- model facts ------------------------------------------------------------------------
    @property
    def image_size(self) -> tuple[int, int]:
        """(H, W): the model's resolution (inputs are cropped/resized to it)."""
        return self.manifest.image_size

    @property
    def near(self) -> float:
        return self.manifest.near

    @property
    def far(self) -> float:
        return self.manifest.far

    @property
    def samples(self) -> int:
        return self.manifest.samples

    def __repr__(self) -> str:
        H, W = self.image_size
        return (f"IrisRuntime({str(self.model_dir)!r}, image_size={H}x{W}, samples={self.samples}, "
                f"threads={self.threads})")

    @property
    def default_quality(self) -> str:
        """``render``'s preset when none is asked for: "auto" (two scales above the model's
        resolution on explicit-colour models, the full render up to it and on other models)."""
        return "auto"

    @property
    def max_views(self) -> int:
        """Most images one ``encode`` accepts: ``MAX_ENCODER_TOKENS`` // (patches per view + 1)."""
        return L.max_views(self.image_size, self.manifest.config.get("patch_size", 8))

    def default_chunk_rays(self, num_views: int, samples: int | None = None) -> int:
        """Rays per renderer call: R * S * V near ``RENDER_BUDGET``, at most ``MAX_CHUNK_RAYS``
        (``limits.default_chunk_rays``; ``samples`` None: the model's)."""
        return L.default_chunk_rays(num_views, samples or self.samples)

    def check_output_size(self, height=None, width=None) -> tuple[int, int]:
        """The (height, width) that ``render`` would produce (None: the model's, or the model's
        aspect for one given side), or ``InputError`` for non-positive / non-integer sizes and for
        more than ``MAX_OUTPUT_PIXELS`` pixels. Allocates nothing (iris-render checks with it
        before writing anything)."""
        return L.check_output_size(self.image_size, height, width)

    def _renderer_graph(self, precision: str) -> str:
        """The manifest's renderer graph of ``precision`` (``PRECISIONS``), or ``ManifestError``
        when the model was exported without it. The one place a precision becomes a graph."""
        graph = PRECISIONS[precision]
        if graph not in self.manifest.graphs:
            raise ManifestError(f"{self.model_dir / MANIFEST_NAME}: no {precision} renderer "
                                f"(graphs.{graph}); export with --quantize int8 for it")
        return graph

    # -- sessions ---------------------------------------------------------------------------
    def _session(self, name: str) -> ort.InferenceSession:
        session = self._sessions.get(name)
        if session is not None:
            return session
        with self._lock:                       # one creation per graph, whatever the threads
            session = self._sessions.get(name)
            if session is None:
                session = self._create_session(name)
                self._sessions[name] = session
        return session

    def _create_session(self, name: str) -> ort.InferenceSession:
        entry = self.manifest.graphs[name]
        data = read_graph_bytes(entry)
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = self.threads or 0
        if self.workers > 1 and name not in ("encoder", "encoder_cameras"):
            total = self.threads or len(os.sched_getaffinity(0))
            opts.intra_op_num_threads = max(1, total // self.workers)
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        # Optimise in memory at load; never write the optimised graph (optimised files
        # are tied to the machine and ORT version that made them).
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.log_severity_level = 3
        try:
            session = ort.InferenceSession(data, sess_options=opts,
                                           providers=list(self.providers))
        except Exception as exc:               # ORT raises its own Fail/InvalidGraph types
            raise ModelFileError(f"{entry.path}: onnxruntime cannot load the {name} graph: "
                                 f"{str(exc).strip().splitlines()[0][:300]}") from None
        if session.get_providers()[0] != self.providers[0]:   # ORT falls back silently
            raise InputError(f"providers: onnxruntime could not start {self.providers[0]} for the "
                             f"{name} graph (it would run on {session.get_providers()})")
        have_in = {i.name for i in session.get_inputs()}
        have_out = {o.name for o in session.get_outputs()}
        if have_in != set(entry.inputs) or not set(entry.outputs) <= have_out:
            raise ModelFileError(f"{entry.path}: graph I/O {sorted(have_in)} -> {sorted(have_out)} "
                                 f"does not match the manifest's {sorted(entry.inputs)} -> "
                                 f"{sorted(entry.outputs)}")
        return session

    # -- encoding ---------------------------------------------------------------------------
    def _load_photos(self, images, name: str = "images", limit: int | None = None,
                     single: bool = False) -> list[np.ndarray]:
        """Images -> uint8 RGB photos [H_i, W_i, 3] at their own resolution (``name``: the
        argument in messages; ``limit``: most images accepted, default ``max_views``; ``single``:
        ``images`` is a one-element list made from one image called ``name``)."""
        if _is_single_image(images):
            raise InputError(f"{name}: expected a sequence of images (paths, PIL images or "
                             f"HxWx3 uint8 arrays), got a single {type(images).__name__}; "
                             f"wrap it in a list")
        try:
            items = list(images)
        except TypeError:
            raise InputError(f"{name}: expected a sequence of images or a Scene, got "
                             f"{type(images).__name__}") from None
        if not items:
            raise InputError(f"{name}: expected at least one image, got an empty sequence")
        if limit is None and len(items) > self.max_views:
            raise InputError(f"{name}: {len(items)} images, at most {self.max_views} per encode "
                             f"for this model (MAX_ENCODER_TOKENS = {MAX_ENCODER_TOKENS}: the "
                             f"encoder's memory grows with the square of the views)")
        if limit is not None and len(items) > limit:
            raise InputError(f"{name}: {len(items)} images, at most {limit} per locate for this "
                             f"scene and model (MAX_LOCATE_CALLS = {MAX_LOCATE_CALLS} encoder calls "
                             f"of up to {self.max_views} views, the scene's references included)")
        return [load_image(item, name if single else f"{name}[{i}]") for i, item in enumerate(items)]

    def _model_batch(self, photos: list[np.ndarray]) -> np.ndarray:
        """uint8 photos -> float32 [V, 3, H, W] in [0, 1] at the model's resolution
        (``fit_to_model``: centre crop to the model's aspect, resize)."""
        H, W = self.image_size
        batch = np.empty((len(photos), 3, H, W), dtype=np.float32)
        for i, photo in enumerate(photos):
            batch[i] = fit_to_model(photo, H, W)[0].transpose(2, 0, 1)
        batch *= np.float32(1.0 / 255.0)
        return batch

    def _load_images(self, images, name: str = "images", limit: int | None = None,
                     single: bool = False) -> np.ndarray:
        """Images -> float32 [V, 3, H, W] in [0, 1] at the model's resolution (arguments as
        ``_load_photos``)."""
        return self._model_batch(self._load_photos(images, name, limit, single))

    def _run_encoder(self, batch: np.ndarray, is_reference: np.ndarray):
        """The encoder graph on ``batch [V, 3, H, W]`` with ``is_reference`` bool [V] -> field_maps
        float32 [V, C', h, w], world_from_cam float32 [V, 4, 4], focal float32 [2], checked."""
        return self._run_checked("encoder", (FIELD_MAPS, WORLD_FROM_CAM, FOCAL), batch,
                                 is_reference)

    def _run_cameras(self, batch: np.ndarray, is_reference: np.ndarray):
        """``_run_encoder``'s cameras alone: world_from_cam float32 [V, 4, 4], focal float32 [2],
        checked. From the model's "encoder_cameras" graph where it has one (the camera head on its
        own encoder: the field's encoder is not run), else from the encoder graph."""
        if "encoder_cameras" not in self.manifest.graphs:
            return self._run_encoder(batch, is_reference)[1:]
        return self._run_checked("encoder_cameras", (WORLD_FROM_CAM, FOCAL), batch, is_reference)

    def _run_checked(self, graph: str, names: tuple[str, ...], batch: np.ndarray,
                     is_reference: np.ndarray) -> tuple[np.ndarray, ...]:
        """Outputs ``names`` of an encoder ``graph`` on ``batch`` and ``is_reference``; a wrong
        shape or a NaN or inf (finite images in [0, 1] never give one) is a ``ModelFileError``
        naming the graph's file."""
        outs = self._session(graph).run(
            list(names), {IMAGES: batch, IS_REFERENCE: np.ascontiguousarray(is_reference, bool)})
        V, channels = batch.shape[0], self.manifest.field_channels

        def fits(name: str, x: np.ndarray) -> bool:
            if name == FIELD_MAPS:
                return x.ndim == 4 and x.shape[0] == V and (not channels or x.shape[1] == channels)
            return x.shape == {WORLD_FROM_CAM: (V, 4, 4), FOCAL: (2,)}[name]

        path = self.manifest.graphs[graph].path
        expected = {FIELD_MAPS: "[V, C', h, w]", WORLD_FROM_CAM: "[V, 4, 4]", FOCAL: "[2]"}
        if not all(fits(n, x) for n, x in zip(names, outs)):
            raise ModelFileError(
                f"{path}: {graph} returned " + ", ".join(f"{n} {x.shape}" for n, x in
                                                         zip(names, outs))
                + f" for {V} views; expected " + ", ".join(expected[n] for n in names))
        if not all(np.all(np.isfinite(x)) for x in outs):
            raise ModelFileError(f"{path}: {graph} returned NaN or inf for finite images in "
                                 f"[0, 1] (broken weights?)")
        return tuple(outs)

    def _blas_threads(self):
        """A context in which numpy's BLAS runs at most ``threads`` threads (the camera solve's
        and refinement's matrix products): left to its default, one BLAS thread per core
        contends with the rest of a busy machine, and an encode on one thread beside one busy
        core took three times as long (docs/PERFORMANCE.md, "Threads"). The limit is
        process-wide while it holds (threadpoolctl); with ``threads`` None, nothing changes."""
        if self.threads is None:
            return contextlib.nullcontext()
        if self._blas is None:
            from threadpoolctl import ThreadpoolController
            self._blas = ThreadpoolController()
        return self._blas.limit(limits=self.threads, user_api="blas")

    @property
    def default_cameras(self) -> str:
        """``encode``'s cameras when none are asked for: the manifest's "cameras" ("solve" for
        a model trained by ``iris-train --render-cameras solve``, "refined" where its camera
        head was then distilled from the solve, as the shipped model's, else "model")."""
        return self.manifest.cameras

    def encode(self, images, cameras: str | None = None) -> Scene:
        """Run the encoder on ``images`` (a sequence of HxWx3 uint8 RGB arrays, PIL images or
        file paths, any size: centre-cropped to the model's aspect ratio and resized, see
        ``iris_runtime.images.fit_to_model``), every image a reference -> an immutable ``Scene``
        (which keeps the model-resolution images for ``locate``).

        cameras: None (default): ``default_cameras``, the cameras this model's renderer was
                 trained with (the manifest's "cameras").
                 "model": the encoder's predicted cameras and focal.
                 "solve": the field maps are the encoder's as always, but the cameras are
                 solved from the photos themselves at their own resolution (a copy at most
                 ``images.CAMERA_WORKING_SIZE`` on the longer side, ``images.camera_copies``)
                 by ``iris_runtime.cameras.solve_cameras``: SIFT matches across every pair,
                 two-view model selection, incremental mapping with bundle adjustment of the
                 poses and the focal; the centres scaled so that the scene's median point
                 depth lies ``cameras.DEPTH_TARGET`` of the way into the renderer's depth range
                 [near, far]. The solved focal, carried through the crop and resize to the
                 model's resolution, becomes the Scene's ``focal`` and ``K`` (the encoder's
                 focal and poses are kept in ``Scene.encoder_focal`` and
                 ``Scene.encoder_world_from_cam``); ``Scene.camera_size`` says the resolution
                 the cameras were solved at and ``Scene.camera_status`` how each view was
                 posed. A view the solve cannot pose keeps the encoder's camera
                 (``camera_status`` "unposed", ``camera_source`` "mixed"; all of them, and
                 ``camera_source`` "model", when view 0 is not posed, since it defines the
                 frame). Cost and accuracy: docs/CAMERAS.md.
                 "refined": as "solve", but the encoder's cameras and focal are the start of
                 one bundle adjustment on the same matches (``cameras.refine_cameras``: no
                 incremental mapper, a fraction of the solve's time) instead of being replaced;
                 ``camera_source`` "refined". The start is the encoder's prediction with the
                 photos in ``cameras.canonical_order`` (a second encoder run where that order
                 differs), so that, as the solve's, the cameras do not depend on the order the
                 photos come in. Where the photos cannot constrain the cameras
                 (fewer than two views keep enough observations), view 0 is not refined, or the
                 adjustment from no other start agrees with the one kept (a wrong minimum,
                 ``cameras.refine.AgreementOptions``), the solve replaces them as with "solve".
                 As accurate as the encoder's start is close (docs/CAMERAS.md, "Refining the
                 model's cameras").
        """
        return self._encode(images, {}, self._check_cameras(
            self.default_cameras if cameras is None else cameras))

    @staticmethod
    def _check_cameras(cameras) -> str:
        cameras = camera_name(cameras)          # a former name (manifest.CAMERA_ALIASES) too
        if not isinstance(cameras, str) or cameras not in CAMERAS:
            raise InputError(f"cameras: expected one of {list(CAMERAS)}, got {cameras!r}")
        return cameras

    def _encode(self, images, timings: dict, cameras: str = "model") -> Scene:
        t0 = time.perf_counter()
        photos = self._load_photos(images)
        batch = self._model_batch(photos)
        t1 = time.perf_counter()
        maps, world_from_cam, focal = self._run_encoder(batch, np.ones(batch.shape[0], bool))
        t2 = time.perf_counter()
        timings["load"] = timings.get("load", 0.0) + (t1 - t0)
        timings["encode"] = timings.get("encode", 0.0) + (t2 - t1)
        H, W = self.image_size
        focal64 = focal.astype(np.float64)
        poses64 = world_from_cam.astype(np.float64)
        model_id = self.manifest.graphs["encoder"].sha256
        model_K = G.intrinsics_from_focal(focal64, H, W)
        # Explicit colour: the photos as given (cropped, bounded) for colours finer than the
        # model's pixels (iris_runtime.colour).
        kept = (tuple(keep_photo(p, (H, W)) for p in photos) if self.manifest.explicit_rgb
                else None)
        if cameras == "model":
            return Scene(maps, poses64, focal64, model_K, (H, W), model_id, batch, photos=kept)
        from .cameras import canonical_start, refine_model_cameras, replace_model_cameras
        with self._blas_threads():
            if cameras == "refined":
                start, start_focal = canonical_start(
                    photos, poses64, focal64,
                    lambda perm: self._run_cameras(batch[perm], np.ones(len(perm), bool)))
                cams = refine_model_cameras(photos, start, start_focal, (H, W),
                                            (self.near, self.far))
            else:
                cams = replace_model_cameras(photos, poses64, focal64, (H, W),
                                             (self.near, self.far))
        timings["cameras"] = timings.get("cameras", 0.0) + (time.perf_counter() - t2)
        return Scene(maps, cams.world_from_cam, cams.focal, cams.K, (H, W), model_id, batch,
                     camera_source=cams.source,
                     encoder_focal=None if cams.source == "model" else focal64,
                     camera_size=cams.camera_size, camera_status=cams.status,
                     camera_solve=cams.solve,
                     encoder_world_from_cam=None if cams.source == "model" else poses64,
                     photos=kept)

    # -- locating ---------------------------------------------------------------------------
    def locate(self, scene: Scene, image, *, with_status: bool = False):
        """Pose of a new photo in ``scene``'s frame, without changing the scene.

        scene:  a ``Scene`` from ``encode`` of this model (or its ``subset``: same frame).
        image:  one photo (path, PIL image or HxWx3 array, any size: fitted like ``encode``'s
                images) or a sequence of them.

        Runs the encoder graph on the scene's reference images followed by the photo(s) as
        queries: each photo sees the references and itself, never the other photos, so locating
        several at once equals locating them one by one, up to float rounding (batches of at most
        ``max_views`` views per encoder call, references included, and at least one photo per
        call; at most ``MAX_LOCATE_CALLS`` calls). Returns ``world_from_cam`` float64 ``[4, 4]``
        for one photo, ``[Q, 4, 4]`` for a sequence (OpenCV axes, the scene's canonical frame:
        its first reference is the identity; the scene's shared focal applies).

        For a Scene whose cameras were solved from its photos (``Scene.camera_solve``, from
        ``cameras="solve"``) the pose is solved the same way, with the scene's cameras held
        fixed: the photo, at its own resolution brought to ``Scene.camera_size`` (a centre crop
        when its aspect differs: it is taken to come from the same camera), is matched against
        the scene's points and posed by PnP (``iris_runtime.cameras.locate_photos``), in the
        scene's frame and unit. A photo it cannot pose gets the model's prediction, which lies
        in the frame of the encoder's reference cameras (same view 0 but another unit).
        Otherwise the pose is the model's prediction.

        with_status: also return, per photo, "located" (posed against the scene's points) or
        "unposed" (the model's prediction): ``(poses, status)``, status a str or a tuple.
        """
        if not isinstance(scene, Scene):
            raise InputError(f"scene: expected a Scene from IrisRuntime.encode, got "
                             f"{type(scene).__name__}")
        self._check_scene(scene, "scene")
        refs = scene.reference_images
        if refs is None:
            raise InputError("scene: this Scene holds no reference images (it was built by hand, "
                             "not by IrisRuntime.encode); locate needs them to run the encoder")
        single = _is_single_image(image)
        if not single and (isinstance(image, (dict, set)) or not hasattr(image, "__iter__")):
            raise InputError(f"image: expected one photo (a path, a PIL image or an HxWx3 array) "
                             f"or a sequence of them, got {type(image).__name__}")
        N = refs.shape[0]
        per_call = max(1, self.max_views - N)
        photos = self._load_photos([image] if single else image, "image",
                                   limit=per_call * MAX_LOCATE_CALLS, single=single)
        queries = self._model_batch(photos)
        poses = []
        for start in range(0, queries.shape[0], per_call):
            chunk = queries[start:start + per_call]
            batch = np.concatenate([refs, chunk])
            world_from_cam, focal = self._run_cameras(batch, np.arange(batch.shape[0]) < N)
            expected = scene.focal if scene.encoder_focal is None else scene.encoder_focal
            if np.abs(focal.astype(np.float64) - expected).max() > 1e-6:   # bitwise when real
                raise InputError(f"scene: its reference_images give focal {focal.tolist()}, not "
                                 f"the encoder's {expected.tolist()} of the scene (not the "
                                 f"images it was encoded from)")
            poses.append(world_from_cam[N:].astype(np.float64))
        poses = np.concatenate(poses)
        located = np.zeros(len(photos), bool)
        solve = scene.camera_solve
        if solve is not None:
            with self._blas_threads():
                solved, located = solve.locate(photos)
            poses = np.where(located[:, None, None], solved, poses)
        if not with_status:
            return poses[0] if single else poses
        status = tuple("located" if ok else "unposed" for ok in located.tolist())
        return (poses[0], status[0]) if single else (poses, status)

    # -- rendering --------------------------------------------------------------------------
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
                    ``depth_window``, ``depth_mass``, ``field_scale``, ``colour_samples``; any
                    other name is an ``InputError``.

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
            settings = dataclasses.replace(settings, field_scale=None)   # a preset: adapts
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
            select_views=job.select_views, **subset)
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
        rgb, depth = detail.compose_fine(
            detail.CoarseField((hc, wc), coarse.weights, coarse.residual, coarse.depth), h, w,
            job.K, job.world_from_cam, G.sample_depths(self.near, self.far, job.samples, 1,
                                                       dtype=np.float32)[0],
            scene.K.astype(np.float32), G.invert_pose(scene.world_from_cam).astype(np.float32),
            scene.image_size, colours, job.settings.colour_samples)
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

    # .. argument checks ......................................................................
    def _check_scene(self, scene: Scene, name: str = "images_or_scene") -> None:
        enc = self.manifest.graphs["encoder"].sha256
        if scene.model_id and scene.model_id != enc:
            raise InputError(f"{name}: this Scene was encoded by another model "
                             f"(encoder sha256 {scene.model_id[:12]}..., this model {enc[:12]}...)")
        channels = self.manifest.field_channels
        if tuple(scene.image_size) != tuple(self.image_size) or (
                channels and scene.field_maps.shape[1] != channels):
            raise InputError(f"{name}: Scene of image size {scene.image_size} with "
                             f"{scene.field_maps.shape[1]} channels; this model has "
                             f"{self.image_size} and {channels}")

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

    def _empty_ray_rgb(self, scene: Scene, graph: str) -> np.ndarray:
        """The renderer's colour for a ray with no valid sample (``raymarch.empty_ray_rgb``),
        asked of each graph once."""
        rgb = self._empty_rgb.get(graph)
        if rgb is None:
            rgb = raymarch.empty_ray_rgb(self._session(graph), scene.field_maps.shape,
                                         self.manifest.explicit_rgb)
            self._empty_rgb[graph] = rgb       # idempotent: a race computes the same value twice
        return rgb
