"""Where ``cameras="refined"`` spends its time, and what a setting of it changes: per held-out
scene at the model's 64x64, the RPA@15 of the cameras ``IrisRuntime.encode`` gives (all 28
pairs), whether the refinement kept them or handed the scene to the solve, the bundle
adjustment's iterations (all starts and rounds) and the seconds of the refinement and of the
whole encode (one run, one thread: a ranking, not a timing; ``encode_cost.py`` times).

    python benchmarks/refine_cost.py MODEL_DIR
    python benchmarks/refine_cost.py MODEL_DIR --set refine.REFINE_TOLERANCE=1e-6 --json out.json

``--set`` takes ``scripts/camera_study.py``'s settings (a scalar or flat-tuple constant of a
module of ``iris_runtime.cameras``). Needs the [train] extra (the held-out scenes).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def measure(model_dir: str, settings: list[str]) -> dict:
    import cv2
    import numpy as np

    import iris_runtime.cameras.refine as refine
    import iris_runtime.cameras.replace as replace
    from benchmarks.camera_solve import heldout_64_scenes, pair_errors
    from iris_runtime import IrisRuntime
    from scripts.camera_study import apply
    cv2.setNumThreads(1)
    apply(list(settings))
    counts = {"iterations": 0, "refine_s": 0.0}
    bundle_adjust, refine_cameras = refine.bundle_adjust, replace.refine_cameras

    def counted(*args, **kw):
        res = bundle_adjust(*args, **kw)
        counts["iterations"] += res.iterations
        return res

    def timed(*args, **kw):
        t0 = time.perf_counter()
        try:
            return refine_cameras(*args, **kw)
        finally:
            counts["refine_s"] += time.perf_counter() - t0

    refine.bundle_adjust, replace.refine_cameras = counted, timed
    rt = IrisRuntime(model_dir, threads=1)
    rows = []
    for scene in heldout_64_scenes():
        counts.update(iterations=0, refine_s=0.0)
        t0 = time.perf_counter()
        encoded = rt.encode(scene.photos, cameras="refined")
        seconds = time.perf_counter() - t0
        rpa = float(np.mean(pair_errors(encoded.world_from_cam, scene.world_from_cam) < 15))
        rows.append({"scene": scene.name.split(" (")[0], "rpa@15": rpa,
                     "source": encoded.camera_source, "encode_s": seconds, **counts})
        r = rows[-1]
        print(f"{r['scene']:20s} RPA@15 {rpa:.3f} {r['source']:9s} BA iterations "
              f"{r['iterations']:4d} refine {r['refine_s']:.2f} s encode {seconds:.2f} s",
              flush=True)
    summary = {"rpa@15": float(np.mean([r["rpa@15"] for r in rows])),
               "handed_to_solve": [r["scene"] for r in rows if r["source"] != "refined"],
               "mean_iterations": float(np.mean([r["iterations"] for r in rows])),
               "median_refine_s": statistics.median(r["refine_s"] for r in rows)}
    print(json.dumps(summary))
    return {"settings": list(settings), "load_before": list(os.getloadavg()), "scenes": rows,
            "summary": summary}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model_dir")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    res = measure(args.model_dir, args.set)
    if args.json is not None:
        from iris_runtime.fileio import atomic_write_bytes
        atomic_write_bytes(args.json, json.dumps(res, indent=1).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
