"""Error against run time: every speed/quality knob of IrisRuntime.render, two anchors, one run.

    python benchmarks/error_vs_time.py                       # models/iris-tiny-rgb.pt, all parts
                                                             # (~12 min on 2 cores, with export,
                                                             # before the sizing part was added)
    python benchmarks/error_vs_time.py --checkpoint runs/tiny/last.pt --scenes 1 --parts knobs
    python benchmarks/error_vs_time.py --quick --model-dir MODEL --out OUT_DIR
                                         # every code path in ~1 min; not a measurement

Parts (everything in one process; the tcmalloc torch anchor and the 512x512 memory measurement
in subprocesses, ``python -m benchmarks.evt.child``):

- knobs:   held-out scenes (``iris_train.data.HELDOUT_SEEDS``, 8 frames, targets
           ``evaluate.TARGET_FRAMES``, the others references; all frames encoded, targets rendered
           from ``Scene.subset(refs)`` at their predicted poses; every row encodes with the camera
           head's cameras, ``encode(cameras="model")``, since torch has no camera solve and
           the cameras do not change the renderer's work). Every knob against the torch
           eager reference (``IrisModel.render``, as installed and with tcmalloc preloaded) and
           the full ORT runtime. Seconds per target frame (median of ``--runs`` timed renders after
           one warm-up render per configuration), max abs difference and PSNR against the full
           render (ORT, exact), PSNR/SSIM against the ground truth.
- scaling: like the paper's Table 11: (reference views, targets) = (4, 1) ... (32, 8), seconds for
           encode + render of all targets: torch eager, the exact ORT path, the balanced preset.
- sizing:  what a server is sized by: seconds per frame of every preset at 64^2, 128^2, 256^2
           from 4, 8, 16 reference views, and frames per second of every preset over a 24-pose
           orbit of one encoded 8-view scene (``--sizing-*``, ``--fps-*``).
- peak:    float32 matmul peak of this machine (numpy, 4096^3) against the renderer graph's
           analytic FLOPs per second (FLOPs counted from the shapes of every renderer call).
- memory:  peak RSS of a 512x512 render from 16 reference views (a fresh subprocess).

Results: ``--out`` (default benchmarks/results/): error_vs_time.json, error_vs_time.md,
error_vs_time.png. The pieces: ``benchmarks/evt/`` (rows, machine, measure, child, targets,
report).
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.evt import measure, report, rows as R  # noqa: E402
from benchmarks.evt.machine import best_peak, machine_facts, matmul_peak  # noqa: E402
from benchmarks.evt.targets import evaluate_targets, fastest_exact  # noqa: E402
from iris_runtime.fileio import sha256_file  # noqa: E402

PARTS = ("knobs", "scaling", "sizing", "peak", "memory")

#: --quick: every part and row at toy sizes (a code-path check in about a minute on 2 busy cores,
#: not a measurement). Applied to the options left at their defaults.
QUICK = {"runs": 1, "size": 16, "scaling": "4x1,16x1", "scaling_size": 8, "memory_size": 32,
         "memory_quality": "balanced,exact@16", "matmul_size": 1024, "sizing_sizes": "8,16",
         "sizing_views": "4,8", "fps_size": 8, "fps_poses": 2}


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", type=Path, default=REPO / "models" / "iris-tiny-rgb.pt")
    ap.add_argument("--model-dir", type=Path, help="an iris-export output of the checkpoint "
                    "(default: export it, with --quantize int8, to a temporary directory)")
    ap.add_argument("--scenes", type=int, default=1)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
    ap.add_argument("--parts", default=",".join(PARTS))
    ap.add_argument("--scaling", default=",".join(f"{v}x{t}" for v, t in R.SCALING),
                    help="(views)x(targets) list")
    ap.add_argument("--size", type=int, default=64, help="knobs: target frame size (64: the "
                    "model's; smaller only for quick checks, ground truth area-resized)")
    ap.add_argument("--scaling-size", type=int, default=24, help="scaling: target frame size")
    ap.add_argument("--sizing-sizes", default=",".join(map(str, R.SIZING_SIZES)),
                    help="sizing: output sizes (square), a list")
    ap.add_argument("--sizing-views", default=",".join(map(str, R.SIZING_VIEWS)),
                    help="sizing: numbers of reference views, a list")
    ap.add_argument("--fps-views", type=int, default=R.SIZING_FPS_VIEWS,
                    help="sizing: reference views of the frames-per-second scene")
    ap.add_argument("--fps-size", type=int, default=R.SIZING_FPS_SIZE,
                    help="sizing: frame size of the frames-per-second orbit")
    ap.add_argument("--fps-poses", type=int, default=R.SIZING_FPS_POSES,
                    help="sizing: poses of the frames-per-second orbit")
    ap.add_argument("--memory-size", type=int, default=512)
    ap.add_argument("--memory-quality", default="balanced,exact@128",
                    help="quality[@size] list (size default --memory-size)")
    ap.add_argument("--matmul-size", type=int, default=4096, help="peak: n of the n^3 matmul")
    ap.add_argument("--no-tcmalloc", action="store_true")
    ap.add_argument("--note", default="", help="a note on the model (e.g. which checkpoint)")
    ap.add_argument("--quick", action="store_true", help="toy sizes and one run everywhere "
                    "(" + ", ".join(f"--{k.replace('_', '-')} {v}" for k, v in QUICK.items())
                    + "): checks every code path, measures nothing; use with --out elsewhere")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    args = ap.parse_args(argv)
    if args.quick:
        for key, value in QUICK.items():
            if getattr(args, key) == ap.get_default(key):
                setattr(args, key, value)
        args.note = "; ".join(n for n in (args.note, "--quick: code-path check, not a "
                                          "measurement") if n)
    args.scaling = [tuple(int(x) for x in s.split("x")) for s in args.scaling.split(",") if s]
    args.memory_quality = [q for q in args.memory_quality.split(",") if q]
    args.sizing_sizes = [int(x) for x in str(args.sizing_sizes).split(",") if x]
    args.sizing_views = [int(x) for x in str(args.sizing_views).split(",") if x]
    return args


def _shown(path: Path) -> str:
    """``path`` as the results record it: relative to the repository where it lies inside it,
    else its name alone (results name no machine's directories)."""
    p = Path(path).resolve()
    return p.relative_to(REPO).as_posix() if p.is_relative_to(REPO) else p.name


def main(argv=None) -> int:
    args = parse_args(argv)
    parts = set(args.parts.split(","))
    t_start = time.perf_counter()

    def log(msg):
        print(f"[{time.perf_counter() - t_start:7.1f} s] {msg}", flush=True)

    from iris_runtime import IrisRuntime
    results: dict = {"machine": machine_facts(args.threads),
                     "args": {k: (_shown(v) if isinstance(v, Path) else v)
                              for k, v in vars(args).items()}}
    results["model"] = {"checkpoint": _shown(args.checkpoint),
                        "sha256": sha256_file(args.checkpoint),
                        "note": args.note}
    tmp = None
    model_dir = args.model_dir
    if model_dir is None:
        from export.pipeline import export_model
        tmp = tempfile.TemporaryDirectory()
        model_dir = Path(tmp.name) / "model"
        log(f"exporting {args.checkpoint} (with int8)")
        export_model(args.checkpoint, model_dir, quantize="int8", force=True, quick=True,
                     progress=False, threads=args.threads)
    rt = IrisRuntime(model_dir, threads=args.threads)
    rt_nocull = IrisRuntime(model_dir, threads=args.threads, cull=False)
    rt_par = IrisRuntime(model_dir, threads=args.threads, workers=2)
    model = None
    try:
        from iris_train.model import load_model, read_checkpoint
        model = load_model(args.checkpoint)
        results["model"]["step"] = read_checkpoint(args.checkpoint).get("step")
    except ImportError:
        log("torch not installed: no torch anchor")
    # The matmul peak first, before anything else has warmed or loaded the machine.
    if "peak" in parts:
        log(f"peak: numpy matmul {args.matmul_size}^3")
        results["peak"] = {"matmul": matmul_peak(args.matmul_size)}
        log(f"  {results['peak']['matmul']['gflops']:.1f} GFLOP/s")
    if "knobs" in parts:
        results["knobs"] = measure.part_knobs(args, rt, rt_nocull, rt_par, model, log)
    if "peak" in parts and "knobs" in parts:
        # Again after the exact paths were timed: the peak is the faster of the two.
        log(f"peak: numpy matmul {args.matmul_size}^3 again")
        again = matmul_peak(args.matmul_size)
        log(f"  {again['gflops']:.1f} GFLOP/s")
        results["peak"]["matmul"] = best_peak([results["peak"]["matmul"], again])
    # The faster exact configuration (1 worker x threads, or 2 workers) runs the remaining parts
    # (same output; measured in the knobs table).
    best = fastest_exact(results)
    workers = 2 if best is not None and best["name"] == R.EXACT_2_WORKERS else 1
    results["workers_used"] = workers
    rt_best = rt_par if workers == 2 else rt
    if "scaling" in parts:
        log(f"scaling (workers={workers})")
        results["scaling"] = measure.part_scaling(args, rt_best, model, log)
    if "sizing" in parts:
        log(f"sizing (workers={workers})")
        results["sizing"] = measure.part_sizing(args, rt_best, log)
    if "peak" in parts:
        results["peak"].update(measure.part_peak(results["peak"]["matmul"],
                                                 results.get("knobs", {}).get("rows", []),
                                                 rt, args.threads))
    if "memory" in parts:
        results["memory"] = measure.part_memory(args, model_dir, workers, log)
    results["targets"] = evaluate_targets(results)
    results["seconds_total"] = time.perf_counter() - t_start
    results["machine"]["load_avg_end"] = os.getloadavg()
    text = report.write(results, args.out)
    log(f"wrote {args.out}/error_vs_time.{{json,md,png}}")
    print(text)
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
