"""The camera solve with one setting changed, on the datasets of ``benchmarks/camera_solve.py``:
the study behind the choices in docs/CAMERAS.md ("Choices").

    python scripts/camera_study.py                                      # the defaults
    python scripts/camera_study.py --set features.CONTRAST_THRESHOLD=0.04
    python scripts/camera_study.py --set max_error=2.0 --set ba_points=250
    python scripts/camera_study.py --set solve.FOCAL_PRIORS=1.2,0.8,1.8 --datasets heldout

``--set MODULE.NAME=VALUE`` changes a constant of ``iris_runtime.cameras.MODULE`` (in every
module of the package that holds that name, as imported names are copies); ``--set
refine.STAGE.FIELD=VALUE`` a field of one stage of the refinement's settings
(``refine.RefineOptions``, e.g. ``refine.adjust.tolerance=1e-6``); ``--set FIELD=VALUE`` a field
of ``MapperOptions``. Prints, per dataset and protocol, the means of RPA@5/15/30 over the
scenes and the median seconds.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

# The settings live with the benchmarks, which take the same --set; imported here
# for scripts/refine_signals.py too (from camera_study import apply).
from benchmarks.camera_settings import apply  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", action="append", default=[], metavar="NAME=VALUE")
    ap.add_argument("--datasets", default="heldout,castle")
    ap.add_argument("--protocol", default="all,eval")
    args = ap.parse_args(argv)
    import cv2

    import benchmarks.camera_solve as B
    import iris_runtime.cameras as C
    cv2.setNumThreads(1)
    options = apply(args.set)
    solve = C.solve_cameras

    def with_options(photos, depth_range, **kw):
        return solve(photos, depth_range, options=options, **kw)
    C.solve_cameras = with_options                      # what the benchmark's solvers call
    for dataset in args.datasets.split(","):
        scenes = list(B.DATASETS[dataset]())
        for protocol in args.protocol.split(","):
            rows = [B.score(*B.solve_ours(s.photos), s) if protocol == "all"
                    else B.eval_protocol(s) for s in scenes]
            means = {k: round(float(np.mean([r[k] for r in rows])), 3)
                     for k in ("rpa@5", "rpa@15", "rpa@30")}
            print(f"{dataset} {protocol}: {means}, median "
                  f"{np.median([r['seconds'] for r in rows]):.2f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
