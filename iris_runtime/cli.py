"""``iris-render MODEL_DIR IMAGES... -o OUT``: novel views from a few unposed photos, torch-free.

A thin command line over ``IrisRuntime``. It encodes the input images once, then renders:

- ``--view i`` (repeatable): the predicted pose of input view i (a reconstruction of it);
- ``--pose FILE``: JSON, one 4x4 ``world_from_cam`` or a list of them, in the canonical frame
  (view 0's camera, OpenCV axes: x right, y down, z forward); a pose rigid only to a few printed
  decimals (within ``validation.SNAP_ATOL = 1e-3``) is snapped to the nearest rigid transform,
  as the camera-file readers do (``validation.snap_world_from_cam``);
- ``--orbit N``: N frames on a smooth closed path through and around the predicted input cameras,
  looking at the scene centre (``iris_runtime.orbit``), plus ``orbit.mp4``;
- ``--locate PHOTO [PHOTO ...]`` (repeatable; put it after IMAGES): the pose of each photo in the
  scene's frame (``IrisRuntime.locate``: the photo is a query, the inputs stay the scene), printed,
  written to ``located_poses.json`` and rendered from the inputs as ``located_NNN``;
- nothing of the above: every input view (``--view`` 0..V-1).

``--cameras solve`` replaces the model's predicted cameras of the inputs by the camera solve of
the photos at their own resolution (``IrisRuntime.encode(images, cameras="solve")``,
``iris_runtime.cameras``: SIFT matches, two-view model selection, incremental mapping with bundle
adjustment of poses and focal, the scene's median depth put in the middle of the renderer's depth
range); every output (renders, ``--view`` poses, orbit, camera files) then uses those cameras and
that focal, and ``--locate`` poses the photo against them (PnP on the inputs' points). The
resolution the cameras were solved at and how each view was posed are printed and written to
``cameras.json``. ``--cameras refined`` refines the model's cameras on the photos into the
solve's terms instead (``iris_runtime.cameras.refine``; the solve where that fails). Without
``--cameras``, the manifest's default (the shipped model's: "refined").

Written to OUT (created if needed; files of the same name are replaced):

- ``<name>.png``: the rendered view (8-bit RGB), ``<name>`` = ``view_003``, ``pose_000``,
  ``orbit_0000``; ``<name>_depth.png``: soft depth as 16-bit PNG, **value = round(depth / far
  * 65535)** (far from the model's manifest, 1.0 unless trained otherwise; 0 where no sample
  sees a reference view); ``<name>_depth.npy``: the float32 depth in model units;
- ``orbit.mp4`` (``mp4v``) and ``orbit_poses.json`` (its poses, usable with ``--pose``);
- ``located_poses.json``: with ``--locate``, one 4x4 ``world_from_cam`` per photo in the order
  given (same convention as ``orbit_poses.json``, usable with ``--pose``);
- ``inputs/NNN.png``: the input images as the model saw them (centre-cropped, resized), with
  their predicted cameras in ``transforms.json`` (nerfstudio; OpenGL axes) and in
  ``colmap/{cameras,images,points3D}.txt`` (COLMAP text; image folder ``inputs/``). The
  intrinsics are in pixels of these model-resolution images;
- ``cameras.png``: a picture of those predicted cameras (frustums with their view indices, from
  above; ``iris_runtime.camera_plot.draw_cameras``), written whenever the inputs are encoded;
- ``cameras.json``: where the cameras come from (``source``: "model", "solve" or "mixed"),
  ``solved_at`` [H, W] the resolution of the photos they were solved at (null for the model's),
  ``status`` per view ("solved", "located", "unposed"; null for the model's), ``focal`` [fx/W,
  fy/H] at the model's resolution and the model's own ``encoder_focal`` and
  ``encoder_world_from_cam`` (the camera head's poses, one 4x4 per view, in the head's own frame
  and unit; equal to the written cameras when those are the model's).

Everything is checked (model, images, poses, view indices) before anything is written. Errors
print one line on stderr and exit with code 2, without a traceback.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .manifest import CAMERAS, camera_name
from .quality import PRECISIONS, QUALITY_PRESETS

if TYPE_CHECKING:
    from .runtime import IrisRuntime

EXIT_ERROR = 2
VIDEO_NAME = "orbit.mp4"


class _Parser(argparse.ArgumentParser):
    """argparse, but usage errors are one line too."""

    def error(self, message: str):
        self.exit(EXIT_ERROR, f"{self.prog}: error: {message} (see --help)\n")


def _size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW (e.g. 256x256), got {text!r}") from None
    if h < 1 or w < 1:
        raise argparse.ArgumentTypeError(f"expected positive HxW, got {text!r}")
    return h, w


def _positive(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def _non_negative(text: str) -> int:
    """An argument that is an integer >= 0 (a view index, a port, a queue length)."""
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}")
    return v


def providers_arg(text: str) -> list[str]:
    """``--providers A,B``: ONNX Runtime execution providers in priority order (checked by
    ``IrisRuntime``, which names the ones this onnxruntime has)."""
    names = [t.strip() for t in text.split(",")]
    if not all(names):
        raise argparse.ArgumentTypeError(f"expected comma-separated provider names, e.g. "
                                         f"CUDAExecutionProvider,CPUExecutionProvider, got {text!r}")
    return names


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="iris-render",
        description="Render novel views of a scene from a few unposed photos with an exported IRIS "
                    "model (ONNX Runtime, no torch). Poses are world_from_cam 4x4 in the frame of "
                    "the first image's camera (OpenCV axes: x right, y down, z forward).",
        epilog="Outputs: NAME.png, NAME_depth.png (16-bit, value = depth / far * 65535), "
               "NAME_depth.npy (float32, model units), orbit.mp4 + orbit_poses.json with --orbit, "
               "located_poses.json with --locate, "
               "inputs/*.png with transforms.json (nerfstudio) and colmap/*.txt (COLMAP text) for "
               "the predicted cameras of the inputs. Exit code 2 on any error (one line on "
               "stderr).")
    p.add_argument("model_dir", metavar="MODEL_DIR", help="directory written by iris-export")
    p.add_argument("images", metavar="IMAGES", nargs="+",
                   help="input photos (any size: centre-cropped to the model's aspect and resized)")
    p.add_argument("-o", "--out", required=True, metavar="OUT", help="output directory")
    target = p.add_argument_group("what to render (default: every input view)")
    target.add_argument("--pose", metavar="FILE", action="append", default=[],
                        help="JSON file with a 4x4 world_from_cam or a list of them (repeatable)")
    target.add_argument("--view", metavar="I", type=_non_negative, action="append", default=[],
                        help="the predicted pose of input view I (repeatable)")
    target.add_argument("--orbit", metavar="N", type=_positive,
                        help="N frames on a closed path around the input cameras, plus orbit.mp4")
    target.add_argument("--locate", metavar="PHOTO", nargs="+", action="extend", default=[],
                        help="find the pose of each PHOTO in the inputs' frame (the inputs stay "
                             "the scene): printed, written to located_poses.json (4x4 "
                             "world_from_cam each) and rendered as located_NNN; give it after "
                             "IMAGES")
    p.add_argument("--cameras", type=camera_name, choices=list(CAMERAS), default=None,
                   help="cameras of the inputs: the model's prediction or the camera solve of "
                        "the photos at their own resolution, scaled to the renderer's depth range "
                        "(views it cannot pose keep the model's camera, reported). Default: the "
                        "cameras the model was trained with (its manifest's 'cameras')")
    out = p.add_argument_group("output and speed")
    out.add_argument("--size", metavar="HxW", type=_size,
                     help="output size (default: the model's resolution)")
    out.add_argument("--fps", type=_positive, default=24,
                     help="frame rate of orbit.mp4 (default 24)")
    out.add_argument("--no-depth", action="store_true", help="skip the depth PNG/NPY files")
    out.add_argument("--threads", type=_positive, default=None,
                     help="ONNX Runtime intra-op threads (default: one per physical core)")
    out.add_argument("--chunk-rays", type=_positive, default=None,
                     help="rays per renderer call (default: chosen from the number of views)")
    out.add_argument("--providers", type=providers_arg, default=None, metavar="A,B",
                     help="ONNX Runtime execution providers in priority order, e.g. "
                          "CUDAExecutionProvider,CPUExecutionProvider with onnxruntime-gpu "
                          "(default: the CPU)")
    out.add_argument("--precision", choices=list(PRECISIONS), default="float32",
                     help="renderer graph: float32, or int8 if exported with --quantize int8")
    out.add_argument("--quality", choices=list(QUALITY_PRESETS), default=None,
                     help="speed/error preset (measured in docs/PERFORMANCE.md; default: the "
                          "model's, auto for explicit colour, else exact): auto = the full render "
                          "up to the model's resolution, above it the field at 1/8 of the size "
                          "and the colour from the photos; exact = the full render; balanced = "
                          "32 samples, <= 8 views per ray; fast = 16 samples, 2 views per ray, "
                          "half resolution; adaptive = quarter resolution, the 12%% least "
                          "trusted pixels rendered again exactly")
    out.add_argument("-q", "--quiet", action="store_true", help="print nothing but errors")
    return p


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


def run(args: argparse.Namespace, runtime=None) -> int:
    """iris-render with parsed ``args``; ``runtime``: an ``IrisRuntime`` of ``args.model_dir`` to
    use instead of loading one (``iris-batch`` renders many scenes with one model load)."""
    say = (lambda *a: None) if args.quiet else (lambda *a: print("iris-render:", *a, flush=True))
    t_all = time.perf_counter()
    t0 = time.perf_counter()
    req = _check_request(args, runtime)                          # 1. everything, before writing anything
    scene, located = _encode(req, args, say, time.perf_counter() - t0)       # 2. encode once
    jobs, orbit = _jobs(req, args, scene, located)
    out = _write_cameras(Path(args.out), req, scene, orbit, located)        # 3. the inputs' cameras
    rendered = _render_jobs(req, args, scene, jobs, out, say)              # 4. render
    _summary(req, args, jobs, out, orbit, located, rendered, say)
    say(f"total {time.perf_counter() - t_all:.2f} s")
    return 0


def _check_request(args: argparse.Namespace, runtime=None) -> _Request:
    """The model, the request limits (``iris_runtime.limits``, checked by the same functions
    ``IrisRuntime`` uses), the images, view indices and pose files: every error before a file is
    written."""
    from . import limits as L
    from .errors import InputError
    from .images import fit_to_model, load_image
    from .runtime import IrisRuntime

    rt = runtime or IrisRuntime(args.model_dir, threads=args.threads, precision=args.precision,
                                providers=args.providers)
    H, W = rt.image_size
    size = rt.check_output_size(*args.size) if args.size else (H, W)
    if args.chunk_rays is not None:
        samples = QUALITY_PRESETS[args.quality or rt.default_quality].samples or rt.samples
        L.check_chunk_rays(args.chunk_rays, size[0] * size[1], samples, len(args.images),
                           name="--chunk-rays")
    originals = [load_image(p, p) for p in args.images]          # own resolution: the solve's
    inputs = [fit_to_model(photo, H, W)[0] for photo in originals]
    V = len(inputs)
    bad = [i for i in args.view if i >= V]
    if bad:
        raise InputError(f"--view {bad[0]}: out of range, {V} input image(s) give views 0..{V - 1}")
    poses = [T for f in args.pose for T in _read_poses(f)]
    photos = [load_image(p, f"--locate {p}") for p in args.locate]
    return _Request(rt, size, inputs, originals, poses, photos)


def _encode(req: _Request, args: argparse.Namespace, say, t_load: float):
    """The Scene of the inputs (``--cameras``) and the --locate photos' poses in its frame."""
    rt = req.rt
    t0 = time.perf_counter()
    scene = rt.encode(req.originals, cameras=args.cameras)   # too many images: refused here
    H, W = rt.image_size
    say(f"encoded {len(req.inputs)} view(s) at {H}x{W} in {time.perf_counter() - t0:.2f} s "
        f"(model check + image loading {t_load:.2f} s); focal fx/W={scene.focal[0]:.4f} "
        f"fy/H={scene.focal[1]:.4f}")
    if (args.cameras or rt.default_cameras) != "model":
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
    for path, T in zip(args.locate, located):
        say(f"located {path}: world_from_cam {json.dumps(np.round(T, 6).tolist())}")
    return scene, located


def _jobs(req: _Request, args: argparse.Namespace, scene, located):
    """``[(name, pose or view index), ...]`` to render, and the orbit's poses (or None)."""
    from .orbit import orbit_poses

    jobs: list[tuple[str, np.ndarray | int]] = []
    jobs += [(f"view_{i:03d}", i) for i in args.view]
    jobs += [(f"pose_{k:03d}", T) for k, T in enumerate(req.poses)]
    if located is not None:
        jobs += [(f"located_{k:03d}", T) for k, T in enumerate(located)]
    orbit = None
    if args.orbit:
        orbit = orbit_poses(scene.world_from_cam, args.orbit, near=req.rt.near, far=req.rt.far)
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


def _render_jobs(req: _Request, args: argparse.Namespace, scene, jobs, out: Path, say) -> dict:
    """Render and write every job (PNG, depth, the orbit's video frames) -> seconds per stage
    (``rays``, ``renderer``, ``write``, ``total``) and whether the video was written."""
    height, width = req.size
    progress = _Progress(total=len(jobs) * height * width, enabled=not args.quiet)
    totals = {"rays": 0.0, "renderer": 0.0, "write": 0.0}
    t_render = time.perf_counter()
    writer = None
    try:
        for k, (name, pose) in enumerate(jobs):
            progress.frame(k * height * width)
            res = req.rt.render(scene, pose, height=height, width=width, depth=True,
                                chunk_rays=args.chunk_rays, progress=progress,
                                quality=args.quality)
            totals["rays"] += res.timings["rays"]
            totals["renderer"] += res.timings["renderer"]
            t0 = time.perf_counter()
            _write_png(out / f"{name}.png", res.image)
            if not args.no_depth:
                _write_depth(out / f"{name}_depth.png", out / f"{name}_depth.npy", res.depth,
                             req.rt.far)
            if name.startswith("orbit_"):
                if writer is None:
                    writer = open_video(out / VIDEO_NAME, args.fps, req.size)
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


def _summary(req: _Request, args, jobs, out: Path, orbit, located, rendered: dict, say) -> None:
    """What was written where, and how long it took."""
    say(f"rendered {len(jobs)} view(s) at {req.size[0]}x{req.size[1]} in "
        f"{rendered['total']:.2f} s (rays {rendered['rays']:.2f} s, renderer "
        f"{rendered['renderer']:.2f} s, writing {rendered['write']:.2f} s)")
    first, last = jobs[0][0], jobs[-1][0]
    say(f"images: {out}/{first}.png" + (f" ... {last}.png" if len(jobs) > 1 else "")
        + ("" if args.no_depth else f", depth in NAME_depth.png (16-bit, depth / far * 65535, "
                                    f"far = {req.rt.far:g}) and NAME_depth.npy (float32)"))
    if rendered["video"]:
        say(f"video: {out / VIDEO_NAME} ({len(orbit)} frames at {args.fps} fps)")
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


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from .errors import IrisError
    try:
        return run(args)
    except (IrisError, OSError) as exc:        # IrisError covers bad input and bad model files
        print(f"iris-render: error: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}",
              file=sys.stderr)
        return EXIT_ERROR
    except KeyboardInterrupt:
        print("iris-render: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
