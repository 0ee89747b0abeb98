"""What ``bundle.bundle_adjust`` costs against another revision's, on the very problems the
refinement gives it: every adjustment ``IrisRuntime.encode(cameras="refined")`` makes on a set of
scenes at 64x64 (its rounds, salvages and witness mapping) is recorded, then each is solved by
this checkout's adjustment and by the one in ``bundle.py`` at ``--against`` (``git show``),
alternately, on one thread. ``--against`` is a revision with the one adjuster (the solve and the
refinement adjusting alike, from the commit "One bundle adjuster" on): before it, ``bundle.py``
held two and the refinement ran the other one. Reports the seconds of each (the sum over the problems, and the best
of ``--runs``), their ratio, and whether the two take the same iterations to the same cameras.

    python benchmarks/adjustment_cost.py MODEL_DIR --against main
    python benchmarks/adjustment_cost.py MODEL_DIR --against main --scenes validation --json F

Needs the [train] extra (the scenes) and git (the other revision).
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def adjustment_at(revision: str):
    """``bundle_adjust`` of ``iris_runtime/cameras/bundle.py`` at git ``revision`` (one with a
    single adjuster: the refinement's)."""
    source = subprocess.run(["git", "show", f"{revision}:iris_runtime/cameras/bundle.py"],
                            cwd=REPO, check=True, capture_output=True, text=True).stdout
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"bundle_{revision}.py"
        path.write_text(source)
        spec = importlib.util.spec_from_file_location(path.stem, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[path.stem] = module              # dataclasses look their module up
        spec.loader.exec_module(module)
    adjusters = [name for name in vars(module) if name.endswith("bundle_adjust")]
    if adjusters != ["bundle_adjust"]:
        raise SystemExit(f"{revision}: bundle.py has the adjusters {adjusters}, not one "
                         "bundle_adjust (a revision from before the single adjuster)")
    return module.bundle_adjust


def recorded_problems(model_dir: str, scenes: str) -> list:
    """The (args, kwargs) of every adjustment the refinement makes on ``scenes``."""
    import cv2

    import iris_runtime.cameras.mapper as mapper
    import iris_runtime.cameras.refine.rounds as refine
    from benchmarks.camera_solve import SETS_64
    from iris_runtime import IrisRuntime
    cv2.setNumThreads(1)
    problems, adjust = [], refine.bundle_adjust

    def recording(*args, **kw):
        problems.append((args, kw))
        return adjust(*args, **kw)

    refine.bundle_adjust = mapper.bundle_adjust = recording
    rt = IrisRuntime(model_dir, threads=1)
    try:
        for scene in SETS_64[scenes]():
            rt.encode(scene.photos, cameras="refined")
    finally:
        refine.bundle_adjust = mapper.bundle_adjust = adjust
    return problems


def compare(problems: list, ours, theirs, runs: int) -> dict:
    import numpy as np
    seconds = {"this checkout": [], "against": []}
    for run in range(runs):
        totals = {"this checkout": 0.0, "against": 0.0}
        for args, kw in problems:
            # Alternately first, so that neither always runs on a warm cache.
            order = (("this checkout", ours), ("against", theirs))
            for name, adjust in (order if run % 2 == 0 else order[::-1]):
                t0 = time.perf_counter()
                adjust(*args, **kw)
                totals[name] += time.perf_counter() - t0
        for name in totals:
            seconds[name].append(totals[name])
        print(f"run {run + 1}: this checkout {totals['this checkout']:.3f} s, "
              f"against {totals['against']:.3f} s", flush=True)
    same_iterations, rotation, focal, points = True, 0.0, 0.0, 0.0
    for args, kw in problems:
        a, b = ours(*args, **kw), theirs(*args, **kw)
        same_iterations &= a.iterations == b.iterations
        rotation = max(rotation, float(np.abs(a.R - b.R).max()))
        focal = max(focal, abs(a.focal - b.focal) / b.focal)
        points = max(points, float(np.abs(a.points - b.points).max()))
    best = {name: min(s) for name, s in seconds.items()}
    return {"problems": len(problems),
            "observations": int(sum(np.asarray(args[6]).sum() for args, _ in problems)),
            "seconds": seconds, "best_s": best,
            "ratio": best["against"] / best["this checkout"],
            "same_iterations": bool(same_iterations),
            "max_rotation_entry_difference": rotation,
            "max_relative_focal_difference": focal,
            "max_point_coordinate_difference": points}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model_dir")
    ap.add_argument("--against", required=True, help="a git revision whose bundle.py to time")
    ap.add_argument("--scenes", default="eval-heldout",
                    choices=("heldout", "validation", "validation-more", "eval-heldout"))
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    from iris_runtime.cameras.bundle import bundle_adjust
    theirs = adjustment_at(args.against)
    problems = recorded_problems(args.model_dir, args.scenes)
    print(f"{len(problems)} adjustments recorded on {args.scenes}", flush=True)
    res = {"scenes": args.scenes, "against": args.against,
           "load_before": list(os.getloadavg()),
           **compare(problems, bundle_adjust, theirs, args.runs)}
    print(json.dumps({k: v for k, v in res.items() if k != "seconds"}))
    if args.json is not None:
        from iris_runtime.fileio import atomic_write_bytes
        atomic_write_bytes(args.json, json.dumps(res, indent=1).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
