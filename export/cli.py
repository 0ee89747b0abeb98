"""``iris-export CKPT OUT_DIR``: a trained checkpoint -> two validated ONNX graphs + ``iris.json``.

A thin wrapper over ``export.pipeline.export_model``. Exit codes: 0 success; 1 validation failed
(ONNX Runtime disagrees with torch beyond the I/O spec's tolerance); 2 bad invocation or input
(existing OUT_DIR without --force, unreadable checkpoint, unsupported option). Errors print one
line, never a traceback; OUT_DIR is left untouched on every failure.
"""
from __future__ import annotations

import argparse
import sys

from iris_runtime.manifest import CAMERAS, camera_name

from .io_spec import DEFAULT_OPSET, MIN_OPSET

EXIT_VALIDATION = 1
EXIT_USAGE = 2


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="iris-export",
        description="Split a trained IRIS checkpoint into encoder.onnx and renderer.onnx, validate "
                    "them with ONNX Runtime against torch, and write OUT_DIR/iris.json (config, "
                    "sha256 of each graph, I/O spec, validation errors and times).",
        epilog="Exit codes: 0 ok; 1 validation beyond tolerance; 2 bad arguments, existing OUT_DIR "
               "or unreadable checkpoint. OUT_DIR is written atomically (temporary directory + rename).")
    parser.add_argument("checkpoint", metavar="CKPT", help="IRIS checkpoint (.pt) written by iris-train")
    parser.add_argument("out_dir", metavar="OUT_DIR", help="output directory (must not exist unless --force)")
    parser.add_argument("--opset", type=int, default=DEFAULT_OPSET,
                        help=f"ONNX opset, >= {MIN_OPSET} (default: {DEFAULT_OPSET})")
    parser.add_argument("--quantize", choices=["int8"], default=None,
                        help="also write renderer.int8.onnx (dynamic int8 quantisation); its error "
                             "vs torch is recorded in iris.json, not enforced")
    parser.add_argument("--renderer", choices=["reference", "fast", "fast-contrib"],
                        default="fast",
                        help="renderer graph: 'fast' (default: laid out for ONNX Runtime's CPU "
                             "kernels, faster frames than 'reference', same values), "
                             "'reference' (the model's render_samples traced as is) or "
                             "'fast-contrib' (fast with com.microsoft fused ops, slower here); "
                             "see export/fast_renderer.py and docs/PERFORMANCE.md")
    parser.add_argument("--cameras", type=camera_name, choices=list(CAMERAS), default=None,
                        help="the runtime's default cameras, recorded in iris.json (default: "
                             "'refined' where the renderer was trained with 'solve' and the "
                             "camera head distilled from the solve, else the ones the renderer "
                             "was trained with); 'refined' (the camera head's refined by the "
                             "photos) over a renderer trained with 'solve'")
    parser.add_argument("--force", action="store_true", help="replace an existing OUT_DIR")
    parser.add_argument("--quick", action="store_true",
                        help="smaller validation probes and timing runs (tests, smoke checks)")
    parser.add_argument("--threads", type=int, default=None,
                        help="intra-op threads of onnxruntime and torch during validation "
                             "(default: their own; 1 is faster on a busy machine)")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    # Heavy imports (torch, onnx) only after --help and argument errors are out of the way.
    from iris_train.model import CheckpointError

    from .errors import ExportError, ValidationError
    from .pipeline import export_model
    try:
        out = export_model(args.checkpoint, args.out_dir, opset=args.opset, quantize=args.quantize,
                           force=args.force, progress=not args.quiet, quick=args.quick,
                           threads=args.threads, renderer=args.renderer, cameras=args.cameras)
    except ValidationError as exc:
        print(f"iris-export: validation failed: {exc}", file=sys.stderr)
        return EXIT_VALIDATION
    except (ExportError, CheckpointError) as exc:
        print(f"iris-export: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("iris-export: interrupted; nothing was written", file=sys.stderr)
        return 130
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
