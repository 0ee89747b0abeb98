"""One ``iris-render`` job as a library call: a model, photos and an output folder in, the render
files out (``render_scene``), with typed options (``RenderOptions``) instead of command-line text.

``iris-render`` (``iris_runtime.cli``) parses its arguments into a ``RenderOptions`` and calls
``render_scene``; ``iris-batch`` calls it for each scene folder on a runtime loaded once per
worker. Both therefore write the same files with the same code: the list of files, their formats
and the order of the checks are in ``iris_runtime.cli``'s docstring. Error messages name the
command-line options (``--view``, ``--pose``, ``--locate``, ``--chunk-rays``) the fields come from.

Also here, for every caller that writes renders (the HTTP service too): ``depth_uint16`` (the
16-bit depth PNG's values) and ``open_video`` (the ``orbit.mp4`` writer).
"""
from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

import numpy as np

from .quality import QUALITY_PRESETS

if TYPE_CHECKING:
    from .runtime import IrisRuntime

__all__ = ["RenderOptions", "render_scene", "depth_uint16", "open_video", "VIDEO_NAME"]

VIDEO_NAME = "orbit.mp4"


@dataclass(frozen=True)
class RenderOptions:
    """What one ``iris-render`` job renders and how (the options after MODEL_DIR IMAGES -o OUT;
    the defaults are ``iris-render``'s). Plain values, so it pickles (Ray sends it to actors).

    What to render (nothing of these: every input view):

    - ``views``: input view indices (each >= 0) whose predicted pose is rendered (``--view``);
    - ``pose_files``: paths of JSON files, each a 4x4 ``world_from_cam`` or a list of them
      (``--pose``);
    - ``orbit``: N >= 1 frames on a closed path around the input cameras, plus ``orbit.mp4``
      (``--orbit``), or None;
    - ``locate``: paths of photos to pose in the inputs' frame and render (``--locate``).

    How: ``cameras`` a name of ``manifest.CAMERAS`` or None (the model's default); ``size``
    (height, width) of the output or None (the model's); ``fps`` (>= 1) of ``orbit.mp4``;
    ``depth`` False skips the depth PNG/NPY files; ``chunk_rays`` rays per renderer call or None;
    ``quality`` a name of ``quality.QUALITY_PRESETS`` or None (the model's); ``quiet`` True prints
    nothing and shows no progress bar. ``threads``, ``precision`` and ``providers`` load the
    runtime when ``render_scene`` is given a model directory (ignored with a loaded runtime).
    """
    views: tuple[int, ...] = ()
    pose_files: tuple[str, ...] = ()
    orbit: int | None = None
    locate: tuple[str, ...] = ()
    cameras: str | None = None
    size: tuple[int, int] | None = None
    fps: int = 24
    depth: bool = True
    threads: int | None = None
    chunk_rays: int | None = None
    providers: tuple[str, ...] | None = None
    precision: str = "float32"
    quality: str | None = None
    quiet: bool = False



def _read_poses(path: str) -> list[np.ndarray]:
    """The poses of a ``--pose`` JSON file, each checked (and, if rigid only to a few printed
    decimals, snapped) by ``validation.snap_world_from_cam``, the one reader-side rigidity rule."""
    from .errors import InputError
    from .validation import snap_world_from_cam
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(f"--pose {path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"--pose {path}: cannot read: {exc}") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"--pose {path}: not valid JSON ({exc})") from None
    try:
        arr = np.asarray(doc, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"--pose {path}: expected a 4x4 matrix or a list of 4x4 matrices "
                         f"(nested lists of numbers)") from None
    if arr.shape == (4, 4):
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[1:] != (4, 4) or len(arr) == 0:
        raise InputError(f"--pose {path}: expected a 4x4 matrix or a non-empty list of 4x4 "
                         f"matrices, got shape {arr.shape}")
    return [snap_world_from_cam(T, f"--pose {path}[{k}]") for k, T in enumerate(arr)]


class _Progress:
    """A tqdm bar over rays when tqdm is installed and stderr is a terminal; silent otherwise."""

    def __init__(self, total: int, enabled: bool):
        self.bar = None
        self.base = 0
        if enabled:
            try:
                from tqdm import tqdm
            except ImportError:            # tqdm is optional: not a runtime dependency
                tqdm = None
            if tqdm is not None:
                self.bar = tqdm(total=total, unit="ray", unit_scale=True, desc="rendering",
                                leave=False, disable=None, dynamic_ncols=True)

    def frame(self, base: int):
        self.base = base

    def __call__(self, done: int, total: int):
        if self.bar is not None:
            self.bar.n = self.base + done
            self.bar.refresh()

    def close(self):
        if self.bar is not None:
            self.bar.close()


def _write_png(path: Path, rgb: np.ndarray) -> None:
    from PIL import Image
    Image.fromarray(rgb).save(path)


def depth_uint16(depth: np.ndarray, far: float) -> np.ndarray:
    """Soft depth [H, W] as the 16-bit values of NAME_depth.png: round(depth / far * 65535)."""
    return np.rint(np.clip(depth / far, 0.0, 1.0) * 65535.0).astype(np.uint16)


def _write_depth(path_png: Path, path_npy: Path, depth: np.ndarray, far: float) -> None:
    import cv2
    scaled = depth_uint16(depth, far)
    if not cv2.imwrite(str(path_png), scaled):
        raise OSError(f"{path_png}: cv2.imwrite failed")
    np.save(path_npy, depth.astype(np.float32))


@dataclass(frozen=True)
class _Request:
    """An ``iris-render`` invocation, checked before anything is written."""
    rt: "IrisRuntime"
    size: tuple[int, int]                     # output (height, width)
    inputs: list[np.ndarray]                  # the input photos at the model's resolution
    originals: list[np.ndarray]               # ... at their own (the camera solve's)
    poses: list[np.ndarray]                   # from the --pose files
    photos: list[np.ndarray]                  # the --locate photos


def render_scene(model: str | os.PathLike | IrisRuntime, images: Sequence[str],
                 out: str | os.PathLike, options: RenderOptions = RenderOptions()) -> None:
    """Render the scene of ``images`` (paths of the input photos, any size, >= 1) with ``model``
    into the folder ``out`` (created if needed; files of the same name are replaced): what
    ``iris-render MODEL_DIR IMAGES... -o OUT`` with ``options`` writes and prints.

    ``model``: the model directory written by iris-export (a runtime is loaded with
    ``options.threads``, ``.precision``, ``.providers``), or an ``IrisRuntime`` already loaded
    (``iris-batch`` renders many scenes with one model load). Everything (model, limits, images,
    view indices, pose files) is checked before a file is written; a failure raises
    ``errors.IrisError`` (bad input or model files) or ``OSError``."""
    opts = options
    say = (lambda *a: None) if opts.quiet else (lambda *a: print("iris-render:", *a, flush=True))
    t_all = time.perf_counter()
    t0 = time.perf_counter()
    req = _check_request(model, list(images), opts)      # 1. everything, before writing anything
    scene, located = _encode(req, opts, say, time.perf_counter() - t0)       # 2. encode once
    jobs, orbit = _jobs(req, opts, scene, located)
    out = _write_cameras(Path(out), req, scene, orbit, located)             # 3. the inputs' cameras
    rendered = _render_jobs(req, opts, scene, jobs, out, say)              # 4. render
    _summary(req, opts, jobs, out, orbit, located, rendered, say)
    say(f"total {time.perf_counter() - t_all:.2f} s")


def _check_request(model, images: list[str], opts: RenderOptions) -> _Request:
    """The model, the request limits (``iris_runtime.limits``, checked by the same functions
    ``IrisRuntime`` uses), the images, view indices and pose files: every error before a file is
    written."""
    from . import limits as L
    from .errors import InputError
    from .images import fit_to_model, load_image
    from .runtime import IrisRuntime

    rt = model
    if isinstance(model, (str, os.PathLike)):
        # providers as a list, as iris-render always passed them (IrisRuntime's message shows it)
        rt = IrisRuntime(model, threads=opts.threads, precision=opts.precision,
                         providers=None if opts.providers is None else list(opts.providers))
    H, W = rt.image_size
    size = rt.check_output_size(*opts.size) if opts.size else (H, W)
    if opts.chunk_rays is not None:
        samples = QUALITY_PRESETS[opts.quality or rt.default_quality].samples or rt.samples
        L.check_chunk_rays(opts.chunk_rays, size[0] * size[1], samples, len(images),
                           name="--chunk-rays")
    originals = [load_image(p, p) for p in images]          # own resolution: the solve's
    inputs = [fit_to_model(photo, H, W)[0] for photo in originals]
    V = len(inputs)
    bad = [i for i in opts.views if i >= V]
    if bad:
        raise InputError(f"--view {bad[0]}: out of range, {V} input image(s) give views 0..{V - 1}")
    poses = [T for f in opts.pose_files for T in _read_poses(f)]
    photos = [load_image(p, f"--locate {p}") for p in opts.locate]
    return _Request(rt, size, inputs, originals, poses, photos)


def _encode(req: _Request, opts: RenderOptions, say, t_load: float):
    """The Scene of the inputs (``--cameras``) and the --locate photos' poses in its frame."""
    rt = req.rt
    t0 = time.perf_counter()
    scene = rt.encode(req.originals, cameras=opts.cameras)   # too many images: refused here
    H, W = rt.image_size
    say(f"encoded {len(req.inputs)} view(s) at {H}x{W} in {time.perf_counter() - t0:.2f} s "
        f"(model check + image loading {t_load:.2f} s); focal fx/W={scene.focal[0]:.4f} "
        f"fy/H={scene.focal[1]:.4f}")
    if (opts.cameras or rt.default_cameras) != "model":
        unposed = [i for i, st in enumerate(scene.camera_status or ()) if st == "unposed"]
        say(f"cameras of the inputs: {scene.camera_source}"
            + {"solve": f" (every view solved from the photos at {_hw_text(scene.camera_size)})",
               "refined": f" (every view's camera refined by the photos at "
                          f"{_hw_text(scene.camera_size)})",
               "mixed": f" (solved at {_hw_text(scene.camera_size)}; views {unposed} could not be "
                        f"posed and keep the model's camera)",
               "model": " (the solve could not pose view 0: the model's cameras)"}
            [scene.camera_source]
            + ("" if scene.encoder_focal is None else
               f"; the model's focal was fx/W={scene.encoder_focal[0]:.4f}"))
    if not req.photos:
        return scene, None
    t0 = time.perf_counter()
    located = rt.locate(scene, req.photos)                       # [Q, 4, 4], scene unchanged
    say(f"located {len(req.photos)} photo(s) in the inputs' frame in "
        f"{time.perf_counter() - t0:.2f} s")
    for path, T in zip(opts.locate, located):
        say(f"located {path}: world_from_cam {json.dumps(np.round(T, 6).tolist())}")
    return scene, located


def _jobs(req: _Request, opts: RenderOptions, scene, located):
    """``[(name, pose or view index), ...]`` to render, and the orbit's poses (or None)."""
    from .orbit import orbit_poses

    jobs: list[tuple[str, np.ndarray | int]] = []
    jobs += [(f"view_{i:03d}", i) for i in opts.views]
    jobs += [(f"pose_{k:03d}", T) for k, T in enumerate(req.poses)]
    if located is not None:
        jobs += [(f"located_{k:03d}", T) for k, T in enumerate(located)]
    orbit = None
    if opts.orbit:
        near, far = req.rt.unit_range             # where the cameras' unit puts the scene
        orbit = orbit_poses(scene.world_from_cam, opts.orbit, near=near, far=far)
        jobs += [(f"orbit_{k:04d}", T) for k, T in enumerate(orbit)]
    if not jobs:
        jobs = [(f"view_{i:03d}", i) for i in range(len(req.inputs))]
    return jobs, orbit


def _write_cameras(out: Path, req: _Request, scene, orbit, located) -> Path:
    """The inputs as the model saw them, their cameras (nerfstudio, COLMAP, a picture) and the
    orbit's and located poses, in ``out`` (created) -> ``out``."""
    from . import camera_io
    from .camera_plot import draw_cameras

    H, W = req.rt.image_size
    V = len(req.inputs)
    out.mkdir(parents=True, exist_ok=True)
    (out / "inputs").mkdir(exist_ok=True)
    names = [f"{i:03d}.png" for i in range(V)]
    for name, rgb in zip(names, req.inputs, strict=True):
        _write_png(out / "inputs" / name, rgb)
    cams = scene.world_from_cam                 # rigid (checked by Scene): written as rendered
    camera_io.write_transforms_json(out / "transforms.json", cams, scene.K, (H, W),
                                    [f"inputs/{n}" for n in names])
    camera_io.write_colmap_text(out / "colmap", cams, scene.K, (H, W), names)
    (out / "cameras.json").write_text(json.dumps({
        "source": scene.camera_source,
        "solved_at": None if scene.camera_size is None else list(scene.camera_size),
        "status": None if scene.camera_status is None else list(scene.camera_status),
        "focal": scene.focal.tolist(),
        "encoder_focal": (scene.focal if scene.encoder_focal is None
                          else scene.encoder_focal).tolist(),
        "encoder_world_from_cam": (cams if scene.encoder_world_from_cam is None
                                   else scene.encoder_world_from_cam).tolist()},
        indent=1) + "\n")
    what = "predicted" if scene.camera_source == "model" else scene.camera_source
    _write_png(out / "cameras.png", draw_cameras(cams, scene.K, size=(480, 640),
                                                 title=f"{what} cameras of the {V} input(s)"))
    if orbit is not None:
        (out / "orbit_poses.json").write_text(json.dumps(orbit.tolist()) + "\n")
    if located is not None:
        (out / "located_poses.json").write_text(json.dumps(located.tolist()) + "\n")
    return out


def _render_jobs(req: _Request, opts: RenderOptions, scene, jobs, out: Path, say) -> dict:
    """Render and write every job (PNG, depth, the orbit's video frames) -> seconds per stage
    (``rays``, ``renderer``, ``write``, ``total``) and whether the video was written."""
    height, width = req.size
    progress = _Progress(total=len(jobs) * height * width, enabled=not opts.quiet)
    totals = {"rays": 0.0, "renderer": 0.0, "write": 0.0}
    t_render = time.perf_counter()
    writer = None
    try:
        for k, (name, pose) in enumerate(jobs):
            progress.frame(k * height * width)
            res = req.rt.render(scene, pose, height=height, width=width, depth=True,
                                chunk_rays=opts.chunk_rays, progress=progress,
                                quality=opts.quality)
            totals["rays"] += res.timings["rays"]
            totals["renderer"] += res.timings["renderer"]
            if res.coverage == 0:
                print(f"iris-render: warning: {name}: the camera sees none of the scene (no ray "
                      f"meets a reference photo's view); its frame is the empty-ray colour",
                      file=sys.stderr)
            t0 = time.perf_counter()
            _write_png(out / f"{name}.png", res.image)
            if opts.depth:
                _write_depth(out / f"{name}_depth.png", out / f"{name}_depth.npy", res.depth,
                             req.rt.far)
            if name.startswith("orbit_"):
                if writer is None:
                    writer = open_video(out / VIDEO_NAME, opts.fps, req.size)
                if writer is not None:
                    writer.write(res.image[..., ::-1].copy())         # OpenCV wants BGR
            totals["write"] += time.perf_counter() - t0
            if progress.bar is None or progress.bar.disable:
                # No live bar (stderr is not a terminal: CI logs, | tee): a line per frame.
                say(f"  frame {k + 1}/{len(jobs)} {name}: {time.perf_counter() - t_render:.1f} s")
    finally:
        progress.close()
        if writer is not None:
            writer.release()
    return {**totals, "total": time.perf_counter() - t_render, "video": writer is not None}


def _summary(req: _Request, opts: RenderOptions, jobs, out: Path, orbit, located, rendered: dict,
             say) -> None:
    """What was written where, and how long it took."""
    say(f"rendered {len(jobs)} view(s) at {req.size[0]}x{req.size[1]} in "
        f"{rendered['total']:.2f} s (rays {rendered['rays']:.2f} s, renderer "
        f"{rendered['renderer']:.2f} s, writing {rendered['write']:.2f} s)")
    first, last = jobs[0][0], jobs[-1][0]
    say(f"images: {out}/{first}.png" + (f" ... {last}.png" if len(jobs) > 1 else "")
        + ("" if not opts.depth else f", depth in NAME_depth.png (16-bit, depth / far * 65535, "
                                    f"far = {req.rt.far:g}) and NAME_depth.npy (float32)"))
    if rendered["video"]:
        say(f"video: {out / VIDEO_NAME} ({len(orbit)} frames at {opts.fps} fps)")
    elif orbit is not None:
        say(f"video: not written (OpenCV has no mp4v encoder here); frames are in {out}")
    say(f"cameras of the inputs: {out / 'transforms.json'}, {out / 'colmap'} "
        f"(images in {out / 'inputs'}; picture {out / 'cameras.png'})")
    if located is not None:
        say(f"located poses: {out / 'located_poses.json'} (one 4x4 world_from_cam per --locate "
            f"photo, usable with --pose)")


def _hw_text(hw) -> str:
    return "?" if hw is None else f"{hw[1]}x{hw[0]}"


def open_video(path: Path, fps: int, size: tuple[int, int]):
    """An OpenCV ``mp4v`` writer of ``size`` (H, W) frames at ``path`` (frames in BGR), or None
    when this OpenCV has no such encoder."""
    import cv2
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(fps),
                             (size[1], size[0]))
    if not writer.isOpened():
        writer.release()
        return None
    return writer
