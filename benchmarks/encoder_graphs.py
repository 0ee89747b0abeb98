"""What each encoder graph of an exported model costs: ``encoder`` (field maps and cameras) and,
where the model has it, ``encoder_cameras`` (the camera head on its own encoder), run on the same
random views at the model's resolution, all of them references, one thread, alternately.
Reports each graph's median milliseconds over ``--runs`` and whether their cameras are equal bit
for bit.

    python benchmarks/encoder_graphs.py MODEL_DIR [--views 8] [--runs 30] [--json out.json]

Runtime dependencies only (no torch).
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


def measure(model_dir: str, views: int, runs: int) -> dict:
    import numpy as np

    from iris_runtime import IrisRuntime
    from iris_runtime.io_spec import FOCAL, IMAGES, IS_REFERENCE, WORLD_FROM_CAM
    rt = IrisRuntime(model_dir, threads=1)
    H, W = rt.image_size
    feed = {IMAGES: np.random.default_rng(0).random((views, 3, H, W), dtype=np.float32),
            IS_REFERENCE: np.ones(views, bool)}
    graphs = [g for g in ("encoder", "encoder_cameras") if g in rt.manifest.graphs]
    sessions = {g: rt._session(g) for g in graphs}
    outputs = {g: [o.name for o in sessions[g].get_outputs()] for g in graphs}
    ms = {g: [] for g in graphs}
    for g in graphs:                                  # warm up
        sessions[g].run(outputs[g], feed)
    for run in range(runs):
        for g in (graphs if run % 2 == 0 else graphs[::-1]):
            t0 = time.perf_counter()
            sessions[g].run(outputs[g], feed)
            ms[g].append(1e3 * (time.perf_counter() - t0))
    res = {"views": views, "runs": runs, "load_before": list(os.getloadavg()),
           "median_ms": {g: statistics.median(ms[g]) for g in graphs}}
    if "encoder_cameras" in sessions:
        full = sessions["encoder"].run([WORLD_FROM_CAM, FOCAL], feed)
        cams = sessions["encoder_cameras"].run([WORLD_FROM_CAM, FOCAL], feed)
        res["cameras_equal"] = all(np.array_equal(a, b) for a, b in zip(full, cams))
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model_dir")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--runs", type=int, default=30)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    res = measure(args.model_dir, args.views, args.runs)
    print(json.dumps(res))
    if args.json is not None:
        from iris_runtime.fileio import atomic_write_bytes
        atomic_write_bytes(args.json, json.dumps(res, indent=1).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
