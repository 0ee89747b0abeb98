"""Two exports of the same model, call by call on the renderer inputs of real frames: what one
graph change is worth per call, without the 10-20 % drift of whole-frame times.

    python benchmarks/call_ab.py MODEL_DIR_A MODEL_DIR_B [--scenes 1 --reps 3]

The feeds are the ones ``IrisRuntime(MODEL_DIR_A)`` gives its renderer (exact path, culling on)
for the targets of ``evaluate.split_frames`` of the first ``--scenes`` held-out scenes, all 8
frames encoded (``cameras="model"``), 64x64, as the knobs part of
``benchmarks/error_vs_time.py`` renders them. Each call is then run on both renderer graphs (one
intra-op thread, as the runtime's 2-worker mode runs them), alternating A and B call by call,
``--reps`` times. Prints the largest output difference, the share of calls and rays whose every
sample has full weight (the calls whose ray attentions need no key bias), and the median of the
per-call time ratios B / A and the ratio of the summed times. Needs the [train] extra (the
held-out scenes are rendered by ``iris_train.data``).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402


def capture_feeds(model_dir: str, scenes: int) -> list[dict[str, np.ndarray]]:
    """The renderer feeds of the exact renders of ``scenes`` held-out scenes' targets."""
    from iris_runtime import IrisRuntime
    from iris_train.data import HELDOUT_SEEDS, SyntheticScenes
    from iris_train.evaluate import split_frames
    rt = IrisRuntime(model_dir, workers=1)
    session, feeds = rt._session("renderer"), []

    class Recorder:                     # IrisRuntime has no hook for its feeds: wrap the session
        def run(self, names, feed):
            feeds.append({k: np.array(v) for k, v in feed.items()})
            return session.run(names, feed)

        def __getattr__(self, name):
            return getattr(session, name)

    rt._sessions["renderer"] = Recorder()
    refs, targets = split_frames(8)
    data = SyntheticScenes(list(HELDOUT_SEEDS)[:scenes], n_views=8)
    for i in range(scenes):
        encoded = rt.encode(list(data[i].images), cameras="model")
        sub = encoded.subset(list(refs))
        for t in targets:
            rt.render(sub, encoded.world_from_cam[t])
    return feeds


def session(model_dir: str):
    import onnxruntime as ort
    from iris_runtime.manifest import read_graph_bytes, read_manifest
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    return ort.InferenceSession(read_graph_bytes(read_manifest(model_dir).graphs["renderer"]),
                                opts, providers=["CPUExecutionProvider"])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model_dir_a")
    ap.add_argument("model_dir_b")
    ap.add_argument("--scenes", type=int, default=1)
    ap.add_argument("--reps", type=int, default=3)
    args = ap.parse_args(argv)
    feeds = capture_feeds(args.model_dir_a, args.scenes)
    full = [bool((f["mask"].max(axis=0) == 1).all()) for f in feeds]
    rays = [f["mask"].shape[1] for f in feeds]
    print(f"{len(feeds)} calls; every sample at full weight in {sum(full)} calls, "
          f"{sum(r for r, k in zip(rays, full) if k) / sum(rays):.1%} of the rays", flush=True)
    a, b = session(args.model_dir_a), session(args.model_dir_b)
    diff = max(float(np.abs(x - y).max()) for f in feeds
               for x, y in zip(a.run(None, f), b.run(None, f)))
    print(f"max |A - B| over every output: {diff:.2e}", flush=True)
    times: tuple[list[float], list[float]] = ([], [])
    for rep in range(args.reps):
        for f in feeds:
            for s, ts in zip((a, b), times):
                t = time.perf_counter()
                s.run(None, f)
                ts.append(time.perf_counter() - t)
        print(f"  rep {rep + 1}/{args.reps}", flush=True)
    ratios = [tb / ta for ta, tb in zip(*times)]
    print(f"B / A per call: median {statistics.median(ratios):.3f}; summed time "
          f"{sum(times[1]) / sum(times[0]):.3f} ({sum(times[0]) / args.reps:.2f} vs "
          f"{sum(times[1]) / args.reps:.2f} s of graph per pass over the calls)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
