"""The ``iris-eval`` command: arguments in, tables out (the work is ``evaluate``)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from iris_runtime.manifest import camera_name
from iris_runtime.quality import QUALITY_PRESETS

from .backends import backend_for
from .cameras import CAMERA_MODES, LOCATE_MODES
from .evaluation import evaluate
from .protocol import DEFAULT_VIEWS, RAND_SEED, TARGET_FRAMES, split_frames
from .report import format_cameras, format_scenes, format_table, write_json
from .scenes import load_evaluable, load_scenes

__all__ = ["main", "build_parser"]

_DESCRIPTION = ("iris-eval: novel view synthesis (PSNR, SSIM) and relative pose accuracy (RPA) of "
                "an IRIS model.")
_EPILOG = """\
    iris-eval runs/tiny/last.pt synthetic:heldout --json eval.json
    iris-eval out/ my_scenes/ --scenes 10 --grid grid.png      # an exported model, users' data
    iris-eval out/ real/castle --cameras true                  # the data's own cameras
    iris-eval out/ synthetic:heldout --size 256 --json eval256.json   # at 256x256 output

--size S: the targets are rendered at SxS and scored against their photos centre-cropped to a
square and shrunk to S (cv2.INTER_AREA); the references go to the encoder as photos at their own
resolution (synthetic sets: their 256x256 renders, so S <= 256; a folder's files as stored; S
above the photos' size is refused). The JSON gains "output_size", "model_size" and the baseline
"upsampled" (the model-resolution render of the same pose, cv2.INTER_CUBIC-resized to S) beside
"best_reference" and "nearest_reference" at S; the cameras and located poses follow the same
protocol. Exported models render through IrisRuntime.render(height=S, width=S); checkpoints
render at S in torch, sampling their explicit colours from the reference photos brought to S.

Protocol: see the module docstring of iris_train.evaluate."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="iris-eval", description=_DESCRIPTION, epilog=_EPILOG,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", metavar="MODEL",
                        help="checkpoint (.pt) or exported model directory (with iris.json)")
    parser.add_argument("data", metavar="DATA",
                        help="'synthetic:heldout' (the record), 'synthetic:validation' (where "
                             "choices are made), 'synthetic:capture-heldout' (capture-like "
                             "held-out scenes), 'synthetic:capture-validation' (their "
                             "validation twins) or a folder of scene folders")
    parser.add_argument("--json", metavar="FILE", type=Path, default=None,
                        help='write {"seq": ..., "rand": ...} (means and one record per scene) '
                             "to FILE (atomically)")
    parser.add_argument("--scenes", metavar="N", type=int, default=None,
                        help="evaluate only the first N scenes")
    parser.add_argument("--views", metavar="N", type=int, default=DEFAULT_VIEWS,
                        help=f"frames per scene (default {DEFAULT_VIEWS}; targets {TARGET_FRAMES} at 8)")
    parser.add_argument("--seed", type=int, default=RAND_SEED,
                        help=f"seed of the Rand-order permutations (default {RAND_SEED})")
    parser.add_argument("--grid", metavar="FILE.png", type=Path, default=None,
                        help="write a PNG grid of one scene (references, targets, renders, "
                             "soft and true depth, and the cameras: those rendered from, the "
                             "true ones and, where --cameras replaced them, the camera head's)")
    parser.add_argument("--grid-scene", metavar="I", type=int, default=0,
                        help="the scene of --grid, by position (default 0, the first)")
    parser.add_argument("--threads", type=int, default=None,
                        help="intra-op threads of torch (checkpoint) or ONNX Runtime (exported "
                             "model); default: the library's choice. On a busy machine 1 can be "
                             "much faster than oversubscribed cores")
    parser.add_argument("--cameras", type=camera_name, choices=CAMERA_MODES, default=None,
                        help="cameras of the references: the model's, the camera solve of "
                             "their photos scaled to the model's units ('solve': "
                             "iris_runtime.cameras), or the data's own ('true': transforms.json / "
                             "COLMAP text of a folder, the true cameras of synthetic scenes; re-based on "
                             "view 0 and scaled by the solve's depth rule); default: the cameras "
                             "the model was trained with (its manifest's or checkpoint's)")
    parser.add_argument("--locate", type=camera_name, choices=LOCATE_MODES, default=None,
                        help="poses of the targets: the model's locate, the camera solve "
                             "against the references' cameras (iris_runtime.cameras."
                             "locate_views; model fallback per target), or the data's own "
                             "(with --cameras true); default: as --cameras")
    parser.add_argument("--size", metavar="S", type=int, default=None,
                        help="evaluate at SxS output (a square model): renders at S against the "
                             "photos brought to S (centre crop, INTER_AREA; refused when the "
                             "data's photos are smaller than S), references encoded from their "
                             "full-resolution photos, plus the 'upsampled' baseline (the "
                             "model-resolution render resized to S, INTER_CUBIC). Exported "
                             "models and checkpoints alike (a checkpoint samples its colours from "
                             "the reference photos brought to S). Default: the model's resolution")
    parser.add_argument("--quality", metavar="PRESET", choices=tuple(QUALITY_PRESETS), default=None,
                        help=f"render preset passed to IrisRuntime.render(quality=...) (one of "
                             f"{', '.join(QUALITY_PRESETS)}; exported models; a checkpoint "
                             "renders 'exact' only), the model-resolution render of --size's "
                             "'upsampled' too; default: none passed (IrisRuntime.render's default)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.scenes is not None and args.scenes < 1:
        parser.error("--scenes must be at least 1")
    if args.views < 2:
        parser.error("--views must be at least 2")
    if args.size is not None and args.size < 1:
        parser.error("--size must be at least 1")
    if args.threads is not None:
        if args.threads < 1:
            parser.error("--threads must be at least 1")
        if not Path(args.model).is_dir():
            import torch
            torch.set_num_threads(args.threads)
    from iris_runtime.errors import IrisError
    try:
        model = load_evaluable(args.model, threads=args.threads)
        model_size = backend_for(model).image_size
        extra = {} if args.size is None else {"size": args.size}     # (none: the calls as ever)
        if args.quality is not None:
            extra["quality"] = args.quality
        scenes, count = load_scenes(args.data, model_size, args.views, args.scenes,
                                    **({} if args.size is None else
                                       {"output_size": (args.size, args.size)}))
        results = evaluate(model, scenes, views=args.views, seed=args.seed, grid=args.grid,
                           progress=not args.no_progress, total=count, cameras=args.cameras,
                           locate=args.locate, grid_scene=args.grid_scene, **extra)
    except (IrisError, ValueError, FileNotFoundError) as exc:   # bad model, data or arguments
        print(f"iris-eval: error: {exc}", file=sys.stderr)
        return 2
    refs, targets = split_frames(args.views)
    print(f"iris-eval: {args.model} on {args.data}: {count} scene(s), {args.views} frames, "
          f"references {refs}, targets {targets}"
          + ("" if args.size is None else
             f"; at {args.size}x{args.size} (model {model_size[1]}x{model_size[0]})")
          + ("" if args.quality is None else f"; quality {args.quality}"))
    print(format_table(results))
    print()
    print(format_scenes(results))
    for line in format_cameras(results):
        print(line)
    if args.json is not None:
        write_json(args.json, results)
        print(f"wrote {args.json}")
    if args.grid is not None:
        print(f"wrote {args.grid}")
    return 0
