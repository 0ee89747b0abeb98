"""Can a refinement tell when it went wrong? Signals of ``cameras="refined"`` per scene, beside
its RPA and the solve's: a probe for a fallback from the refinement to the solve
(docs/CAMERAS.md, "Telling a wrong refinement").

    python scripts/refine_signals.py MODEL_DIR out.json synthetic:heldout@64 \\
        synthetic:capture-heldout /work/real/castle /work/real/castel /work/real/cube

Each DATA is an iris-eval set (``@64``: the model's 64x64 images as the photos, as
``benchmarks/encode_cost.py --heldout`` gives them); all 8 frames of every scene are encoded
with ``cameras="refined"`` and (unless ``--no-solve``) ``"epipolar"``. The signals are read
from inside ``refine.refine_cameras`` (its pairs' essential matrices, its start and its last
round), with no change to it:

- ``explained``: ``refine.explained_share``, the share of the pairs' essential-matrix inliers
  that the refined cameras explain (what ``refine.MIN_EXPLAINED`` gates; here the gate is off,
  so that every refinement is seen);
- ``kept``: the share of the tracks' observations the last round keeps;
- ``start_rotation``: the median angle between the head's relative rotation of a pair and its
  essential matrix's (degrees): how far the start is from the photos' own evidence;
- ``focal_ratio``: the refined focal over the head's.

Per scene: RPA@15 of the refined and solved cameras against the truth where the set has it,
and ``agree@5``, the share of pairs on which the two agree within 5 degrees.
"""
from __future__ import annotations

import argparse
import json
import time

import cv2
import numpy as np

from iris_runtime import IrisRuntime
from iris_runtime.cameras import refine as R
from iris_train.evaluate.scenes import load_scenes
from refine_probe import rpa15 as rpa

_seen: dict = {}


def _watch():
    """Wrap refine's start, rounds and pair estimates to record what each saw (one scene at a
    time, in ``_seen``)."""
    start, round_, pair = R._start, R._round, R.essential_pose

    def watched_start(Rs, *a, **k):
        _seen.setdefault("R_start", Rs.copy())
        return start(Rs, *a, **k)

    def watched_round(a, iterations, refine_focal, last, centre, tracks, *rest, **k):
        _seen.setdefault("focal_start", a.focal)
        out = round_(a, iterations, refine_focal, last, centre, tracks, *rest, **k)
        _seen.update(last=out, observed=tracks.observed, centre=centre)
        return out

    def watched_pair(p, q, focal, size, max_error):
        out = pair(p, q, focal, size, max_error)
        _seen["max_error"] = max_error
        _seen.setdefault("pairs", []).append(
            None if out is None else (out[1], p[out[0]], q[out[0]]))
        return out

    R._start, R._round, R.essential_pose = watched_start, watched_round, watched_pair


def _angle(Ra, Rb) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1) / 2, -1, 1))))


def signals() -> dict:
    last = _seen["last"]
    registered = last.active.sum(0) >= R.REFINED_MIN_OBSERVATIONS
    V = len(last.R)
    pairs = iter(_seen["pairs"])
    matches, start_rot = {}, []
    for a in range(V):
        for b in range(a + 1, V):
            p = next(pairs)
            if p is None:
                continue
            T, ua, ub = p
            if registered[a] and registered[b]:
                matches[a, b] = (ua, ub)
            Rs = _seen["R_start"]
            start_rot.append(_angle(T[:3, :3], Rs[b] @ Rs[a].T))
    return {"explained": R.explained_share(last.R, last.t, last.focal, _seen["centre"], matches,
                                           _seen["max_error"]),
            "kept": float(last.active.sum() / max(_seen["observed"].sum(), 1)),
            "start_rotation": float(np.median(start_rot)) if start_rot else None,
            "focal_ratio": float(last.focal / _seen["focal_start"]), "pairs": len(start_rot)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model_dir")
    ap.add_argument("out")
    ap.add_argument("data", nargs="+")
    ap.add_argument("--no-solve", action="store_true", help="refine only (no agree@5, no solve RPA)")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    _watch()
    R.MIN_EXPLAINED = 0.0     # every refinement is kept, so that its signals and RPA are seen
    rt = IrisRuntime(args.model_dir, threads=1)
    rows = []
    for data in args.data:
        small = data.endswith("@64")
        scenes, _ = load_scenes(data.removesuffix("@64"), rt.image_size, views=8)
        for index, scene in enumerate(scenes):
            photos = list(scene.images if small else (getattr(scene, "photos", None)
                                                      or scene.images))
            _seen.clear()
            t0 = time.perf_counter()
            refined = rt.encode(photos, cameras="refined")
            row = {"data": data, "scene": index, "source": refined.camera_source,
                   "refined_seconds": time.perf_counter() - t0}
            if refined.camera_source == "refined":
                row |= signals()
            truth = getattr(scene, "world_from_cam", None)
            if truth is not None:
                truth = np.linalg.inv(truth[0]) @ truth
                row["refined_rpa@15"] = rpa(refined.world_from_cam, truth)
            if not args.no_solve:
                t0 = time.perf_counter()
                solved = rt.encode(photos, cameras="epipolar")
                row["solve_seconds"] = time.perf_counter() - t0
                row["agree@5"] = rpa(refined.world_from_cam, solved.world_from_cam, 5.0)
                if truth is not None:
                    row["solve_rpa@15"] = rpa(solved.world_from_cam, truth)
            rows.append(row)
            print(json.dumps(row), flush=True)
    with open(args.out, "w") as f:
        json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
