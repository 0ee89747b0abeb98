"""The runtime's geometric cue in numpy: ``iris_runtime.geometry``'s written-out 3-vector norms
and dot products against the ``np.linalg.norm`` / ``.sum(-1)`` form they replaced, on one
renderer call's points (the facts behind ``geometry._dot3``).

    python benchmarks/cue_numpy.py [--rays 102 --samples 64 --views 5 --runs 100]

Checks that both give the same cues and view alignments bit for bit, then prints the median
(and min) milliseconds per call of each. Needs numpy only.
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from iris_runtime import geometry as G  # noqa: E402


def cue_with_reductions(points, target_centre, source_centres, eps=G.NORM_EPS,
                        cue_eps=G.CUE_EPS):
    """The form before ``_dot3``: numpy's norm and sum over the last axis."""
    t = np.asarray(target_centre, points.dtype) - points
    t = t / np.maximum(np.linalg.norm(t, axis=-1, keepdims=True), eps)
    s = source_centres.astype(points.dtype) - points[..., None, :]
    s_norm = np.maximum(np.linalg.norm(s, axis=-1, keepdims=True), eps)
    align = (s * t[..., None, :]).sum(-1) / s_norm[..., 0]
    s = s / s_norm
    diff = t[..., None, :] - s
    diff = diff / np.maximum(np.linalg.norm(diff, axis=-1, keepdims=True), cue_eps)
    dot = (t[..., None, :] * s).sum(-1, keepdims=True)
    return np.concatenate([diff, dot], axis=-1), align


def cue_runtime(points, target_centre, source_centres):
    t, s, s_norm = G.cue_vectors(points, target_centre, source_centres)
    return G.cue_from_vectors(t, s, s_norm), G.cue_alignment(t, s, s_norm)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rays", type=int, default=102)
    ap.add_argument("--samples", type=int, default=64)
    ap.add_argument("--views", type=int, default=5)
    ap.add_argument("--runs", type=int, default=100)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    points = rng.standard_normal((args.rays, args.samples, 3)).astype(np.float32)
    target, sources = np.array([0.1, 0.2, -2.0]), rng.standard_normal((args.views, 3))
    want, got = (f(points, target, sources) for f in (cue_with_reductions, cue_runtime))
    same = all(np.array_equal(a, b) for a, b in zip(want, got))
    print(f"points [{args.rays}, {args.samples}, 3], {args.views} views; bit for bit the same: "
          f"{same}")
    for name, f in (("np.linalg.norm / .sum(-1)", cue_with_reductions),
                    ("geometry (written out)", cue_runtime)):
        times = []
        for _ in range(args.runs):
            t = time.perf_counter()
            f(points, target, sources)
            times.append(time.perf_counter() - t)
        print(f"  {name:28s} {statistics.median(times) * 1e3:6.2f} ms ({min(times) * 1e3:.2f})")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
