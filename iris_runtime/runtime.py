"""IrisRuntime: run an exported IRIS model (encoder.onnx + renderer.onnx + iris.json) with
ONNX Runtime on the CPU, torch-free.

    rt = IrisRuntime("out/")                      # checks the manifest and the graphs' sha256
    image = rt.render(images, pose)               # one shot: encode, then render one pose
    scene = rt.encode(images)                     # run the encoder once (the expensive half) ...
    result = rt.render(scene, 2, depth=True)      # ... and render many poses from it
    pose = rt.locate(scene, photo)                # a new photo's world_from_cam; scene unchanged

A thin facade: this module holds the runtime's bookkeeping (the model's facts, the providers, the
sessions, the BLAS threads, the checks both halves share); its two halves are mixins:
``iris_runtime.encoding`` (``encode`` and ``locate``: the encoder graph, references and queries)
and ``iris_runtime.rendering`` (``render``: its argument checks, then the ray march of
``iris_runtime.raymarch``). The value types are ``iris_runtime.scene`` (``Scene``,
``RenderResult``), the request limits and the memory model ``iris_runtime.limits``, the
speed/quality knobs ``iris_runtime.quality``. Every name of those that was importable from here
still is.

Cameras follow docs/ARCHITECTURE.md: OpenCV axes, ``world_from_cam`` 4x4, canonical frame = view 0's camera,
intrinsics in pixels with pixel centres at (j + 0.5, i + 0.5).
"""
from __future__ import annotations

import contextlib
import os
import threading
from pathlib import Path
from typing import Sequence

import numpy as np
import onnxruntime as ort

from . import limits as L
from .encoding import Encoding
from .errors import InputError, ManifestError, ModelFileError
from .limits import (MAX_CHUNK_RAYS, MAX_CHUNK_SAMPLES, MAX_ENCODER_TOKENS, MAX_LOCATE_CALLS,
                     MAX_OUTPUT_PIXELS, RENDER_BUDGET, render_memory_bound)
from .manifest import CAMERAS, MANIFEST_NAME, Manifest, read_graph_bytes, read_manifest
from .quality import PRECISIONS, QUALITY_PRESETS, RenderSettings
from .rendering import Rendering
from .scene import CAMERA_SOURCES, RenderResult, Scene, check_pose

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


class IrisRuntime(Encoding, Rendering):
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

    @property
    def unit_range(self) -> tuple[float, float]:
        """The ``depth_range`` the camera solve is given (``Manifest.unit_range``)."""
        return self.manifest.unit_range

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
    def default_cameras(self) -> str:
        """``encode``'s cameras when none are asked for: the manifest's "cameras" ("solve" for
        a model trained by ``iris-train --render-cameras solve``, "refined" where its camera
        head was then distilled from the solve, as the shipped model's, else "model")."""
        return self.manifest.cameras

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

    # -- numpy's threads ---------------------------------------------------------------------
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

    @contextlib.contextmanager
    def _opencv_threads(self):
        """A context in which OpenCV runs at most ``threads`` threads (the two-scale pass's
        ``cv2.remap``), for the reason of ``_blas_threads``; process-wide while it holds, the
        previous count restored after. With ``threads`` None, nothing changes."""
        if self.threads is None:
            yield
            return
        import cv2
        before = cv2.getNumThreads()
        cv2.setNumThreads(self.threads)
        try:
            yield
        finally:
            cv2.setNumThreads(before)

    # -- the checks both halves share --------------------------------------------------------
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
