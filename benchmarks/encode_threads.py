"""Does ``IrisRuntime(threads=1)`` keep its camera work on one thread? ``encode`` of the 16
held-out scenes at 64x64 with the model's default cameras, with the runtime's BLAS limit
(``IrisRuntime._blas_threads``) and without it (numpy's BLAS then runs its default, one thread
per core), on an idle machine and beside one busy core (a process spinning, as a loaded server
has). Medians and maxima of one pass after a warm-up.

    python benchmarks/encode_threads.py MODEL_DIR [--json out.json]

Run it without ``OMP_NUM_THREADS`` / ``OPENBLAS_NUM_THREADS`` set: they would limit the BLAS
for both settings. Needs the [train] extra (the held-out scenes).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing
import os
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _spin(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def _pass(rt, scenes, limited: bool) -> dict:
    if not limited:
        rt._blas_threads = contextlib.nullcontext          # the BLAS's own default
    try:
        rt.encode(scenes[0].photos)                          # warm-up
        seconds = []
        for scene in scenes:
            t0 = time.perf_counter()
            rt.encode(scene.photos)
            seconds.append(time.perf_counter() - t0)
    finally:
        rt.__dict__.pop("_blas_threads", None)
    return {"median_s": statistics.median(seconds), "max_s": max(seconds)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model_dir")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        if name in os.environ:
            ap.error(f"{name} is set: it limits the BLAS for both settings; unset it")
    import numpy  # noqa: F401  (its BLAS starts now, before camera_solve sets OMP_NUM_THREADS)
    from benchmarks.camera_solve import heldout_64_scenes
    from iris_runtime import IrisRuntime
    scenes = list(heldout_64_scenes())
    rt = IrisRuntime(args.model_dir, threads=1)
    rows = []
    for busy in (False, True):
        spinner = None
        if busy:
            spinner = multiprocessing.Process(target=_spin, args=(600.0,), daemon=True)
            spinner.start()
        try:
            for limited in (True, False):
                row = {"busy_core": busy, "blas_limited": limited,
                       **_pass(rt, scenes, limited)}
                rows.append(row)
                print(json.dumps(row), flush=True)
        finally:
            if spinner is not None:
                spinner.terminate()
                spinner.join()
    result = {"cameras": rt.default_cameras, "scenes": len(scenes), "rows": rows,
              "load_after": list(os.getloadavg())}
    if args.json is not None:
        from iris_runtime.fileio import atomic_write_bytes
        atomic_write_bytes(args.json, json.dumps(result, indent=1).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
