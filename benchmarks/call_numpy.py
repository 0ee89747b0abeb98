"""The runtime's per-call numpy against the forms it replaced, on one renderer call's points:

- the geometric cue: ``iris_runtime.geometry``'s written-out 3-vector norms and dot products
  against the ``np.linalg.norm`` / ``.sum(-1)`` form (the facts behind ``geometry._dot3``);
- the explicit-colour photos' RGB at the samples: ``geometry.sample_taps`` (one gather of a
  cell's four taps, channel-major) against ``sample_bilinear`` per view (four row gathers).

    python benchmarks/call_numpy.py [--rays 102 --samples 64 --views 5 --runs 100]

Checks that each pair gives the same values bit for bit, then prints the median (and min)
milliseconds per call of each, interleaved. Needs numpy only.
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


def photos_per_view(photos, grid):
    """The form before ``sample_taps``: ``sample_bilinear`` of each view."""
    return np.stack([G.sample_bilinear(photos[k], grid[k]) for k in range(len(photos))])


def timed(pairs: dict, runs: int) -> dict:
    """Median and min seconds of each ``name -> (f, args)``, the calls interleaved."""
    times = {name: [] for name in pairs}
    for _ in range(runs):
        for name, (f, args) in pairs.items():
            t = time.perf_counter()
            f(*args)
            times[name].append(time.perf_counter() - t)
    return {name: (statistics.median(ts), min(ts)) for name, ts in times.items()}


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
    photos = rng.random((args.views, 3, 64, 64), dtype=np.float32)
    grid = rng.uniform(-1.05, 1.05, (args.views, args.rays, args.samples, 2)).astype(np.float32)
    taps = G.bilinear_taps(photos)
    cases = {
        "cue": {"np.linalg.norm / .sum(-1)": (cue_with_reductions, (points, target, sources)),
                "geometry (written out)": (cue_runtime, (points, target, sources))},
        "photo RGB [3, 64, 64]": {
            "sample_bilinear per view": (photos_per_view, (photos, grid)),
            "sample_taps": (G.sample_taps, (taps, (64, 64), grid))},
    }
    print(f"points [{args.rays}, {args.samples}, 3], {args.views} views")
    ok = True
    for case, pairs in cases.items():
        want, got = (f(*a) for f, a in pairs.values())
        same = all(np.array_equal(a, b) for a, b in zip(want, got)) if case == "cue" \
            else np.array_equal(want, got)
        ok &= bool(same)
        print(f"{case}: bit for bit the same: {same}")
        for name, (med, low) in timed(pairs, args.runs).items():
            print(f"  {name:28s} {med * 1e3:6.2f} ms ({low * 1e3:.2f})")
    print(f"  (taps of the photos, once per render: "
          f"{timed({'t': (G.bilinear_taps, (photos,))}, args.runs)['t'][0] * 1e3:.2f} ms)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
