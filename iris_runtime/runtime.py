"""IrisRuntime: run an exported IRIS model (encoder.onnx + renderer.onnx + iris.json) with
ONNX Runtime on the CPU, torch-free.

    rt = IrisRuntime("out/")                      # checks the manifest and the graphs' sha256
    image = rt.render(images, pose)               # one shot: encode, then render one pose
    scene = rt.encode(images)                     # run the encoder once (the expensive half) ...
    result = rt.render(scene, 2, depth=True)      # ... and render many poses from it
    pose = rt.locate(scene, photo)                # a new photo's world_from_cam; scene unchanged

References and queries: ``encode`` runs the encoder graph with every image a reference.
``locate`` runs it again on the scene's reference images (kept, read-only, in the ``Scene``)
followed by the photos as queries (``is_reference = [True] * V + [False] * Q``): a reference's
tokens attend to references only, a query's to the references and itself, so the references'
features and cameras are those of the scene (bitwise, in ONNX Runtime) and the query's pose comes
out in the scene's frame. The scene is not changed and queries never see each other.

Cameras follow DESIGN.md: OpenCV axes, ``world_from_cam`` 4x4, canonical frame = view 0's camera,
intrinsics in pixels with pixel centres at (j + 0.5, i + 0.5).

What happens per chunk of rays (numpy, ``iris_runtime.geometry``): rays through the pixel
centres, deterministic bin-centre depths in [near, far], sample points, their projection into
every reference view (``cam_from_world = invert_pose(world_from_cam)``), the normalised grid
coordinates, the validity mask and the geometric cue (target centre = the ray origin). The
renderer graph samples the field maps itself (GridSample) and returns rgb and per-sample weights;
depth = sum(weights * z).

Explicit-colour models (``config.explicit_rgb`` in the manifest, e.g. preset ``tiny-rgb``): per
renderer call the reference photos' RGB is sampled in numpy at the same grid positions as the
field maps (``geometry.sample_bilinear_views``: bilinear, align_corners=False, border-clamped,
full model resolution, float32) for the call's views and packed samples and fed as ``colours``
[V', R, S, 3]. Each view's photo is ``Scene.reference_images[Scene.image_index]``, so ``subset``
and hand-built Scenes say which photo a view is; reference photos stay at the model's resolution
whatever the output size, scale or sample count. Masked (view, sample) pairs carry colours too
(ignored by the graph), so every culling, top_k, samples, scale, int8 and workers path feeds the
graph exactly what it feeds without explicit colour, plus the colours of the same samples.

Culling (exact): samples that project validly into no reference view, views into which no sample
of the chunk projects, and rays without any valid sample carry no information — the renderer
masks them out of every attention, pool and weight (see iris_train/ray_renderer.py), so dropping
them changes nothing but the float rounding of sums. Each chunk is therefore packed to the valid
samples of each ray (in depth order, padded to the chunk's longest ray with masked samples),
the views that see the chunk, and the rays that see anything; an empty ray gets the renderer's
answer to an empty ray (``rgb = head(0)``, zero weights, depth 0), computed once per runtime.
"""
from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import onnxruntime as ort

from . import geometry as G
from . import quality as Q
from .errors import InputError, ManifestError, ModelFileError
from .images import fit_to_model, load_image
from .manifest import MANIFEST_NAME, Manifest, read_graph_bytes, read_manifest

__all__ = ["IrisRuntime", "Scene", "RenderResult", "check_pose", "CAMERAS", "CAMERA_SOURCES",
           "RENDER_BUDGET", "MAX_CHUNK_RAYS",
           "MAX_OUTPUT_PIXELS", "MAX_ENCODER_TOKENS", "MAX_CHUNK_SAMPLES", "MAX_LOCATE_CALLS",
           "render_memory_bound",
           "PRECISIONS", "RenderSettings", "QUALITY_PRESETS"]

RenderSettings = Q.RenderSettings
QUALITY_PRESETS = Q.QUALITY_PRESETS

#: Values of ``IrisRuntime.encode(images, cameras=...)``: the encoder's cameras, or the global
#: epipolar solve of the images (``iris_runtime.epipolar.refine_cameras``).
CAMERAS = ("model", "epipolar")
#: Values of ``Scene.camera_source``.
CAMERA_SOURCES = ("model", "epipolar", "mixed")

#: Rays per renderer call: ``min(MAX_CHUNK_RAYS, RENDER_BUDGET // (S * V))``, V the scene's
#: reference views (the worst case of the culled V'): 256 rays for 1-2 views, 128 for 4, 64 for 8
#: at S = 64. Measured with benchmarks/runtime_chunks.py (tiny model, 1 thread, CPU time; results
#: in benchmarks/results/runtime_chunks.json): bigger chunks are not faster per ray (V = 1: 0.97 s
#: per 1000 rays at 128 rays per call, 1.34 at 8192; V = 4: 2.04 at 32, 2.31 at 128, 2.44 at 2048;
#: V = 8: 3.6 from 16 to 256, 4.0 at 1024), while ONNX Runtime's peak memory grows linearly with
#: the chunk, about 1.2 + 0.1 V MB per ray (V = 4: +0.18 GB at 128 rays, +0.72 GB at 512, +1.65 GB
#: at 2048; V = 8: +2.2 GB at 1024). ONNX-NOTES.md's "R * V ~ 8k" (R * S * V = 512k) would cost
#: 1.5-2.5 GB for no gain; this budget keeps a chunk near 0.1-0.35 GB.
RENDER_BUDGET = 32 * 1024
MAX_CHUNK_RAYS = 256

# -- Request limits (checked before anything is allocated; exceeding one raises InputError) --------
#: Output pixels per render (4096 x 4096). The output is assembled whole: float32 rgb + depth, the
#: uint8 image and the clipping temporaries take ~31 bytes per pixel, 0.5 GB at this limit (and
#: the render itself ~1-2 ms of CPU per ray: hours). Larger views: render tiles with ``intrinsics``.
MAX_OUTPUT_PIXELS = 4096 * 4096
#: Encoder tokens per ``encode`` call: views x (patches per view + 1 camera token). Cross-view
#: attention memory grows with the square of the tokens (tiny model, 64 tokens + 1 per view,
#: measured peak RSS over the runtime's: 32 views +0.22 GB, 128 views +2.5 GB; ONNX-NOTES.md: 8192
#: tokens 4.1 GB). 4160 tokens (64 views of the tiny model, 16 of the paper preset) stay under
#: ~0.7 GB. ``IrisRuntime.max_views`` is this limit in views of the model at hand.
MAX_ENCODER_TOKENS = 4160
#: Rays x samples x views per renderer call when ``chunk_rays`` is given explicitly (8 x the default
#: budget): ONNX Runtime's peak grows linearly with it (``render_memory_bound``), ~1 GB here.
MAX_CHUNK_SAMPLES = 8 * RENDER_BUDGET
#: Encoder calls one ``locate`` may make: photos per call are ``max_views`` minus the scene's
#: references (at least 1), so one call locates up to this many batches (bounded work per request).
MAX_LOCATE_CALLS = 64


def render_memory_bound(num_views: int, chunk_rays: int, samples: int = 64,
                        concurrent: int = 1) -> int:
    """Documented bound (bytes) of the memory that ``concurrent`` renders in flight add to a warm
    runtime: per renderer call (1.2 + 0.1 V) MB per ray at S = 64 samples, scaled by S / 64 (the
    measurements of ``RENDER_BUDGET``'s comment, rounded up to 1.5 + 0.15 V), plus 64 MB of numpy
    geometry and allocator slack per call. The 8-thread load test of tests/test_stability.py
    checks it."""
    per_ray = (1.5 + 0.15 * num_views) * 2 ** 20 * samples / 64
    return int(concurrent * (chunk_rays * per_ray + 64 * 2 ** 20))

#: Renderer graph per precision: "int8" is the dynamically quantised variant iris-export writes with
#: --quantize int8 (its error vs torch is in the manifest's validation report). Dynamic quantisation
#: scales activations per call, so int8 results depend slightly on how rays are chunked.
PRECISIONS = {"float32": "renderer", "int8": "renderer_int8"}

# Bilinear sampling of the field maps runs inside the renderer graph (ONNX GridSample,
# align_corners=False, border padding), not in numpy or OpenCV. Measured in ONNX-NOTES.md (4 views
# x 64 channels x 32^2 grid, 262k points per view): ORT GridSample 161 ms and exact; cv2.remap
# 107 ms but NOT exact (it quantises the bilinear weights to 1/32 px: errors 0.13-0.15); numpy
# channel-last gather 513 ms; numpy channel-first 3.9-4.7 s. Exactness (parity with torch to 1e-4)
# decides for GridSample, which is also the fastest exact option.


def _is_single_image(x) -> bool:
    """One image (a path, a PIL image, an HxW(xC) array) rather than a sequence of images."""
    return (isinstance(x, (str, os.PathLike, bytes)) or hasattr(x, "getpixel")
            or (isinstance(x, np.ndarray) and x.ndim != 4))


def _readonly(a, dtype) -> np.ndarray:
    out = np.array(a, dtype=dtype, copy=True, order="C")
    out.setflags(write=False)
    return out


def check_pose(pose, name: str = "pose") -> np.ndarray:
    """``pose`` as a float64 4x4 rigid ``world_from_cam``, or ``InputError`` naming ``name`` and
    what is wrong: not numeric, shape, NaN/inf, singular, mirrored (det < 0), not orthonormal,
    last row not [0, 0, 0, 1] (``geometry.is_rigid``, tolerance 1e-4)."""
    try:
        T = np.asarray(pose)
    except Exception:
        T = np.asarray(None, dtype=object)
    if T.dtype == object or not (np.issubdtype(T.dtype, np.floating)
                                 or np.issubdtype(T.dtype, np.integer)):
        raise InputError(f"{name}: expected a 4x4 world_from_cam matrix of numbers, got "
                         f"{type(pose).__name__} of dtype {T.dtype}")
    if T.shape != (4, 4):
        raise InputError(f"{name}: expected a 4x4 world_from_cam matrix, got shape {T.shape}")
    T = T.astype(np.float64)
    if not np.all(np.isfinite(T)):
        raise InputError(f"{name}: contains NaN or inf")
    if not G.is_rigid(T):
        R = T[:3, :3]
        det = float(np.linalg.det(R))
        if abs(det) < 1e-6:
            why = f"its rotation block is singular (det {det:.2g})"
        elif det < 0:
            why = f"it is mirrored (det {det:.3g} < 0): a reflection is not a camera pose"
        elif not np.allclose(T[3], [0, 0, 0, 1], atol=1e-4):
            why = f"its last row is {T[3].tolist()}, expected [0, 0, 0, 1]"
        else:
            err = float(np.abs(R.T @ R - np.eye(3)).max())
            why = (f"its rotation block is not orthonormal (max |R^T R - I| = {err:.2g}, "
                   f"det {det:.4g})")
        raise InputError(f"{name}: expected a rigid world_from_cam transform (orthonormal rotation "
                         f"with det +1, last row [0, 0, 0, 1]), but {why}")
    return T


@dataclass(frozen=True, eq=False)
class Scene:
    """What the encoder leaves for rendering (immutable; arrays are read-only copies).

    field_maps:     float32 [V, C', h, w]  per-view field maps the renderer samples
    world_from_cam: float64 [V, 4, 4]      predicted poses, OpenCV axes, view 0 = identity
    focal:          float64 [2]            shared focal (fx / W, fy / H), normalised
    K:              float64 [3, 3]         intrinsics in pixels of the model's resolution
    image_size:     (H, W)                 the model's resolution
    model_id:       sha256 of the encoder graph that made the scene ('' if unknown)
    reference_images: float32 [N, 3, H, W] in [0, 1], the model-resolution images the scene was
                    encoded from, what ``IrisRuntime.locate`` runs the encoder on (all N of them,
                    also after ``subset``, which keeps the frame and so the images that define it);
                    None for a Scene built by hand (``locate`` refuses it)
    image_index:    int64 [V], the row of ``reference_images`` that each view was encoded from
                    (``subset`` keeps it in step with the views): where explicit-colour models
                    read each view's photo. Default: ``arange(V)`` when there are V reference
                    images, else None (unknown; explicit-colour renders refuse such a Scene)
    camera_source:  where ``world_from_cam`` comes from: "model" (the encoder's prediction),
                    "epipolar" (``encode(..., cameras="epipolar")``: every view from the global
                    epipolar solve, ``iris_runtime.epipolar.refine_cameras``) or "mixed" (the
                    solve reached only some views through trusted pairs; the others keep the
                    model's camera). ``subset`` keeps the value of the scene it was cut from
    encoder_focal:  float64 [2], the focal the encoder predicted when ``focal`` is another one
                    (``cameras="epipolar"`` puts the grid-searched focal in ``focal`` and ``K``);
                    None when ``focal`` is the encoder's. ``locate`` checks the reference images
                    against it
    """
    field_maps: np.ndarray
    world_from_cam: np.ndarray
    focal: np.ndarray
    K: np.ndarray
    image_size: tuple[int, int]
    model_id: str = ""
    reference_images: np.ndarray | None = field(default=None, repr=False)
    image_index: np.ndarray | None = field(default=None, repr=False)
    camera_source: str = "model"
    encoder_focal: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self):
        arrays = {}
        for name, dtype in (("field_maps", np.float32), ("world_from_cam", np.float64),
                            ("focal", np.float64), ("K", np.float64)):
            try:
                arrays[name] = _readonly(getattr(self, name), dtype)
            except (TypeError, ValueError):
                raise InputError(f"{name}: expected an array of numbers, got "
                                 f"{type(getattr(self, name)).__name__}") from None
            if not np.all(np.isfinite(arrays[name])):
                raise InputError(f"{name}: contains NaN or inf")
        maps, poses, focal, K = (arrays[k] for k in ("field_maps", "world_from_cam", "focal", "K"))
        if maps.ndim != 4 or maps.shape[0] == 0:
            raise InputError(f"field_maps: expected [V, C', h, w] with V >= 1, got {maps.shape}")
        V = maps.shape[0]
        if poses.shape != (V, 4, 4):
            raise InputError(f"world_from_cam: expected [{V}, 4, 4], got {poses.shape}")
        if focal.shape != (2,) or K.shape != (3, 3):
            raise InputError(f"focal, K: expected [2] and [3, 3], got {focal.shape} and {K.shape}")
        if not np.all(focal > 0) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise InputError(f"focal, K: expected positive focal lengths, got focal "
                             f"{focal.tolist()} and K diagonal {np.diag(K).tolist()}")
        for i in range(V):
            if not G.is_rigid(poses[i]):
                check_pose(poses[i], f"world_from_cam[{i}]")   # raises, saying what is wrong
        size = tuple(int(s) for s in self.image_size)
        if len(size) != 2 or min(size) <= 0:
            raise InputError(f"image_size: expected (H, W) positive, got {self.image_size!r}")
        refs = self.reference_images
        if refs is not None:
            try:
                refs = _readonly(refs, np.float32)
            except (TypeError, ValueError):
                raise InputError(f"reference_images: expected an array of numbers or None, got "
                                 f"{type(self.reference_images).__name__}") from None
            if refs.ndim != 4 or refs.shape[0] == 0 or refs.shape[1:] != (3, *size):
                raise InputError(f"reference_images: expected [N, 3, {size[0]}, {size[1]}] with "
                                 f"N >= 1, got {refs.shape}")
            if not (np.all(np.isfinite(refs)) and refs.min() >= 0.0 and refs.max() <= 1.0):
                raise InputError("reference_images: expected values in [0, 1] (no NaN or inf)")
        index = self.image_index
        if index is not None:
            if refs is None:
                raise InputError("image_index: given without reference_images (it indexes them)")
            try:
                index = np.asarray(index)
            except (TypeError, ValueError):
                index = np.asarray(None, dtype=object)
            if index.shape != (V,) or not np.issubdtype(index.dtype, np.integer) \
                    or index.min() < 0 or index.max() >= refs.shape[0]:
                raise InputError(f"image_index: expected {V} integers in 0..{refs.shape[0] - 1} "
                                 f"(the reference image of each view), got {self.image_index!r}")
            index = _readonly(index, np.int64)
        elif refs is not None and refs.shape[0] == V:
            index = _readonly(np.arange(V), np.int64)
        if not isinstance(self.camera_source, str) or self.camera_source not in CAMERA_SOURCES:
            raise InputError(f"camera_source: expected one of {list(CAMERA_SOURCES)}, got "
                             f"{self.camera_source!r}")
        enc_focal = self.encoder_focal
        if enc_focal is not None:
            try:
                enc_focal = _readonly(enc_focal, np.float64)
            except (TypeError, ValueError):
                raise InputError(f"encoder_focal: expected [2] numbers or None, got "
                                 f"{type(self.encoder_focal).__name__}") from None
            if enc_focal.shape != (2,) or not (np.all(np.isfinite(enc_focal))
                                               and np.all(enc_focal > 0)):
                raise InputError(f"encoder_focal: expected [2] positive finite numbers or None, "
                                 f"got {enc_focal.tolist()}")
        for name, value in (("field_maps", maps), ("world_from_cam", poses), ("focal", focal),
                            ("image_size", size), ("K", K), ("reference_images", refs),
                            ("image_index", index), ("encoder_focal", enc_focal)):
            object.__setattr__(self, name, value)

    @property
    def num_views(self) -> int:
        return self.field_maps.shape[0]

    def intrinsics(self, height: int | None = None, width: int | None = None) -> np.ndarray:
        """``K [3, 3]`` (float64) of the shared focal for an image of (height, width) pixels
        (default: the model's resolution)."""
        H, W = self.image_size
        return G.intrinsics_from_focal(self.focal, height or H, width or W).astype(np.float64)

    def subset(self, indices: Sequence[int]) -> "Scene":
        """A scene keeping only views ``indices`` (in that order) as references, in the same
        camera frame (poses are not re-based: view 0 of the original stays the world frame)."""
        try:
            idx = np.asarray(list(indices) if not isinstance(indices, np.ndarray) else indices)
        except (TypeError, ValueError):
            raise InputError(f"indices: expected a non-empty sequence of view indices (ints), "
                             f"got {indices!r}") from None
        V = self.num_views
        if idx.ndim != 1 or idx.size == 0 or not (np.issubdtype(idx.dtype, np.integer)):
            raise InputError(f"indices: expected a non-empty sequence of view indices (ints), "
                             f"got {indices!r}")
        if idx.min() < 0 or idx.max() >= V:
            raise InputError(f"indices: view index out of range 0..{V - 1}: {idx.tolist()}")
        if len(set(idx.tolist())) != idx.size:
            raise InputError(f"indices: repeated view index in {idx.tolist()} (a view counted "
                             f"twice would weigh twice in the view attention)")
        return Scene(self.field_maps[idx], self.world_from_cam[idx], self.focal, self.K,
                     self.image_size, self.model_id, self.reference_images,
                     None if self.image_index is None else self.image_index[idx],
                     self.camera_source, self.encoder_focal)

    def __repr__(self) -> str:
        return (f"Scene(views={self.num_views}, field_maps={tuple(self.field_maps.shape)}, "
                f"image_size={self.image_size}, focal={np.round(self.focal, 4).tolist()}, "
                f"camera_source={self.camera_source!r})")


@dataclass(frozen=True, eq=False)
class RenderResult:
    """One rendered view.

    image:       uint8   [H, W, 3] RGB
    image_float: float32 [H, W, 3] RGB in [0, 1] (what the renderer returned)
    depth:       float32 [H, W]    soft camera depth sum_m w_m z_m in model units, within
                                   [near, far]; 0 where no sample sees any reference view
    timings:     seconds per stage (``load``/``encode`` when images were given, ``rays``: numpy
                 geometry, ``renderer``: ONNX Runtime, ``upsample`` when scale < 1, ``total``)
    work:        what the renderer graph was given: ``calls``, and over the calls the sums of
                 R (``rays``), R*S (``points``), R*S*V' (``point_views``) and R*S^2
                 (``ray_pairs``), R/S/V' the rays, samples and views of a call (FLOP counts)
    settings:    the ``RenderSettings`` used
    """
    image: np.ndarray
    image_float: np.ndarray
    depth: np.ndarray
    timings: dict = field(default_factory=dict)
    work: dict = field(default_factory=dict)
    settings: "Q.RenderSettings | None" = None


class IrisRuntime:
    """An exported IRIS model, run with ONNX Runtime (see the module docstring).

    ``threads``: intra-op threads of each ONNX Runtime session (None: ORT's default, one per
    physical core). ``precision``: "float32" (default) or "int8" (the quantised renderer, when
    the model was exported with ``--quantize int8``). ``cull``: skip samples, views and rays
    that see no reference view (exact, see the module docstring; False only to check that).
    ``workers``: renderer calls in flight at once within one render (Python threads over blocks of
    rays, exact: the same calls, only concurrent); with ``workers > 1`` each renderer session
    runs ``max(1, threads // workers)`` intra-op threads (``threads`` None: the usable CPUs), so
    ``workers=2`` on 2 cores is data-parallel instead of ORT's op-parallel threading.
    Construction reads and checks ``iris.json`` and the sha256 of both graphs; sessions are
    created on first use (and the graph bytes hashed again, so the graph that runs is the one
    that was checked). Safe to share between threads.
    """

    def __init__(self, model_dir: str | os.PathLike, threads: int | None = None, *,
                 precision: str = "float32", cull: bool = True, workers: int = 1):
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
        self.manifest: Manifest = read_manifest(model_dir)
        self.model_dir: Path = self.manifest.model_dir
        self.threads = None if threads is None else int(threads)
        self.precision = precision
        self._renderer = PRECISIONS[precision]
        if self._renderer not in self.manifest.graphs:
            raise ManifestError(f"{self.model_dir / MANIFEST_NAME}: no {precision} renderer "
                                f"(graphs.{self._renderer}); export with --quantize int8 for it")
        self.cull = bool(cull)
        self.workers = int(workers)
        self._sessions: dict[str, ort.InferenceSession] = {}
        self._lock = threading.Lock()
        self._empty_rgb: dict[str, np.ndarray] = {}       # per renderer graph

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
    def max_views(self) -> int:
        """Most images one ``encode`` accepts: ``MAX_ENCODER_TOKENS`` // (patches per view + 1)."""
        H, W = self.image_size
        p = self.manifest.config.get("patch_size", 8)
        p = p if isinstance(p, int) and not isinstance(p, bool) and p > 0 else 8
        return MAX_ENCODER_TOKENS // ((H // p) * (W // p) + 1)

    def default_chunk_rays(self, num_views: int, samples: int | None = None) -> int:
        """Rays per renderer call: R * S * V near ``RENDER_BUDGET``, at most ``MAX_CHUNK_RAYS``."""
        S = samples or self.samples
        return min(MAX_CHUNK_RAYS, max(1, RENDER_BUDGET // (S * max(1, num_views))))

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
        if self.workers > 1 and name != "encoder":
            total = self.threads or len(os.sched_getaffinity(0))
            opts.intra_op_num_threads = max(1, total // self.workers)
        opts.inter_op_num_threads = 1
        opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        # Optimise in memory at load; never write the optimised graph (ONNX-NOTES: optimised files
        # are tied to the machine and ORT version that made them).
        opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        opts.log_severity_level = 3
        try:
            session = ort.InferenceSession(data, sess_options=opts,
                                           providers=["CPUExecutionProvider"])
        except Exception as exc:               # ORT raises its own Fail/InvalidGraph types
            raise ModelFileError(f"{entry.path}: onnxruntime cannot load the {name} graph: "
                                 f"{str(exc).strip().splitlines()[0][:300]}") from None
        have_in = {i.name for i in session.get_inputs()}
        have_out = {o.name for o in session.get_outputs()}
        if have_in != set(entry.inputs) or not set(entry.outputs) <= have_out:
            raise ModelFileError(f"{entry.path}: graph I/O {sorted(have_in)} -> {sorted(have_out)} "
                                 f"does not match the manifest's {sorted(entry.inputs)} -> "
                                 f"{sorted(entry.outputs)}")
        return session

    # -- encoding ---------------------------------------------------------------------------
    def _load_images(self, images, name: str = "images", limit: int | None = None,
                     single: bool = False) -> np.ndarray:
        """Images -> float32 [V, 3, H, W] in [0, 1] at the model's resolution (``name``: the
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
        H, W = self.image_size
        batch = np.empty((len(items), 3, H, W), dtype=np.float32)
        for i, item in enumerate(items):
            rgb, _ = fit_to_model(load_image(item, name if single else f"{name}[{i}]"), H, W)
            batch[i] = rgb.transpose(2, 0, 1)
        batch *= np.float32(1.0 / 255.0)
        return batch

    def _run_encoder(self, batch: np.ndarray, is_reference: np.ndarray):
        """The encoder graph on ``batch [V, 3, H, W]`` with ``is_reference`` bool [V] -> field_maps
        float32 [V, C', h, w], world_from_cam float32 [V, 4, 4], focal float32 [2], checked."""
        maps, world_from_cam, focal = self._session("encoder").run(
            ["field_maps", "world_from_cam", "focal"],
            {"images": batch, "is_reference": np.ascontiguousarray(is_reference, dtype=bool)})
        V = batch.shape[0]
        channels = self.manifest.field_channels
        if (maps.ndim != 4 or maps.shape[0] != V or (channels and maps.shape[1] != channels)
                or world_from_cam.shape != (V, 4, 4) or focal.shape != (2,)):
            raise ModelFileError(f"{self.manifest.graphs['encoder'].path}: encoder returned "
                                 f"field_maps {maps.shape}, world_from_cam {world_from_cam.shape}, "
                                 f"focal {focal.shape} for {V} views; expected [V, C', h, w], "
                                 f"[V, 4, 4], [2]")
        if not (np.all(np.isfinite(maps)) and np.all(np.isfinite(world_from_cam))
                and np.all(np.isfinite(focal))):
            raise ModelFileError(f"{self.manifest.graphs['encoder'].path}: the encoder returned NaN "
                                 f"or inf for finite images in [0, 1] (broken weights?)")
        return maps, world_from_cam, focal

    def encode(self, images, cameras: str = "model") -> Scene:
        """Run the encoder on ``images`` (a sequence of HxWx3 uint8 RGB arrays, PIL images or
        file paths, any size: centre-cropped to the model's aspect ratio and resized, see
        ``iris_runtime.images.fit_to_model``), every image a reference -> an immutable ``Scene``
        (which keeps the model-resolution images for ``locate``).

        cameras: "model" (default): the encoder's predicted cameras and focal.
                 "epipolar": the field maps are the encoder's as always, but the poses are the
                 global epipolar solve of the model-resolution images
                 (``iris_runtime.epipolar.refine_cameras``: DIS flow, an essential matrix per
                 pair at the grid-searched focal, rotation and translation averaging), with the
                 centres scaled by least squares onto the encoder's centres (so the renderer
                 keeps its units; collapsed or opposed model centres: the model's mean baseline
                 or ``epipolar.DEFAULT_BASELINE``, see ``epipolar.fit_scale``). The grid-searched
                 focal becomes the Scene's ``focal`` and ``K`` (rendering uses the focal the
                 poses were solved at); the encoder's is kept in ``Scene.encoder_focal``. Views
                 that view 0 does not reach through trusted pairs keep the encoder's camera
                 (``Scene.camera_source`` "mixed"; "model" if none is reached). Costs ~1 s per 8
                 views on one core (V (V - 1) / 2 pairs of flow), beside the encoder.
                 Held-out figures: README, "Epipolar cameras".
        """
        return self._encode(images, {}, self._check_cameras(cameras))

    @staticmethod
    def _check_cameras(cameras) -> str:
        if not isinstance(cameras, str) or cameras not in CAMERAS:
            raise InputError(f"cameras: expected one of {list(CAMERAS)}, got {cameras!r}")
        return cameras

    def _encode(self, images, timings: dict, cameras: str = "model") -> Scene:
        t0 = time.perf_counter()
        batch = self._load_images(images)
        t1 = time.perf_counter()
        maps, world_from_cam, focal = self._run_encoder(batch, np.ones(batch.shape[0], bool))
        t2 = time.perf_counter()
        timings["load"] = timings.get("load", 0.0) + (t1 - t0)
        timings["encode"] = timings.get("encode", 0.0) + (t2 - t1)
        H, W = self.image_size
        focal64 = focal.astype(np.float64)
        poses64 = world_from_cam.astype(np.float64)
        model_id = self.manifest.graphs["encoder"].sha256
        if cameras == "model":
            return Scene(maps, poses64, focal64, G.intrinsics_from_focal(focal64, H, W), (H, W),
                         model_id, batch)
        from . import epipolar
        # The batch is uint8 / 255 in float32: rint(x * 255) gives the uint8 pixels back exactly.
        pixels = np.rint(batch * 255.0).astype(np.uint8).transpose(0, 2, 3, 1)
        ref = epipolar.refine_cameras(pixels, poses64, focal64)
        timings["cameras"] = timings.get("cameras", 0.0) + (time.perf_counter() - t2)
        same_focal = bool(np.array_equal(ref.focal, focal64))
        return Scene(maps, ref.world_from_cam, ref.focal,
                     G.intrinsics_from_focal(ref.focal, H, W), (H, W), model_id, batch,
                     camera_source=ref.source, encoder_focal=None if same_focal else focal64)

    # -- locating ---------------------------------------------------------------------------
    def locate(self, scene: Scene, image) -> np.ndarray:
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

        The pose is always the model's prediction, also for a Scene encoded with
        ``cameras="epipolar"``: it is then in the frame of the encoder's cameras of the
        references, which shares view 0 (= I) and, through the scale fit, the unit with the
        scene's epipolar cameras, but not the other views' rotations. (An epipolar pose of a
        query with the references fixed is ``iris_runtime.epipolar.locate_views``; iris-eval
        measures it, see README "Epipolar cameras"; not wired in here yet.)
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
        queries = self._load_images([image] if single else image, "image",
                                    limit=per_call * MAX_LOCATE_CALLS, single=single)
        poses = []
        for start in range(0, queries.shape[0], per_call):
            chunk = queries[start:start + per_call]
            batch = np.concatenate([refs, chunk])
            _, world_from_cam, focal = self._run_encoder(batch, np.arange(batch.shape[0]) < N)
            expected = scene.focal if scene.encoder_focal is None else scene.encoder_focal
            if np.abs(focal.astype(np.float64) - expected).max() > 1e-6:   # bitwise when real
                raise InputError(f"scene: its reference_images give focal {focal.tolist()}, not "
                                 f"the encoder's {expected.tolist()} of the scene (not the "
                                 f"images it was encoded from)")
            poses.append(world_from_cam[N:].astype(np.float64))
        poses = np.concatenate(poses)
        return poses[0] if single else poses

    # -- rendering --------------------------------------------------------------------------
    def render(self, images_or_scene, pose, *, height: int | None = None, width: int | None = None,
               intrinsics=None, depth: bool = False, chunk_rays: int | None = None,
               progress: Callable[[int, int], None] | None = None,
               quality: "str | Q.RenderSettings | None" = None, samples: int | None = None,
               top_k: int | None = None, top_k_by: str | None = None,
               scale: float | None = None, upsample: str | None = None,
               precision: str | None = None):
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
        chunk_rays: rays per renderer call (default ``default_chunk_rays(V)``); peak memory is
                    bounded by it whatever the output size.
        progress:   called as ``progress(rays_done, rays_total)`` after each chunk.

        Speed/quality (``iris_runtime.quality``; measured error and time in docs/PERFORMANCE.md):
        quality:    a preset, "exact" (default: the full render), "balanced" or "fast"
                    (``QUALITY_PRESETS``), or a ``RenderSettings``; the keywords below override
                    single fields of it.
        samples:    samples per ray (default the model's, 64): bin centres in [near, far].
        top_k:      keep at most this many reference views per point (largest cue t.s among the
                    valid views); ``top_k_by`` "ray" (one set of views per ray, so renderer calls
                    shrink to top_k views) or "point".
        scale:      render at (H, W) * scale and resize to (H, W) (``upsample`` "linear"/"cubic").
        precision:  "float32" or "int8" renderer for this call (default: the runtime's).

        Returns uint8 [H, W, 3] RGB, or a ``RenderResult`` with ``depth=True``.
        """
        t_start = time.perf_counter()
        timings: dict[str, float] = {}
        settings = Q.resolve_settings(quality, samples=samples, top_k=top_k, top_k_by=top_k_by,
                                      scale=scale, upsample=upsample, precision=precision)
        graph = PRECISIONS[settings.precision or self.precision]
        if graph not in self.manifest.graphs:
            raise ManifestError(f"{self.model_dir / MANIFEST_NAME}: no {settings.precision} "
                                f"renderer (graphs.{graph}); export with --quantize int8 for it")
        height, width = self._check_size(height, width)        # before encoding or allocating
        if progress is not None and not callable(progress):
            raise InputError(f"progress: expected a callable progress(done, total) or None, got "
                             f"{type(progress).__name__}")
        if isinstance(images_or_scene, Scene):
            scene = images_or_scene
            self._check_scene(scene)
            self._view_images(scene)                  # explicit colour: the photos are there
        else:
            scene = self._encode(images_or_scene, timings)
        world_from_cam = self._check_pose(pose, scene)
        K = self._check_intrinsics(intrinsics, scene, height, width)
        S = settings.samples or self.samples
        by_ray = settings.top_k is not None and settings.top_k_by == "ray"
        if chunk_rays is None:
            views = min(scene.num_views, settings.top_k) if by_ray else scene.num_views
            chunk_rays = self.default_chunk_rays(views, S)
        elif isinstance(chunk_rays, bool) or not isinstance(chunk_rays, (int, np.integer)) \
                or chunk_rays < 1:
            raise InputError(f"chunk_rays: expected a positive integer, got {chunk_rays!r}")
        elif min(int(chunk_rays), height * width) * S * scene.num_views > MAX_CHUNK_SAMPLES:
            raise InputError(f"chunk_rays: {int(chunk_rays)} rays x {S} samples x "
                             f"{scene.num_views} views per renderer call exceeds "
                             f"MAX_CHUNK_SAMPLES = {MAX_CHUNK_SAMPLES} (memory grows with it); "
                             f"use at most {max(1, MAX_CHUNK_SAMPLES // (S * scene.num_views))}")
        h, w = height, width
        if settings.scale != 1.0:
            h = max(1, int(round(height * settings.scale)))
            w = max(1, int(round(width * settings.scale)))
            if h * w > MAX_OUTPUT_PIXELS:
                raise InputError(f"scale: renders {h}x{w} pixels, more than MAX_OUTPUT_PIXELS = "
                                 f"{MAX_OUTPUT_PIXELS}")
            K = G.scale_intrinsics(K, (height, width), (h, w))
        work: dict[str, int] = {}
        rgb, z = self._render_rays(scene, world_from_cam, K, h, w, int(chunk_rays),
                                   timings, progress, settings, graph, work)
        image_float = rgb.reshape(h, w, 3)
        z = z.reshape(h, w)
        if (h, w) != (height, width):
            t0 = time.perf_counter()
            import cv2                         # only needed for scale < 1
            interp = cv2.INTER_CUBIC if settings.upsample == "cubic" else cv2.INTER_LINEAR
            image_float = np.clip(cv2.resize(image_float, (width, height), interpolation=interp),
                                  0.0, 1.0)
            z = cv2.resize(z, (width, height), interpolation=cv2.INTER_LINEAR)
            timings["upsample"] = time.perf_counter() - t0
        image = np.rint(np.clip(image_float, 0.0, 1.0) * 255.0).astype(np.uint8)
        timings["total"] = time.perf_counter() - t_start
        if not depth:
            return image
        return RenderResult(image, image_float, z, timings, work, settings)

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
        if isinstance(pose, (int, np.integer)) and not isinstance(pose, (bool, np.bool_)):
            V = scene.num_views
            if not 0 <= pose < V:
                raise InputError(f"pose: view index {int(pose)} out of range 0..{V - 1} "
                                 f"(the scene has {V} views)")
            return scene.world_from_cam[int(pose)].copy()
        return check_pose(pose)

    def check_output_size(self, height=None, width=None) -> tuple[int, int]:
        """The (height, width) that ``render`` would produce (None: the model's, or the model's
        aspect for one given side), or ``InputError`` for non-positive / non-integer sizes and for
        more than ``MAX_OUTPUT_PIXELS`` pixels. Allocates nothing (iris-render checks with it
        before writing anything)."""
        Hm, Wm = self.image_size
        for name, v in (("height", height), ("width", width)):
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer))
                                  or v < 1):
                raise InputError(f"{name}: expected a positive integer or None, got {v!r}")
        if height is None and width is None:
            h, w = Hm, Wm
        elif height is None:
            h, w = max(1, round(width * Hm / Wm)), int(width)
        elif width is None:
            h, w = int(height), max(1, round(height * Wm / Hm))
        else:
            h, w = int(height), int(width)
        if h * w > MAX_OUTPUT_PIXELS:
            raise InputError(f"height, width: {h}x{w} = {h * w} output pixels exceeds "
                             f"MAX_OUTPUT_PIXELS = {MAX_OUTPUT_PIXELS} (the output is held in "
                             f"memory whole, ~31 bytes per pixel); render tiles with intrinsics")
        return h, w

    _check_size = check_output_size

    @staticmethod
    def _check_intrinsics(intrinsics, scene: Scene, height: int, width: int) -> np.ndarray:
        if intrinsics is None:
            return scene.intrinsics(height, width)
        try:
            K = np.asarray(intrinsics, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(f"intrinsics: expected a 3x3 matrix of numbers, got "
                             f"{type(intrinsics).__name__}") from None
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise InputError(f"intrinsics: expected a finite 3x3 matrix, got shape {K.shape}")
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0 \
                or K[0, 1] != 0:
            raise InputError("intrinsics: expected pinhole [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] "
                             f"in pixels of the output with fx, fy > 0, got {K.tolist()}")
        return K

    # .. the ray loop ........................................................................
    def _empty_ray_rgb(self, scene: Scene, graph: str | None = None) -> np.ndarray:
        """The renderer's colour for a ray with no valid sample (a constant of the model: every
        input is masked, so nothing of the scene reaches it). Asked of each graph once."""
        graph = graph or self._renderer
        rgb = self._empty_rgb.get(graph)
        if rgb is None:
            _, C, h, w = scene.field_maps.shape
            feed = {"field_maps": np.zeros((1, C, h, w), np.float32),
                    "grid": np.zeros((1, 1, 1, 2), np.float32),
                    "cues": np.zeros((1, 1, 1, 4), np.float32),
                    "mask": np.zeros((1, 1, 1), bool),
                    "positions": np.zeros((1, 1, 3), np.float32),
                    "directions": np.array([[0, 0, 1]], np.float32)}
            if self.manifest.explicit_rgb:     # masked: the blend of nothing, whatever colour
                feed["colours"] = np.zeros((1, 1, 1, 3), np.float32)
            rgb = self._session(graph).run(["rgb"], feed)[0][0]
            rgb.setflags(write=False)
            self._empty_rgb[graph] = rgb       # idempotent: a race computes the same value twice
        return rgb

    def _render_rays(self, scene: Scene, world_from_cam: np.ndarray, K: np.ndarray,
                     height: int, width: int, chunk_rays: int, timings: dict,
                     progress: Callable[[int, int], None] | None,
                     settings: "Q.RenderSettings | None" = None, graph: str | None = None,
                     work: dict | None = None):
        """-> rgb float32 [H*W, 3], depth float32 [H*W] (rows of pixels, row-major).

        Per block of pixels: rays, samples and their projection into every reference view
        (numpy); then one renderer call per (rays, views) group: the whole block when every view
        is kept, or (``top_k_by="ray"``) one call per set of kept views, at most ``chunk_rays``
        rays each. With culling, each call is packed to its rays' valid samples and its views.
        Blocks run on ``self.workers`` threads; each writes its own rows.
        """
        f32 = np.float32
        settings = settings or Q.RenderSettings()
        graph = graph or self._renderer
        work = work if work is not None else {}
        S = settings.samples or self.samples
        k = settings.top_k
        V = scene.num_views
        by_ray = k is not None and settings.top_k_by == "ray" and k < V
        n = height * width
        pose = world_from_cam.astype(f32)
        ctx = {"session": self._session(graph), "scene": scene, "S": S, "k": k, "by_ray": by_ray,
               "K_ref": scene.K.astype(f32),
               "cam_from_world": G.invert_pose(scene.world_from_cam).astype(f32),   # [V, 4, 4]
               "centres": scene.world_from_cam[:, :3, 3].astype(f32),               # [V, 3]
               "pose": pose, "K_out": K.astype(f32), "origin": pose[:3, 3],
               "z_bins": G.sample_depths(self.near, self.far, S, 1, dtype=f32)[0],  # bin centres
               "empty": self._empty_ray_rgb(scene, graph) if self.cull else None,
               "view_images": self._view_images(scene),                            # [V, 3, H, W]
               "width": width, "n": n, "chunk_rays": chunk_rays,
               "rgb": np.empty((n, 3), f32), "depth": np.zeros(n, f32)}
        # With per-ray view sets the geometry block spans several calls (same numpy memory as one
        # all-view call); calls then hold at most chunk_rays rays.
        block = chunk_rays * max(1, V // k) if by_ray else chunk_rays
        starts = range(0, n, block)
        stats = {"rays_s": 0.0, "renderer_s": 0.0, "calls": 0, "rays": 0, "points": 0,
                 "point_views": 0, "ray_pairs": 0}

        def add(part: dict) -> None:
            for key, value in part.items():
                stats[key] += value

        if self.workers == 1 or len(starts) == 1:
            for start in starts:
                add(self._render_block(ctx, start, block))
                if progress is not None:
                    progress(min(n, start + block), n)
        else:
            from concurrent.futures import ThreadPoolExecutor
            with ThreadPoolExecutor(self.workers, thread_name_prefix="iris-render") as pool:
                for start, part in zip(starts, pool.map(
                        lambda st: self._render_block(ctx, st, block), starts)):
                    add(part)
                    if progress is not None:
                        progress(min(n, start + block), n)
        for key in ("calls", "rays", "points", "point_views", "ray_pairs"):
            work[key] = work.get(key, 0) + stats[key]
        # Summed over blocks (thread time when workers > 1).
        timings["rays"] = timings.get("rays", 0.0) + stats["rays_s"]
        timings["renderer"] = timings.get("renderer", 0.0) + stats["renderer_s"]
        return ctx["rgb"], ctx["depth"]

    def _render_block(self, ctx: dict, start: int, block: int) -> dict:
        """Render pixels ``start .. start + block`` into ``ctx["rgb"]``, ``ctx["depth"]``."""
        f32 = np.float32
        t0 = time.perf_counter()
        scene, S, k, by_ray = ctx["scene"], ctx["S"], ctx["k"], ctx["by_ray"]
        origin, z_bins, centres = ctx["origin"], ctx["z_bins"], ctx["centres"]
        rgb, depth, width = ctx["rgb"], ctx["depth"], ctx["width"]
        view_images = ctx["view_images"]
        Hm, Wm = scene.image_size
        V = scene.num_views
        cull = self.cull
        stats = {"rays_s": 0.0, "renderer_s": 0.0, "calls": 0, "rays": 0, "points": 0,
                 "point_views": 0, "ray_pairs": 0}
        pix = np.arange(start, min(ctx["n"], start + block))
        uv = np.stack([pix % width, pix // width], axis=-1).astype(f32) + f32(0.5)
        _, directions = G.rays_from_pixels(uv, ctx["K_out"], ctx["pose"])    # [R, 3]
        points = origin + z_bins[None, :, None] * directions[:, None, :]      # [R, S, 3]
        uv_ref, _, valid = G.project_points(points, ctx["K_ref"], ctx["cam_from_world"],
                                            Hm, Wm)                           # [V, R, S]
        vsel = np.arange(V)
        if cull:
            rgb[pix] = ctx["empty"]
            vsel = np.flatnonzero(valid.reshape(V, -1).any(axis=1))          # views seeing the block
            uv_ref, valid = uv_ref[vsel], valid[vsel]
        sets = None
        if k is not None and len(vsel) > k:
            dot = Q.cue_dot(points, origin, centres[vsel])                      # [V'', R, S]
            if by_ray:
                sets = Q.ray_view_sets(valid, dot, k)                           # [V'', R]
                valid = valid & sets[:, :, None]
            else:
                valid = valid & Q.top_k_mask(valid, dot, k)
        # (rays, views) of each renderer call, as indices into the block's rays and vsel.
        if cull:
            live = np.flatnonzero(valid.any(axis=(0, 2)))
            if live.size == 0:                   # nothing of the scene on these rays
                calls = []
            elif sets is not None:
                calls = [(live[r], v) for r, v in Q.group_rays(sets[:, live], k, ctx["chunk_rays"])]
            else:
                seen = np.flatnonzero(valid[:, live].reshape(len(vsel), -1).any(axis=1))
                calls = [(live, seen)] if live.size else []
        else:
            calls = [(np.arange(len(pix)), np.arange(len(vsel)))]
        stats["rays_s"] += time.perf_counter() - t0
        maps_key, maps = None, None
        for rays, views in calls:
            t0 = time.perf_counter()
            val = valid[np.ix_(views, rays)]                                   # [v, r, S]
            uvc = uv_ref[np.ix_(views, rays)]
            pts = points[rays]
            z = np.broadcast_to(z_bins, (len(rays), S))
            if cull:
                sample_valid = val.any(axis=0)                                  # [r, S]
                s_max = int(sample_valid.sum(axis=1).max())
                if s_max < S:
                    # Valid samples first, in depth order (stable), cut to the longest ray.
                    order = np.argsort(~sample_valid, axis=1, kind="stable")[:, :s_max]
                    pts = np.take_along_axis(pts, order[..., None], axis=1)
                    uvc = np.take_along_axis(uvc, order[None, ..., None], axis=2)
                    val = np.take_along_axis(val, order[None], axis=2)
                    z = z_bins[order]
            gviews = vsel[views]
            if maps is None or gviews.tobytes() != maps_key:   # neighbouring calls share views
                maps_key = gviews.tobytes()
                maps = scene.field_maps if len(gviews) == V and cull is False \
                    else np.ascontiguousarray(scene.field_maps[gviews])
            cue = G.geometric_cue(pts, origin, centres[gviews])                # [r, s, v, 4]
            grid = G.pixels_to_grid(uvc, Hm, Wm)
            feed = {"field_maps": maps, "grid": grid,
                    "cues": np.ascontiguousarray(np.moveaxis(cue, 2, 0)),      # view-major
                    "mask": np.ascontiguousarray(val), "positions": pts,
                    "directions": directions[rays]}
            if view_images is not None:      # explicit colour: the photos at the same grid
                feed["colours"] = G.sample_bilinear_views(view_images[gviews], grid)
            t1 = time.perf_counter()
            out_rgb, weights = ctx["session"].run(["rgb", "weights"], feed)
            t2 = time.perf_counter()
            rows = pix[rays]
            rgb[rows] = out_rgb
            depth[rows] = (weights * z).sum(axis=1)
            t3 = time.perf_counter()
            stats["rays_s"] += (t1 - t0) + (t3 - t2)
            stats["renderer_s"] += t2 - t1
            v_, r_, s_ = val.shape
            stats["calls"] += 1
            stats["rays"] += r_
            stats["points"] += r_ * s_
            stats["point_views"] += r_ * s_ * v_
            stats["ray_pairs"] += r_ * s_ * s_
        return stats
