"""A salvage that grows: the probe behind docs/CAMERAS.md's "Salvaging the views two starts agree
on" (not shipped). Where no start confirms the chosen one, ``refine.salvage.salvage_agreed_views`` poses every view
outside the agreeing set at once against that set's points; this variant registers them one at a
time as the mapper does (the view that sees the most points, PnP, ten iterations of adjustment,
points triangulated again), then runs the refinement's rounds.

    python scripts/salvage_grow_probe.py MODEL_DIR validation [--min-views 3] [--share 0]
    python scripts/salvage_grow_probe.py MODEL_DIR scenes [--min-views 3] [--share 0] [--real DIR]

``validation``: ``benchmarks/refine_cost.py``'s 24 validation scenes at 64x64 (RPA@15 and the
scenes handed to the solve); ``scenes``: the scenes whose starts agree on three views
(iris-eval's held-out scenes 8 and 10 at 64x64, held-out 10 and 15 at 256x256, `Castle-simu`),
one row each (source, views posed by the salvage, RPA@15, seconds).
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

from iris_runtime.cameras.locate import PNP_MIN_INLIERS, pose_from_points  # noqa: E402
from iris_runtime.cameras.refine import ladder as L  # noqa: E402
from iris_runtime.cameras.refine import salvage as S  # noqa: E402
from iris_runtime.cameras.refine.rounds import (adjust_round, as_reconstruction,  # noqa: E402
                                                run_rounds, start_adjustment)
from iris_runtime.cameras.triangulation import triangulate  # noqa: E402


def grown(best, witnesses, evidence, opts, stages):
    """``refine.salvage.salvage_agreed_views``'s signature and agreeing set; the other views
    registered one at a time, each followed by ten iterations of adjustment with the focal
    held."""
    tracks, centre, image_size = evidence.tracks, evidence.centre, evidence.image_size
    max_error, loss_scale, pnp_error = opts.max_error, opts.loss_scale, opts.pnp_error
    adjust = stages.adjust
    core = S.salvage_core(best, witnesses, stages.salvage, stages.agreement)
    if core is None:
        return None
    V = len(core)
    rot, t, f = best.R.copy(), best.t.copy(), best.focal
    posed, failed = core.copy(), np.zeros(V, bool)

    def scale_view():
        C = -np.einsum("vji,vj->vi", rot, t)
        return int(np.argmax(np.where(posed, np.linalg.norm(C - C[0], axis=1), -1.0)))

    while True:
        X, ok = triangulate(rot, t, f, centre, tracks.uv, tracks.observed & posed[None],
                            max_error=max_error, min_angle=adjust.retriangulation_angle)
        seen = np.where(posed | failed, -1, (ok[:, None] & tracks.observed).sum(0))
        v = int(np.argmax(seen))
        if seen[v] < PNP_MIN_INLIERS:
            break
        sees = ok & tracks.observed[:, v]
        pose = pose_from_points(X[sees], tracks.uv[sees, v], f, image_size, max_error=pnp_error,
                                min_inliers=PNP_MIN_INLIERS, method=stages.salvage.pnp.method)
        if pose is None:
            failed[v] = True
            continue
        rot[v], t[v] = pose[0], pose[1]
        posed[v] = True
        if posed[0]:                                 # view 0 is the gauge the rounds hold fixed
            a = adjust_round(start_adjustment(rot, t, f, centre, tracks, posed), 10, False, True,
                             centre, tracks, scale_view(), max_error, loss_scale, adjust)
            if a is None:
                return None
            rot, t, f = a.R.copy(), a.t.copy(), a.focal
    if not posed[0]:
        return None
    sv = scale_view()
    a = run_rounds(start_adjustment(rot, t, f, centre, tracks, posed), 0, None, centre, tracks,
                   sv, max_error, loss_scale, adjust)
    return as_reconstruction(a, tracks, sv, adjust) if a is not None else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model_dir")
    ap.add_argument("which", choices=("validation", "scenes"))
    ap.add_argument("--min-views", type=int, default=L.DEFAULTS.salvage.min_core_views)
    ap.add_argument("--share", type=float, default=L.DEFAULTS.salvage.min_core_share)
    ap.add_argument("--real", type=Path, default=REPO.parent / "real",
                    help="the real sets (scripts/real_sets.py --out); its castle/ is used")
    args = ap.parse_args()
    S.salvage_agreed_views = grown
    L.DEFAULTS = replace(L.DEFAULTS, salvage=replace(L.DEFAULTS.salvage,
                                                     min_core_views=args.min_views,
                                                     min_core_share=args.share))
    if args.which == "validation":
        from benchmarks.refine_cost import measure
        print(json.dumps(measure(args.model_dir, [], scenes="validation")["summary"]))
        return
    import cv2
    from refine_signals import scene_signals

    from iris_runtime import IrisRuntime
    from iris_train.evaluate.scenes import load_scenes
    cv2.setNumThreads(1)
    rt = IrisRuntime(args.model_dir, threads=1)
    for data, chosen in (("synthetic:heldout@64", (8, 10)), ("synthetic:heldout", (10, 15)),
                         (str(args.real / "castle"), (0, 1))):
        small = data.endswith("@64")
        scenes, _ = load_scenes(data.removesuffix("@64"), rt.image_size, views=8)
        for i, scene in enumerate(scenes):
            if i not in chosen:
                continue
            photos = list(scene.images if small else (getattr(scene, "photos", None)
                                                      or scene.images))
            truth = getattr(scene, "world_from_cam", None)
            truth = None if truth is None else np.linalg.inv(truth[0]) @ truth
            r = scene_signals(rt, photos, truth, False)
            print(json.dumps({"data": data, "scene": i, "source": r["source"],
                              "salvaged": r.get("salvaged"), "rpa@15": r.get("refined_rpa@15"),
                              "seconds": r["refined_seconds"]}), flush=True)


if __name__ == "__main__":
    main()
