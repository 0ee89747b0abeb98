"""IrisRuntime: run an exported IRIS model (encoder.onnx + renderer.onnx + iris.json) with
ONNX Runtime on the CPU, torch-free.

    rt = IrisRuntime("out/")                      # checks the manifest and the graphs' sha256
    image = rt.render(images, pose)               # one shot: encode, then render one pose
    scene = rt.encode(images)                     # run the encoder once (the expensive half) ...
    result = rt.render(scene, 2, depth=True)      # ... and render many poses from it

Cameras follow DESIGN.md: OpenCV axes, ``world_from_cam`` 4x4, canonical frame = view 0's camera,
intrinsics in pixels with pixel centres at (j + 0.5, i + 0.5).

What happens per chunk of rays (numpy, ``iris_runtime.geometry``): rays through the pixel
centres, deterministic bin-centre depths in [near, far], sample points, their projection into
every reference view (``cam_from_world = invert_pose(world_from_cam)``), the normalised grid
coordinates, the validity mask and the geometric cue (target centre = the ray origin). The
renderer graph samples the field maps itself (GridSample) and returns rgb and per-sample weights;
depth = sum(weights * z).

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
from .errors import InputError, ManifestError, ModelFileError
from .images import fit_to_model, load_image
from .manifest import MANIFEST_NAME, Manifest, read_graph_bytes, read_manifest

__all__ = ["IrisRuntime", "Scene", "RenderResult", "check_pose", "RENDER_BUDGET", "MAX_CHUNK_RAYS",
           "PRECISIONS"]

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
    """
    field_maps: np.ndarray
    world_from_cam: np.ndarray
    focal: np.ndarray
    K: np.ndarray
    image_size: tuple[int, int]
    model_id: str = ""

    def __post_init__(self):
        maps = _readonly(self.field_maps, np.float32)
        poses = _readonly(self.world_from_cam, np.float64)
        focal = _readonly(self.focal, np.float64)
        K = _readonly(self.K, np.float64)
        if maps.ndim != 4 or maps.shape[0] == 0:
            raise InputError(f"field_maps: expected [V, C', h, w] with V >= 1, got {maps.shape}")
        V = maps.shape[0]
        if poses.shape != (V, 4, 4):
            raise InputError(f"world_from_cam: expected [{V}, 4, 4], got {poses.shape}")
        if focal.shape != (2,) or K.shape != (3, 3):
            raise InputError(f"focal, K: expected [2] and [3, 3], got {focal.shape} and {K.shape}")
        size = tuple(int(s) for s in self.image_size)
        if len(size) != 2 or min(size) <= 0:
            raise InputError(f"image_size: expected (H, W) positive, got {self.image_size!r}")
        for name, value in (("field_maps", maps), ("world_from_cam", poses), ("focal", focal),
                            ("image_size", size), ("K", K)):
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
        idx = np.asarray(list(indices) if not isinstance(indices, np.ndarray) else indices)
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
                     self.image_size, self.model_id)

    def __repr__(self) -> str:
        return (f"Scene(views={self.num_views}, field_maps={tuple(self.field_maps.shape)}, "
                f"image_size={self.image_size}, focal={np.round(self.focal, 4).tolist()})")


@dataclass(frozen=True, eq=False)
class RenderResult:
    """One rendered view.

    image:       uint8   [H, W, 3] RGB
    image_float: float32 [H, W, 3] RGB in [0, 1] (what the renderer returned)
    depth:       float32 [H, W]    soft camera depth sum_m w_m z_m in model units, within
                                   [near, far]; 0 where no sample sees any reference view
    timings:     seconds per stage (``load``/``encode`` when images were given, ``rays``: numpy
                 geometry, ``renderer``: ONNX Runtime, ``total``)
    """
    image: np.ndarray
    image_float: np.ndarray
    depth: np.ndarray
    timings: dict = field(default_factory=dict)


class IrisRuntime:
    """An exported IRIS model, run with ONNX Runtime (see the module docstring).

    ``threads``: intra-op threads of each ONNX Runtime session (None: ORT's default, one per
    physical core). ``precision``: "float32" (default) or "int8" (the quantised renderer, when
    the model was exported with ``--quantize int8``). ``cull``: skip samples, views and rays
    that see no reference view (exact, see the module docstring; False only to check that).
    Construction reads and checks ``iris.json`` and the sha256 of both graphs; sessions are
    created on first use (and the graph bytes hashed again, so the graph that runs is the one
    that was checked). Safe to share between threads.
    """

    def __init__(self, model_dir: str | os.PathLike, threads: int | None = None, *,
                 precision: str = "float32", cull: bool = True):
        if precision not in PRECISIONS:
            raise InputError(f"precision: expected one of {list(PRECISIONS)}, got {precision!r}")
        if threads is not None and (isinstance(threads, bool) or threads < 1
                                    or not isinstance(threads, (int, np.integer))):
            raise InputError(f"threads: expected a positive integer or None, got {threads!r}")
        self.manifest: Manifest = read_manifest(model_dir)
        self.model_dir: Path = self.manifest.model_dir
        self.threads = None if threads is None else int(threads)
        self.precision = precision
        self._renderer = PRECISIONS[precision]
        if self._renderer not in self.manifest.graphs:
            raise ManifestError(f"{self.model_dir / MANIFEST_NAME}: no {precision} renderer "
                                f"(graphs.{self._renderer}); export with --quantize int8 for it")
        self.cull = bool(cull)
        self._sessions: dict[str, ort.InferenceSession] = {}
        self._lock = threading.Lock()
        self._empty_rgb: np.ndarray | None = None

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

    def default_chunk_rays(self, num_views: int) -> int:
        """Rays per renderer call: R * S * V near ``RENDER_BUDGET``, at most ``MAX_CHUNK_RAYS``."""
        return min(MAX_CHUNK_RAYS, max(1, RENDER_BUDGET // (self.samples * max(1, num_views))))

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
    def _load_images(self, images) -> np.ndarray:
        """Images -> float32 [V, 3, H, W] in [0, 1] at the model's resolution."""
        if isinstance(images, (str, os.PathLike, bytes)) or (
                isinstance(images, np.ndarray) and images.ndim != 4) or hasattr(images, "getpixel"):
            raise InputError(f"images: expected a sequence of images (paths, PIL images or "
                             f"HxWx3 uint8 arrays), got a single {type(images).__name__}; "
                             f"wrap it in a list")
        try:
            items = list(images)
        except TypeError:
            raise InputError(f"images: expected a sequence of images or a Scene, got "
                             f"{type(images).__name__}") from None
        if not items:
            raise InputError("images: expected at least one image, got an empty sequence")
        H, W = self.image_size
        batch = np.empty((len(items), 3, H, W), dtype=np.float32)
        for i, item in enumerate(items):
            rgb, _ = fit_to_model(load_image(item, f"images[{i}]"), H, W)
            batch[i] = rgb.transpose(2, 0, 1)
        batch *= np.float32(1.0 / 255.0)
        return batch

    def encode(self, images) -> Scene:
        """Run the encoder on ``images`` (a sequence of HxWx3 uint8 RGB arrays, PIL images or
        file paths, any size: centre-cropped to the model's aspect ratio and resized, see
        ``iris_runtime.images.fit_to_model``) -> an immutable ``Scene``."""
        return self._encode(images, {})

    def _encode(self, images, timings: dict) -> Scene:
        t0 = time.perf_counter()
        batch = self._load_images(images)
        t1 = time.perf_counter()
        maps, world_from_cam, focal = self._session("encoder").run(
            ["field_maps", "world_from_cam", "focal"], {"images": batch})
        t2 = time.perf_counter()
        timings["load"] = timings.get("load", 0.0) + (t1 - t0)
        timings["encode"] = timings.get("encode", 0.0) + (t2 - t1)
        V = batch.shape[0]
        channels = self.manifest.field_channels
        if (maps.ndim != 4 or maps.shape[0] != V or (channels and maps.shape[1] != channels)
                or world_from_cam.shape != (V, 4, 4) or focal.shape != (2,)):
            raise ModelFileError(f"{self.manifest.graphs['encoder'].path}: encoder returned "
                                 f"field_maps {maps.shape}, world_from_cam {world_from_cam.shape}, "
                                 f"focal {focal.shape} for {V} views; expected [V, C', h, w], "
                                 f"[V, 4, 4], [2]")
        H, W = self.image_size
        focal64 = focal.astype(np.float64)
        return Scene(maps, world_from_cam.astype(np.float64), focal64,
                     G.intrinsics_from_focal(focal64, H, W), (H, W),
                     self.manifest.graphs["encoder"].sha256)

    # -- rendering --------------------------------------------------------------------------
    def render(self, images_or_scene, pose, *, height: int | None = None, width: int | None = None,
               intrinsics=None, depth: bool = False, chunk_rays: int | None = None,
               progress: Callable[[int, int], None] | None = None):
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

        Returns uint8 [H, W, 3] RGB, or a ``RenderResult`` with ``depth=True``.
        """
        t_start = time.perf_counter()
        timings: dict[str, float] = {}
        if isinstance(images_or_scene, Scene):
            scene = images_or_scene
            self._check_scene(scene)
        else:
            scene = self._encode(images_or_scene, timings)
        world_from_cam = self._check_pose(pose, scene)
        height, width = self._check_size(height, width)
        K = self._check_intrinsics(intrinsics, scene, height, width)
        if chunk_rays is None:
            chunk_rays = self.default_chunk_rays(scene.num_views)
        elif isinstance(chunk_rays, bool) or not isinstance(chunk_rays, (int, np.integer)) \
                or chunk_rays < 1:
            raise InputError(f"chunk_rays: expected a positive integer, got {chunk_rays!r}")
        rgb, z = self._render_rays(scene, world_from_cam, K, height, width, int(chunk_rays),
                                   timings, progress)
        image_float = rgb.reshape(height, width, 3)
        image = np.rint(np.clip(image_float, 0.0, 1.0) * 255.0).astype(np.uint8)
        timings["total"] = time.perf_counter() - t_start
        if not depth:
            return image
        return RenderResult(image, image_float, z.reshape(height, width), timings)

    # .. argument checks ......................................................................
    def _check_scene(self, scene: Scene) -> None:
        enc = self.manifest.graphs["encoder"].sha256
        if scene.model_id and scene.model_id != enc:
            raise InputError("images_or_scene: this Scene was encoded by another model "
                             f"(encoder sha256 {scene.model_id[:12]}..., this model {enc[:12]}...)")
        channels = self.manifest.field_channels
        if tuple(scene.image_size) != tuple(self.image_size) or (
                channels and scene.field_maps.shape[1] != channels):
            raise InputError(f"images_or_scene: Scene of image size {scene.image_size} with "
                             f"{scene.field_maps.shape[1]} channels; this model has "
                             f"{self.image_size} and {channels}")

    @staticmethod
    def _check_pose(pose, scene: Scene) -> np.ndarray:
        if isinstance(pose, (int, np.integer)) and not isinstance(pose, (bool, np.bool_)):
            V = scene.num_views
            if not 0 <= pose < V:
                raise InputError(f"pose: view index {int(pose)} out of range 0..{V - 1} "
                                 f"(the scene has {V} views)")
            return scene.world_from_cam[int(pose)].copy()
        return check_pose(pose)

    def _check_size(self, height, width) -> tuple[int, int]:
        Hm, Wm = self.image_size
        for name, v in (("height", height), ("width", width)):
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer))
                                  or v < 1):
                raise InputError(f"{name}: expected a positive integer or None, got {v!r}")
        if height is None and width is None:
            return Hm, Wm
        if height is None:
            return max(1, round(width * Hm / Wm)), int(width)
        if width is None:
            return int(height), max(1, round(height * Wm / Hm))
        return int(height), int(width)

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
    def _empty_ray_rgb(self, scene: Scene) -> np.ndarray:
        """The renderer's colour for a ray with no valid sample (a constant of the model: every
        input is masked, so nothing of the scene reaches it). Asked of the graph once."""
        rgb = self._empty_rgb
        if rgb is None:
            _, C, h, w = scene.field_maps.shape
            feed = {"field_maps": np.zeros((1, C, h, w), np.float32),
                    "grid": np.zeros((1, 1, 1, 2), np.float32),
                    "cues": np.zeros((1, 1, 1, 4), np.float32),
                    "mask": np.zeros((1, 1, 1), bool),
                    "positions": np.zeros((1, 1, 3), np.float32),
                    "directions": np.array([[0, 0, 1]], np.float32)}
            rgb = self._session(self._renderer).run(["rgb"], feed)[0][0]
            rgb.setflags(write=False)
            self._empty_rgb = rgb              # idempotent: a race computes the same value twice
        return rgb

    def _render_rays(self, scene: Scene, world_from_cam: np.ndarray, K: np.ndarray,
                     height: int, width: int, chunk_rays: int, timings: dict,
                     progress: Callable[[int, int], None] | None):
        """-> rgb float32 [H*W, 3], depth float32 [H*W] (rows of pixels, row-major)."""
        f32 = np.float32
        Hm, Wm = scene.image_size
        S = self.samples
        n = height * width
        session = self._session(self._renderer)
        K_ref = scene.K.astype(f32)
        cam_from_world = G.invert_pose(scene.world_from_cam).astype(f32)    # [V, 4, 4]
        centres = scene.world_from_cam[:, :3, 3].astype(f32)                 # [V, 3]
        pose = world_from_cam.astype(f32)
        K_out = K.astype(f32)
        origin = pose[:3, 3]
        z_bins = G.sample_depths(self.near, self.far, S, 1, dtype=f32)[0]    # [S] bin centres
        all_views = np.arange(scene.num_views)
        cull = self.cull
        maps_key, maps = all_views.tobytes(), scene.field_maps    # maps of the last view subset

        rgb = np.empty((n, 3), f32)
        depth = np.zeros(n, f32)
        t_rays = t_ort = 0.0
        for start in range(0, n, chunk_rays):
            t0 = time.perf_counter()
            pix = np.arange(start, min(n, start + chunk_rays))
            uv = np.stack([pix % width, pix // width], axis=-1).astype(f32) + f32(0.5)
            _, directions = G.rays_from_pixels(uv, K_out, pose)              # [R, 3]
            points = origin + z_bins[None, :, None] * directions[:, None, :]  # [R, S, 3]
            uv_ref, _, valid = G.project_points(points, K_ref, cam_from_world, Hm, Wm)  # [V, R, S]
            rays, views, z = slice(None), all_views, np.broadcast_to(z_bins, (len(pix), S))
            if cull:
                sample_valid = valid.any(axis=0)                             # [R, S]
                n_valid = sample_valid.sum(axis=1)
                rgb[pix] = self._empty_ray_rgb(scene)
                rays = np.flatnonzero(n_valid)
                if rays.size == 0:                  # nothing of the scene on these rays
                    t_rays += time.perf_counter() - t0
                    if progress is not None:
                        progress(int(pix[-1]) + 1, n)
                    continue
                views = np.flatnonzero(valid[:, rays].reshape(len(valid), -1).any(axis=1))
                s_max = int(n_valid.max())
                points, directions = points[rays], directions[rays]
                uv_ref, valid = uv_ref[np.ix_(views, rays)], valid[np.ix_(views, rays)]
                if s_max < S:
                    # Valid samples first, in depth order (stable), cut to the longest ray.
                    order = np.argsort(~sample_valid[rays], axis=1, kind="stable")[:, :s_max]
                    points = np.take_along_axis(points, order[..., None], axis=1)
                    uv_ref = np.take_along_axis(uv_ref, order[None, ..., None], axis=2)
                    valid = np.take_along_axis(valid, order[None], axis=2)
                    z = z_bins[order]
                else:
                    z = z[rays]
            if views.tobytes() != maps_key:       # neighbouring chunks mostly see the same views
                maps_key, maps = views.tobytes(), np.ascontiguousarray(scene.field_maps[views])
            grid = G.pixels_to_grid(uv_ref, Hm, Wm)                          # [V', R', S', 2]
            cues = G.geometric_cue(points, origin, centres[views])            # [R', S', V', 4]
            feed = {"field_maps": maps, "grid": grid,
                    "cues": np.ascontiguousarray(np.moveaxis(cues, 2, 0)),    # view-major
                    "mask": np.ascontiguousarray(valid), "positions": points,
                    "directions": directions}
            t1 = time.perf_counter()
            out_rgb, weights = session.run(["rgb", "weights"], feed)
            t2 = time.perf_counter()
            rows = pix[rays]
            rgb[rows] = out_rgb
            depth[rows] = (weights * z).sum(axis=1)
            t3 = time.perf_counter()
            t_rays += (t1 - t0) + (t3 - t2)
            t_ort += t2 - t1
            if progress is not None:
                progress(int(pix[-1]) + 1, n)
        timings["rays"] = t_rays
        timings["renderer"] = t_ort
        return rgb, depth
