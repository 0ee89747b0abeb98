"""``iris-render MODEL_DIR IMAGES... -o OUT``: novel views from a few unposed photos, torch-free.

A thin command line over ``IrisRuntime``: its arguments become a ``render_job.RenderOptions`` for
``render_job.render_scene`` (the code ``iris-batch`` runs for each scene too), which encodes the
input images once, then renders:

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
import sys

from .manifest import CAMERAS, camera_name
from .quality import PRECISIONS, QUALITY_PRESETS
from .render_job import RenderOptions, render_scene

EXIT_ERROR = 2


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


def options_from_args(args: argparse.Namespace) -> RenderOptions:
    """The ``RenderOptions`` of ``iris-render``'s parsed ``args`` (``build_parser``)."""
    return RenderOptions(
        views=tuple(args.view), pose_files=tuple(args.pose), orbit=args.orbit,
        locate=tuple(args.locate), cameras=args.cameras, size=args.size, fps=args.fps,
        depth=not args.no_depth, threads=args.threads, chunk_rays=args.chunk_rays,
        providers=None if args.providers is None else tuple(args.providers),
        precision=args.precision, quality=args.quality, quiet=args.quiet)


def run(args: argparse.Namespace) -> int:
    """iris-render with parsed ``args`` (``build_parser``): ``render_job.render_scene`` of
    ``args.model_dir``, ``args.images`` into ``args.out`` -> exit code 0 (errors are raised)."""
    render_scene(args.model_dir, args.images, args.out, options_from_args(args))
    return 0


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
