"""What solving the cameras costs at encode time: ``IrisRuntime.encode`` of the committed 8-view
sample scene with the encoder's cameras, and with the epipolar solve under each focal-search
pair rule of ``iris_runtime.epipolar.search_focal`` ("all", the default, and "gap", the first
rule), and with the default rule but the texture test of ``flow_matches`` off (``TEXTURE_MIN``
= 0). Median of ``--runs`` wall times after one warm-up per configuration, one process.

    python benchmarks/epipolar_cost.py MODEL_DIR              # an iris-export output
    python benchmarks/epipolar_cost.py MODEL_DIR --threads 1 --runs 3 --json out.json
"""
from __future__ import annotations

import argparse
import functools
import json
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "samples" / "heldout-1000003"


def measure(model_dir: str, threads: int, runs: int) -> dict:
    import cv2

    import iris_runtime.epipolar as E
    from iris_runtime import IrisRuntime
    cv2.setNumThreads(threads)
    rt = IrisRuntime(model_dir, threads=threads)
    paths = sorted(SAMPLE.glob("frame_*.png"))
    original, texture = E.search_focal, E.TEXTURE_MIN
    out = {"views": len(paths), "size": list(rt.image_size), "threads": threads, "runs": runs}
    try:
        for name, cameras, pairs, texture_min in (
                ("encoder cameras", "model", None, texture),
                ("epipolar, focal over every pair", "epipolar", "all", texture),
                ("epipolar, focal over pairs 2-3 apart", "epipolar", "gap", texture),
                ("epipolar, every pair, texture test off", "epipolar", "all", 0.0)):
            if pairs is not None:
                E.search_focal = functools.partial(original, pairs=pairs)
            E.TEXTURE_MIN = texture_min
            rt.encode(paths, cameras=cameras)                      # warm-up
            times = []
            for _ in range(runs):
                t0 = time.perf_counter()
                rt.encode(paths, cameras=cameras)
                times.append(time.perf_counter() - t0)
            out[name] = {"median_s": statistics.median(times), "runs_s": times}
            print(f"{name:40s} {statistics.median(times):7.3f} s", flush=True)
    finally:
        E.search_focal, E.TEXTURE_MIN = original, texture
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model_dir")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    res = measure(args.model_dir, args.threads, args.runs)
    if args.json is not None:
        from iris_runtime.fileio import atomic_write_bytes
        atomic_write_bytes(args.json, json.dumps(res, indent=1).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
