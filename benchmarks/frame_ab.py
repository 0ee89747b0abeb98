"""Two exports of the same model, whole frames side by side: the runtime's seconds per frame with
each, interleaved (A, B, A, B, ...) so that both see the same machine state.

    python benchmarks/frame_ab.py MODEL_DIR_A MODEL_DIR_B [--runs 8 --threads 2 --workers 2]

Held-out scene ``HELDOUT_SEEDS[0]``: all 8 frames encoded (``cameras="model"``), the first target
of ``evaluate.split_frames`` rendered from the references at its predicted pose, as the knobs
part of ``benchmarks/error_vs_time.py`` does. Prints the largest pixel difference between the two
renders and the median (and min) seconds per frame of each. Frame-level times drift by 10-20 %
over minutes on these machines; only the interleaved ratio compares. Needs the [train] extra
(the held-out scene is rendered by ``iris_train.data``).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402


def main(argv=None) -> int:
    from iris_runtime import IrisRuntime
    from iris_train.data import HELDOUT_SEEDS, SyntheticScenes
    from iris_train.evaluate import split_frames

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model_dirs", nargs=2, type=Path)
    ap.add_argument("--runs", type=int, default=8)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    scene = SyntheticScenes([HELDOUT_SEEDS[0]], n_views=8)[0]
    refs, targets = (list(x) for x in split_frames(8))
    runs = []
    for d in args.model_dirs:
        rt = IrisRuntime(d, threads=args.threads, workers=args.workers)
        encoded = rt.encode(list(scene.images), cameras="model")
        runs.append((rt, encoded.subset(refs), encoded.world_from_cam[targets[0]]))
    images = [rt.render(sub, pose, depth=True).image_float for rt, sub, pose in runs]  # warm-up
    print(f"max |A - B| = {float(np.abs(images[0] - images[1]).max()):.2e}")
    times = [[] for _ in runs]
    for _ in range(args.runs):
        for i, (rt, sub, pose) in enumerate(runs):
            t = time.perf_counter()
            rt.render(sub, pose)
            times[i].append(time.perf_counter() - t)
    for d, ts in zip(args.model_dirs, times):
        print(f"{str(d):40s} median {statistics.median(ts):.3f} s/frame (min {min(ts):.3f})")
    print(f"A/B ratio of medians: {statistics.median(times[0]) / statistics.median(times[1]):.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
