"""What the cameras cost at encode time: ``IrisRuntime.encode`` of 8 photos of 320x240 (and of
the quickstart's 64x64 sample) on one thread, with the encoder's cameras, with the camera solve
(``cameras="solve"``) and with the encoder's cameras refined by the photos
(``cameras="refined"``). Medians of ``--runs`` wall times after one warm-up, one process.

    python benchmarks/encode_cost.py MODEL_DIR                  # an iris-export output
    python benchmarks/encode_cost.py MODEL_DIR --runs 7 --json benchmarks/results/encode_cost.json
    python benchmarks/encode_cost.py MODEL_DIR --set min_trials=2      # a solve setting changed
    python benchmarks/encode_cost.py MODEL_DIR --heldout --cameras model,solve,refined --runs 3
    python benchmarks/encode_cost.py MODEL_DIR --heldout --eval-heldout --cameras refined --runs 3

``--heldout`` adds the 16 held-out synthetic scenes at the model's 64x64 (rendered at 256x256
and area-averaged, as the quickstart's sample is; the [train] extra) and, for every set with true
cameras, the RPA@15 of each mode's cameras over all pairs: error against run time.
``--eval-heldout`` adds the same scenes as ``iris-eval`` brings them to 64x64 (its loader's
resize: other pixels, so other keypoints, and other paths through the refinement).

``--set`` takes the camera studies' settings (``benchmarks/camera_settings.py``: a constant of
a module of ``iris_runtime.cameras``, or a field of ``MapperOptions``).

Photos: ViSP ``Castle-simu`` frames 1, 6, ..., 36 at 320x240 (``benchmarks/camera_solve.py``,
Debian ``visp-images-data``) and the held-out synthetic scene 1000003 rendered at 320x240 (needs
the [train] extra), whichever are available. The machine's load is recorded beside the figures
(``os.getloadavg``): a loaded machine stretches every figure.
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


def photo_sets(heldout: bool = False, eval_heldout: bool = False) -> dict:
    """{name: (8 uint8 RGB photos, their true world_from_cam [8, 4, 4] or None)}: of 240x320,
    the quickstart's 64x64 sample and, with ``heldout`` / ``eval_heldout``, the held-out scenes
    at 64x64 (as the sample is made / as iris-eval loads them)."""
    import numpy as np
    from PIL import Image
    out = {}
    sample = sorted((REPO / "samples" / "heldout-1000003").glob("frame_*.png"))
    if sample:
        out["sample 1000003 64x64"] = ([np.asarray(Image.open(f).convert("RGB")) for f in sample],
                                       None)
    if heldout:
        from benchmarks.camera_solve import heldout_64_scenes
        for scene in heldout_64_scenes():
            out[scene.name.split(" (")[0]] = (scene.photos, scene.world_from_cam)
    if eval_heldout:
        from benchmarks.camera_solve import eval_heldout_64_scenes
        for scene in eval_heldout_64_scenes():
            out[scene.name] = (scene.photos, scene.world_from_cam)
    from benchmarks.camera_solve import CASTLE, CASTLE_SUBSETS, castle_scenes
    if CASTLE.is_dir():
        for scene in castle_scenes():
            if scene.name == "castle 1-36 320x240" and len(CASTLE_SUBSETS["1-36"]) == 8:
                out["castle 1-36 320x240"] = (scene.photos, None)    # RPA needs torch
    try:
        from iris_train.synthetic import render_scene
        s = render_scene(1_000_003, 8, (240, 320))
        out["synthetic 1000003 320x240"] = (list(np.asarray(s.images)), s.world_from_cam)
    except ImportError:
        pass
    return out


def measure(model_dir: str, runs: int, settings: list[str] = (),
            modes: tuple[str, ...] = ("model", "solve", "refined"),
            heldout: bool = False, eval_heldout: bool = False) -> dict:
    import cv2

    import iris_runtime.cameras.replace as replace
    import numpy as np

    from iris_runtime import IrisRuntime
    from benchmarks.camera_settings import apply
    cv2.setNumThreads(1)
    if settings:
        options, solve = apply(list(settings)), replace.solve_cameras
        replace.solve_cameras = lambda photos, depth_range, **kw: solve(
            photos, depth_range, options=options, **kw)        # what encode's solve calls
    rt = IrisRuntime(model_dir, threads=1)
    out = {"threads": 1, "runs": runs, "settings": list(settings),
           "load_before": list(os.getloadavg()), "sets": {}}
    for name, (photos, truth) in photo_sets(heldout, eval_heldout).items():
        res = {}
        for cameras in modes:
            rt.encode(photos, cameras=cameras)                       # warm-up
            times, steps = [], []
            for _ in range(runs):
                timings = {}
                t0 = time.perf_counter()
                scene = rt._encode(photos, timings, cameras)
                times.append(time.perf_counter() - t0)
                steps.append(timings)
            res[cameras] = {"median_s": statistics.median(times), "runs_s": times,
                            "cameras_median_s": statistics.median(t.get("cameras", 0.0)
                                                                  for t in steps),
                            "camera_status": list(scene.camera_status or ()),
                            "camera_source": scene.camera_source,
                            "camera_size": scene.camera_size}
            if truth is not None:
                from benchmarks.camera_solve import pair_errors      # iris_train: torch
                err = pair_errors(scene.world_from_cam, truth)
                res[cameras]["rpa@15"] = float(np.mean(err < 15))
            print(f"{name:28s} cameras={cameras:9s} {res[cameras]['median_s']:.3f} s "
                  f"(cameras {res[cameras]['cameras_median_s']:.3f} s; runs "
                  f"{', '.join(f'{t:.2f}' for t in times)})"
                  + (f" RPA@15 {res[cameras]['rpa@15']:.3f}" if truth is not None else ""),
                  flush=True)
        out["sets"][name] = res
    for prefix in ("heldout-64", "eval-heldout-64"):
        held = {k: v for k, v in out["sets"].items() if k.startswith(prefix + " ")}
        if not held:
            continue
        key = prefix.replace("-", "_")
        out[key] = {}
        for m in modes:
            seconds = [v[m]["median_s"] for v in held.values()]
            r = out[key][m] = {
                "median_s": statistics.median(seconds), "max_s": max(seconds),
                "slowest": max(held, key=lambda k: held[k][m]["median_s"]),
                "rpa@15": float(np.mean([v[m]["rpa@15"] for v in held.values()]))}
            print(f"{prefix}, {len(held)} scenes, cameras={m:9s}: median {r['median_s']:.3f} s,"
                  f" max {r['max_s']:.3f} s ({r['slowest']}), RPA@15 {r['rpa@15']:.3f}",
                  flush=True)
    out["load_after"] = list(os.getloadavg())
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model_dir")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="a solve setting changed (benchmarks/camera_settings.py)")
    ap.add_argument("--cameras", default="model,solve,refined",
                    help="comma-separated camera modes of encode (default: all three)")
    ap.add_argument("--heldout", action="store_true",
                    help="add the 16 held-out scenes at 64x64, with RPA@15 against true cameras")
    ap.add_argument("--eval-heldout", action="store_true",
                    help="add the 16 held-out scenes as iris-eval loads them at 64x64")
    args = ap.parse_args(argv)
    res = measure(args.model_dir, args.runs, args.set, tuple(args.cameras.split(",")),
                  args.heldout, args.eval_heldout)
    print(f"load average before / after: {res['load_before']} / {res['load_after']}")
    if args.json is not None:
        from iris_runtime.fileio import atomic_write_bytes
        atomic_write_bytes(args.json, json.dumps(res, indent=1).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
