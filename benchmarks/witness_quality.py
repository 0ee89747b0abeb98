"""How good the refinement's witness mapping (``refine.witness.witness_mapping``) is, on every
scene rather than on the few that reach it: each scene's refinement runs to its first question to the witness
with no start confirmed and no salvage on the starts, and there the witness maps the scene once
per setting. Per setting and scene set: the views it registers, its RPA@5 and RPA@15 against the
true cameras over the pairs it poses (the witness's cameras are judged at 5 degrees,
``AgreementOptions.degrees``), the scenes on which it is worse or better at 5 degrees than the
first setting, and its seconds (one thread, summed over the set).

    python benchmarks/witness_quality.py MODEL_DIR \
        --witness ba_iterations=10,final_ba_iterations=50 \
        --witness ba_iterations=5,final_ba_iterations=20 --json out.json

``--witness`` takes ``MapperOptions`` fields that replace the witness's own (those
``witness_mapping`` sets, ``WitnessOptions.iterations`` among them); the first is the reference. The
scenes: all four sets of ``refine_cost.py`` (validation 0-23 and 24-47 to choose on, the held-out
scenes as made and as iris-eval resizes them to check). Needs the [train] extra.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

SETS = ("validation", "validation-more", "heldout", "eval-heldout")


class _Asked(Exception):
    """Raised once the witness has been asked: the scene's refinement ends there."""


def _options(text: str) -> dict:
    """``FIELD=VALUE,...`` -> ``MapperOptions`` fields, each of its default's type."""
    from iris_runtime.cameras import MapperOptions
    from benchmarks.camera_settings import parse_value
    fields = dict(item.split("=", 1) for item in text.split(",") if item)
    return {name: parse_value(value, getattr(MapperOptions(), name))
            for name, value in fields.items()}


def measure(model_dir: str, settings: list[dict]) -> dict:
    import cv2
    import numpy as np

    from benchmarks.camera_solve import SETS_64, pair_errors
    from iris_runtime.cameras.refine import ladder, witness as witness_stage
    from iris_runtime import IrisRuntime
    cv2.setNumThreads(1)
    # No start confirms and none is salvaged, so every scene asks the witness.
    shipped = ladder.DEFAULTS
    ladder.DEFAULTS = dataclasses.replace(
        shipped, agreement=dataclasses.replace(shipped.agreement, min_share=1.01),
        salvage=dataclasses.replace(shipped.salvage, min_core_views=10 ** 6))
    witness, canonical_order = witness_stage.witness_mapping, ladder.canonical_order
    incremental_mapping = witness_stage.incremental_mapping
    scene = {}

    def ordered(photos):
        scene["perm"] = canonical_order(photos)
        return scene["perm"]

    def asked(evidence, focal, opts, useful, stages):
        truth = scene["truth"][scene["perm"]]
        for k, setting in enumerate(settings):
            t0 = time.perf_counter()
            scene["setting"] = setting
            mapped = witness(evidence, focal, opts, useful, stages)
            seconds = time.perf_counter() - t0
            row = {"registered": 0, "rpa@5": 0.0, "rpa@15": 0.0, "seconds": seconds}
            if mapped is not None:
                cam = np.tile(np.eye(4), (len(mapped.R), 1, 1))
                cam[:, :3, :3], cam[:, :3, 3] = mapped.R, mapped.t
                errors = pair_errors(np.linalg.inv(cam), truth)
                i, j = np.triu_indices(len(cam), 1)
                posed = mapped.registered[i] & mapped.registered[j]
                row.update(registered=int(mapped.registered.sum()),
                           **{f"rpa@{d}": float(np.mean(errors[posed] < d)) if posed.any()
                              else 0.0 for d in (5, 15)})
            scene["rows"][k].append(row)
        raise _Asked

    def mapping(*args):
        *head, opts = args
        return incremental_mapping(*head, dataclasses.replace(opts, **scene["setting"]))

    witness_stage.witness_mapping, ladder.canonical_order = asked, ordered
    witness_stage.incremental_mapping = mapping
    rt = IrisRuntime(model_dir, threads=1)
    out = {"settings": settings, "load_before": list(os.getloadavg()), "sets": {}}
    for name in SETS:
        scene["rows"] = [[] for _ in settings]
        names = []
        for s in SETS_64[name]():
            scene["truth"] = s.world_from_cam
            try:
                rt.encode(s.photos, cameras="refined")
            except _Asked:
                names.append(s.name.split(" (")[0])
        rows = scene["rows"]
        summary = []
        for k, setting in enumerate(settings):
            at5 = np.array([r["rpa@5"] for r in rows[k]])
            ref5 = np.array([r["rpa@5"] for r in rows[0]])
            summary.append({
                "witness": setting, "scenes": len(rows[k]),
                "registered": float(np.mean([r["registered"] for r in rows[k]])),
                "rpa@5": float(at5.mean()),
                "rpa@15": float(np.mean([r["rpa@15"] for r in rows[k]])),
                "worse@5": int((at5 < ref5 - 1e-9).sum()),
                "better@5": int((at5 > ref5 + 1e-9).sum()),
                "seconds": float(sum(r["seconds"] for r in rows[k]))})
            s = summary[-1]
            print(f"{name:16s} {json.dumps(setting):50s} scenes {s['scenes']:2d} registered "
                  f"{s['registered']:.2f} RPA@5 {s['rpa@5']:.3f} RPA@15 {s['rpa@15']:.3f} "
                  f"worse/better@5 {s['worse@5']}/{s['better@5']} {s['seconds']:.2f} s",
                  flush=True)
        out["sets"][name] = {"scenes": names, "rows": rows, "summary": summary}
    out["load_after"] = list(os.getloadavg())
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model_dir")
    ap.add_argument("--witness", action="append", type=_options, default=[],
                    metavar="FIELD=VALUE,...", help="MapperOptions fields of the witness; the "
                    "first is the reference (default: the shipped witness alone)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    res = measure(args.model_dir, args.witness or [{}])
    if args.json is not None:
        from iris_runtime.fileio import atomic_write_bytes
        atomic_write_bytes(args.json, json.dumps(res, indent=1).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
