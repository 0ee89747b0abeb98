"""Can a refinement tell when it went wrong? The agreement between the starts of
``cameras="refined"`` per scene, each start's RPA, beside the solve: the evidence behind
``AgreementOptions.min_share`` (docs/CAMERAS.md, "Telling a wrong refinement").

    python scripts/refine_signals.py MODEL_DIR out.json synthetic:heldout@64 \\
        synthetic:capture-heldout data/real/castle data/real/castel data/real/cube

Each DATA is an iris-eval set (``@64``: the model's 64x64 images as the photos, as
``benchmarks/encode_cost.py --heldout`` gives them). All 8 frames of every scene are encoded
with ``cameras="refined"`` through the runtime's public entry point: as shipped, recording the
values ``refine.confirm.agreement`` returns to the check (the best-ranked start's cameras against
each other start's, until one reaches ``min_share``), where none does, the salvage (``"core"``:
the views of the largest set another start agrees with it on; ``"salvaged"``: the views it
posed, 0 where the set was too small), where that failed too, what the witness mapping did
(``"witness"``: "confirmed a start", "salvaged N views", "none" or "no mapping"), the source and
the seconds; then with ``min_share = 0`` (the chosen
start's cameras, whatever the check says) and with ``StartOptions.kinds`` one start at a time (each start's
own end; a start that leaves view 0 unposed is handed to the solve by the runtime and has no
RPA of its own). Where the set has true cameras: RPA@15 of each, of the cameras as shipped and
of the solve (``"solve"``, unless ``--no-solve``).
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from iris_runtime import IrisRuntime
from iris_runtime.cameras.refine import confirm as C
from iris_runtime.cameras.refine import ladder as L
from iris_runtime.cameras.refine import salvage as S
from iris_runtime.cameras.refine import witness as W
from iris_train.evaluate.scenes import load_scenes
from refine_probe import rpa15 as rpa


def scene_signals(rt: IrisRuntime, photos, truth, solve: bool) -> dict:
    shipped = L.DEFAULTS, C.agreement, S.salvage_agreed_views, C.agreeing_views
    witnessed_as_shipped = W.witness_verdict
    seen: list[float] = []
    salvaged: list[int] = []
    core = [0]
    witness: list[str] = []

    def witnessed(best, ends, mapped, *rest):
        rec = witnessed_as_shipped(best, ends, mapped, *rest)
        witness.append("no mapping" if mapped is None else "none" if rec is None
                       else "confirmed a start" if any(rec is e for e in (best, *ends))
                       else f"salvaged {int(rec.registered.sum())} views")
        return rec

    def views(*args):
        out = shipped[3](*args)
        core[0] = max(core[0], int(out.sum()))
        return out

    def recorded(*args):
        seen.append(shipped[1](*args))
        return seen[-1]

    def salvage(*args):
        rec = shipped[2](*args)
        salvaged.append(0 if rec is None else int(rec.registered.sum()))
        return rec

    C.agreement, S.salvage_agreed_views, C.agreeing_views = recorded, salvage, views
    W.witness_verdict = witnessed
    try:
        t0 = time.perf_counter()
        as_shipped = rt.encode(photos, cameras="refined")
        row = {"refined_seconds": time.perf_counter() - t0, "source": as_shipped.camera_source,
               "agreement": list(seen),
               **({"core": core[0], "salvaged": salvaged[0]} if salvaged else {}),
               **({"witness": witness[0]} if witness else {})}
        S.salvage_agreed_views, W.witness_verdict = shipped[2], witnessed_as_shipped
        unchecked = replace(shipped[0], agreement=replace(shipped[0].agreement, min_share=0.0))
        L.DEFAULTS = unchecked
        chosen = rt.encode(photos, cameras="refined")
        ends = {}
        for kind in shipped[0].starts.kinds:
            L.DEFAULTS = replace(unchecked, starts=replace(unchecked.starts, kinds=(kind,)))
            ends[kind] = rt.encode(photos, cameras="refined")
    finally:
        L.DEFAULTS, C.agreement, S.salvage_agreed_views, C.agreeing_views = shipped
        W.witness_verdict = witnessed_as_shipped
    if truth is not None:
        row["refined_rpa@15"] = rpa(as_shipped.world_from_cam, truth)
        if chosen.camera_source == "refined":
            row["chosen_rpa@15"] = rpa(chosen.world_from_cam, truth)
        row["rpa@15"] = {k: rpa(e.world_from_cam, truth) for k, e in ends.items()
                         if e.camera_source == "refined"}
    if solve:
        t0 = time.perf_counter()
        solved = rt.encode(photos, cameras="solve")
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
