"""Where ``cameras="refined"`` spends its time, and what a setting of it changes: per held-out
(or ``--scenes validation``, ``validation-more``) scene at the model's 64x64, the RPA@15 of the
cameras ``IrisRuntime.encode`` gives (all 28 pairs), whether the refinement kept them or handed the
scene to the solve, the bundle adjustment's iterations (all starts and rounds) and the seconds of
the refinement and of the whole encode (one run, one thread: a ranking, not a timing;
``encode_cost.py`` times).

    python benchmarks/refine_cost.py MODEL_DIR
    python benchmarks/refine_cost.py MODEL_DIR --set refine.adjust.tolerance=1e-6 --json out.json
    python benchmarks/refine_cost.py MODEL_DIR --profile      # + the refinement's time by step

``--profile`` runs the scenes under cProfile and adds each scene's seconds in each of the
refinement's steps (SIFT, matching, essential matrices, tracks, bundle adjustment,
triangulation, the witness mapping) and their shares over the set.

``--set`` takes the camera studies' settings (``benchmarks/camera_settings.py``: a scalar or
flat-tuple constant of a module of ``iris_runtime.cameras``, or ``refine.STAGE.FIELD``, a field
of the refinement's ``RefineOptions``). Needs the [train] extra (the held-out scenes).
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


#: The refinement's steps, by the function that does each (``iris_runtime.cameras``). The
#: witness mapping's own adjustments and registrations count under "witness mapping" only.
STEPS = {"scene_features": "SIFT", "match_features": "matching",
         "essential_pose": "essential matrices", "build_tracks": "tracks",
         "bundle_adjust": "bundle adjustment",
         "triangulate": "triangulation", "witness_mapping": "witness mapping"}


def step_seconds(profile) -> tuple[dict, float]:
    """({step: seconds}, the seconds of ``refine_cameras``) from a ``cProfile.Profile``."""
    import pstats
    total, steps = 0.0, {}
    for (path, _, name), (_, _, _, cumulative, callers) in pstats.Stats(profile).stats.items():
        if "iris_runtime" not in path:
            continue
        if name == "refine_cameras":
            total += cumulative
        elif name in STEPS:
            # Only the calls made inside the refinement (the solve calls some of them too).
            inside = sum(c[3] for (_, _, caller), c in callers.items()
                         if caller in ("refine_cameras", "adjust_round", "start_adjustment",
                                         "counted"))
            steps[STEPS[name]] = steps.get(STEPS[name], 0.0) + inside
    return dict(sorted(steps.items(), key=lambda kv: -kv[1])), total


def measure(model_dir: str, settings: list[str], profile: bool = False,
            scenes: str = "heldout") -> dict:
    import cProfile

    import cv2
    import numpy as np

    import iris_runtime.cameras.refine.rounds as refine
    import iris_runtime.cameras.replace as replace
    from benchmarks.camera_solve import SETS_64, pair_errors
    from iris_runtime import IrisRuntime
    from benchmarks.camera_settings import apply
    cv2.setNumThreads(1)
    apply(list(settings))
    counts = {"iterations": 0, "refine_s": 0.0}
    adjust, refine_cameras = refine.bundle_adjust, replace.refine_cameras

    def counted(*args, **kw):
        res = adjust(*args, **kw)
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
    by_step, profiled = {}, 0.0
    for scene in SETS_64[scenes]():
        counts.update(iterations=0, refine_s=0.0)
        profiler = cProfile.Profile() if profile else None
        t0 = time.perf_counter()
        if profiler is not None:
            profiler.enable()
        encoded = rt.encode(scene.photos, cameras="refined")
        if profiler is not None:
            profiler.disable()
        seconds = time.perf_counter() - t0
        rpa = float(np.mean(pair_errors(encoded.world_from_cam, scene.world_from_cam) < 15))
        rows.append({"scene": scene.name.split(" (")[0], "rpa@15": rpa,
                     "source": encoded.camera_source, "encode_s": seconds, **counts})
        r = rows[-1]
        if profiler is not None:     # seconds under cProfile: a ranking of the steps
            steps, total = step_seconds(profiler)
            r["refine_steps_s"] = steps
            profiled += total
            for k, v in steps.items():
                by_step[k] = by_step.get(k, 0.0) + v
        print(f"{r['scene']:20s} RPA@15 {rpa:.3f} {r['source']:9s} BA iterations "
              f"{r['iterations']:4d} refine {r['refine_s']:.2f} s encode {seconds:.2f} s",
              flush=True)
    summary = {"rpa@15": float(np.mean([r["rpa@15"] for r in rows])),
               "handed_to_solve": [r["scene"] for r in rows if r["source"] != "refined"],
               "mean_iterations": float(np.mean([r["iterations"] for r in rows])),
               "median_refine_s": statistics.median(r["refine_s"] for r in rows)}
    if profile and profiled:
        summary["refine_time_by_step"] = {k: v / profiled for k, v in sorted(
            by_step.items(), key=lambda kv: -kv[1])}
    print(json.dumps(summary))
    return {"settings": list(settings), "set": scenes,
            "load_before": list(os.getloadavg()),
            "scenes": rows,
            "summary": summary}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model_dir")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--scenes", default="heldout",
                    choices=("heldout", "validation", "validation-more", "eval-heldout"),
                    help="the 16 held-out scenes, the first 24 validation scenes (where a "
                         "setting is chosen), validation scenes 24-47, or the held-out scenes "
                         "as iris-eval resizes them, at 64x64")
    ap.add_argument("--profile", action="store_true",
                    help="also the share of the refinement's time in each of its steps")
    args = ap.parse_args(argv)
    res = measure(args.model_dir, args.set, args.profile, args.scenes)
    if args.json is not None:
        from iris_runtime.fileio import atomic_write_bytes
        atomic_write_bytes(args.json, json.dumps(res, indent=1).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
