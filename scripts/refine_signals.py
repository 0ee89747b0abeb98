"""Can a refinement tell when it went wrong? The agreement between the starts of
``cameras="refined"`` per scene, each start's RPA, beside the solve: the evidence behind
``refine.MIN_AGREEMENT`` (docs/CAMERAS.md, "Telling a wrong refinement").

    python scripts/refine_signals.py MODEL_DIR out.json synthetic:heldout@64 \\
        synthetic:capture-heldout data/real/castle data/real/castel data/real/cube

Each DATA is an iris-eval set (``@64``: the model's 64x64 images as the photos, as
``benchmarks/encode_cost.py --heldout`` gives them). All 8 frames of every scene are encoded
with ``cameras="refined"`` through the runtime's public entry point: as shipped, recording the
values ``refine.agreement`` returns to the check (the best-ranked start's cameras against each
other start's, until one reaches ``MIN_AGREEMENT``), where none does, the salvage (``"core"``:
the views of the largest set another start agrees with it on; ``"salvaged"``: the views it
posed, 0 where the set was too small), where that failed too, what the witness mapping did
(``"witness"``: "confirmed a start", "salvaged N views", "none" or "no mapping"), the source and
the seconds; then with ``MIN_AGREEMENT = 0`` (the chosen
start's cameras, whatever the check says) and with ``STARTS`` one start at a time (each start's
own end; a start that leaves view 0 unposed is handed to the solve by the runtime and has no
RPA of its own). Where the set has true cameras: RPA@15 of each, of the cameras as shipped and
of the solve (``"epipolar"``, unless ``--no-solve``).
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from iris_runtime import IrisRuntime
from iris_runtime.cameras import refine as R
from iris_train.evaluate.scenes import load_scenes
from refine_probe import rpa15 as rpa


def scene_signals(rt: IrisRuntime, photos, truth, solve: bool) -> dict:
    shipped = R.MIN_AGREEMENT, R.STARTS, R.agreement, R._salvaged, R.agreeing_views
    witnessed_as_shipped = R._witnessed
    seen: list[float] = []
    salvaged: list[int] = []
    core = [0]
    witness: list[str] = []

    def witnessed(best, ends, mapped, salvage):
        rec = witnessed_as_shipped(best, ends, mapped, salvage)
        witness.append("no mapping" if mapped is None else "none" if rec is None
                       else "confirmed a start" if any(rec is e for e in (best, *ends))
                       else f"salvaged {int(rec.registered.sum())} views")
        return rec

    def views(*args):
        out = shipped[4](*args)
        core[0] = max(core[0], int(out.sum()))
        return out

    def recorded(*args):
        seen.append(shipped[2](*args))
        return seen[-1]

    def salvage(*args):
        rec = shipped[3](*args)
        salvaged.append(0 if rec is None else int(rec.registered.sum()))
        return rec

    R.agreement, R._salvaged, R.agreeing_views = recorded, salvage, views
    R._witnessed = witnessed
    try:
        t0 = time.perf_counter()
        as_shipped = rt.encode(photos, cameras="refined")
        row = {"refined_seconds": time.perf_counter() - t0, "source": as_shipped.camera_source,
               "agreement": list(seen),
               **({"core": core[0], "salvaged": salvaged[0]} if salvaged else {}),
               **({"witness": witness[0]} if witness else {})}
        R._salvaged, R._witnessed = shipped[3], witnessed_as_shipped
        R.MIN_AGREEMENT = 0.0
        chosen = rt.encode(photos, cameras="refined")
        ends = {}
        for kind in shipped[1]:
            R.STARTS = (kind,)
            ends[kind] = rt.encode(photos, cameras="refined")
    finally:
        R.MIN_AGREEMENT, R.STARTS, R.agreement, R._salvaged, R.agreeing_views = shipped
        R._witnessed = witnessed_as_shipped
    if truth is not None:
        row["refined_rpa@15"] = rpa(as_shipped.world_from_cam, truth)
        if chosen.camera_source == "refined":
            row["chosen_rpa@15"] = rpa(chosen.world_from_cam, truth)
        row["rpa@15"] = {k: rpa(e.world_from_cam, truth) for k, e in ends.items()
                         if e.camera_source == "refined"}
    if solve:
        t0 = time.perf_counter()
        solved = rt.encode(photos, cameras="epipolar")
        row["solve_seconds"] = time.perf_counter() - t0
        if truth is not None:
            row["solve_rpa@15"] = rpa(solved.world_from_cam, truth)
    return row


def _shown(data: str) -> str:
    """A DATA argument as the results record it: a set name as given, a folder relative to the
    repository where it lies inside it, else its parent's name and its own (``real/castle``:
    results name no machine's directories)."""
    if data.startswith("synthetic:"):
        return data
    p, root = Path(data).resolve(), Path(__file__).resolve().parents[1]
    return (p.relative_to(root) if p.is_relative_to(root)
            else Path(p.parent.name, p.name)).as_posix()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model_dir")
    ap.add_argument("out")
    ap.add_argument("data", nargs="+")
    ap.add_argument("--no-solve", action="store_true", help="no solve RPA")
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                    help="a setting of iris_runtime.cameras (scripts/camera_study.py's --set)")
    args = ap.parse_args()
    from camera_study import apply
    apply(args.set)
    cv2.setNumThreads(1)
    rt = IrisRuntime(args.model_dir, threads=1)
    rows = []
    for data in args.data:
        small = data.endswith("@64")
        scenes, _ = load_scenes(data.removesuffix("@64"), rt.image_size, views=8)
        for index, scene in enumerate(scenes):
            photos = list(scene.images if small else (getattr(scene, "photos", None)
                                                      or scene.images))
            truth = getattr(scene, "world_from_cam", None)
            truth = None if truth is None else np.linalg.inv(truth[0]) @ truth
            row = {"data": _shown(data), "scene": index} | scene_signals(rt, photos, truth,
                                                                 not args.no_solve)
            rows.append(row)
            print(json.dumps(row), flush=True)
    with open(args.out, "w") as f:
        json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
