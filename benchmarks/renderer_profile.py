"""Two renderer graphs side by side on the same feed: per-op-type share of node time (ONNX Runtime
profiling) and the median time of one call.

    python benchmarks/renderer_profile.py MODEL_DIR_A MODEL_DIR_B [--rays 4096 --samples 64
        --views 4 --runs 5 --threads 2 --json out.json]

``MODEL_DIR_A`` / ``MODEL_DIR_B`` are iris-export output directories of the same model (e.g.
``iris-export ckpt.pt a/`` and ``iris-export ckpt.pt b/ --renderer fast``); their field maps must
have the same shape (the feed is shared). The feed is seeded random data in the renderer's I/O
spec: field maps N(0, 1), grid coordinates in [-1.1, 1.1] (a few samples off the map), unit cues,
validity weights 1 with probability ``--valid`` (default 0.9: real scenes keep almost every sample) and,
for explicit-colour models, uniform colours. Sessions are created like ``IrisRuntime`` creates
them (``ORT_ENABLE_ALL``, sequential, ``--threads`` intra-op threads): one plain session for the
call times (one warm-up call, then ``--runs`` timed calls, interleaved A/B), and one with
profiling for the op shares (``--profile-runs`` calls after a warm-up; node events only).

Times are only meaningful on a quiet machine: check the load first (nothing here does).
Needs numpy and onnxruntime only (no torch).
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import onnxruntime as ort  # noqa: E402

from iris_runtime.manifest import read_manifest  # noqa: E402


def make_feed(manifest, rays: int, samples: int, views: int, valid: float, seed: int = 0) -> dict:
    """Seeded random renderer inputs for ``manifest``'s model (see the module docstring)."""
    rng = np.random.default_rng(seed)
    dims = manifest.raw["dims"]
    V, R, S = views, rays, samples
    f32 = np.float32
    unit = rng.standard_normal((V, R, S, 3))
    unit /= np.maximum(np.linalg.norm(unit, axis=-1, keepdims=True), 1e-6)
    feed = {
        "field_maps": rng.standard_normal((V, dims["C'"], dims["h"], dims["w"])).astype(f32),
        "grid": rng.uniform(-1.1, 1.1, (V, R, S, 2)).astype(f32),
        "cues": np.concatenate([unit, rng.uniform(-1, 1, (V, R, S, 1))], -1).astype(f32),
        "mask": (rng.random((V, R, S)) < valid).astype(f32),        # validity weights 0 / 1
        "positions": (rng.standard_normal((R, S, 3)) * 0.5).astype(f32),
        "directions": rng.standard_normal((R, 3)).astype(f32),
    }
    if manifest.explicit_rgb:
        feed["colours"] = rng.random((V, R, S, 3)).astype(f32)
    return feed


def session(path: Path, threads: int, profile_dir: str | None = None) -> ort.InferenceSession:
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3
    if profile_dir is not None:
        opts.enable_profiling = True
        opts.profile_file_prefix = str(Path(profile_dir) / "renderer")
    return ort.InferenceSession(str(path), opts, providers=["CPUExecutionProvider"])


def op_shares(path: Path, feed: dict, threads: int, runs: int) -> dict:
    """``{"shares": {op_type: fraction of node time}, "node_us": total per call, "nodes": n}``
    from ONNX Runtime's profile of ``runs`` calls (after one warm-up call)."""
    with tempfile.TemporaryDirectory() as tmp:
        sess = session(path, threads, tmp)
        for _ in range(runs + 1):                              # the first call is a warm-up
            sess.run(None, feed)
        events = json.loads(Path(sess.end_profiling()).read_text())
    calls = sorted((ev["ts"], ev["ts"] + ev["dur"]) for ev in events
                   if ev.get("cat") == "Session" and ev.get("name") == "model_run")
    warm_up_end = calls[0][1] if calls else 0
    per_op, nodes = collections.Counter(), set()
    for ev in events:
        if (ev.get("cat") != "Node" or not ev.get("name", "").endswith("_kernel_time")
                or ev["ts"] < warm_up_end):
            continue
        per_op[ev["args"].get("op_name", "?")] += ev["dur"]
        nodes.add(ev["name"])
    total = sum(per_op.values())
    return {"shares": {op: us / total for op, us in per_op.most_common()} if total else {},
            "node_us": total / max(runs, 1), "nodes": len(nodes)}


def call_times(paths: list[Path], feed: dict, threads: int, runs: int) -> list[list[float]]:
    sessions = [session(p, threads) for p in paths]
    for s in sessions:
        s.run(None, feed)                                      # warm-up
    times = [[] for _ in paths]
    for _ in range(runs):                                      # interleaved: drift hits both
        for i, s in enumerate(sessions):
            t0 = time.perf_counter()
            s.run(None, feed)
            times[i].append(time.perf_counter() - t0)
    return times


def _shown(path: Path) -> str:
    """``path`` as the results record it: relative to the repository where it lies inside it,
    else its name alone (results name no machine's directories)."""
    p, root = Path(path).resolve(), Path(__file__).resolve().parents[1]
    return p.relative_to(root).as_posix() if p.is_relative_to(root) else p.name


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model_dirs", nargs=2, metavar="MODEL_DIR")
    ap.add_argument("--rays", type=int, default=4096)
    ap.add_argument("--samples", type=int, default=64)
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--valid", type=float, default=0.9,
                    help="probability that a (view, sample) is valid")
    ap.add_argument("--runs", type=int, default=5, help="timed calls per graph")
    ap.add_argument("--profile-runs", type=int, default=3, help="profiled calls per graph")
    ap.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
    ap.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = ap.parse_args(argv)

    manifests = [read_manifest(d) for d in args.model_dirs]
    dims = [m.raw["dims"] for m in manifests]
    if dims[0] != dims[1] or manifests[0].explicit_rgb != manifests[1].explicit_rgb:
        ap.error(f"the two models take different renderer inputs ({dims[0]} vs {dims[1]}, "
                 f"explicit_rgb {manifests[0].explicit_rgb} vs {manifests[1].explicit_rgb})")
    paths = [m.graphs["renderer"].path for m in manifests]
    kinds = [m.raw.get("export", {}).get("renderer_graph", "reference") for m in manifests]
    feed = make_feed(manifests[0], args.rays, args.samples, args.views, args.valid)

    outs = [session(p, args.threads).run(None, feed) for p in paths]
    diff = max(float(np.abs(a - b).max()) for a, b in zip(*outs))
    times = call_times(paths, feed, args.threads, args.runs)
    profiles = [op_shares(p, feed, args.threads, args.profile_runs) for p in paths]

    names = [f"A ({kinds[0]})", f"B ({kinds[1]})"]
    print(f"feed: V'={args.views} R={args.rays} S={args.samples} valid={args.valid} "
          f"threads={args.threads}; max |A - B| over outputs = {diff:.2e}")
    med = [statistics.median(t) for t in times]
    print(f"{'':28s}{names[0]:>22s}{names[1]:>22s}")
    print(f"{'median call [s]':28s}{med[0]:22.4f}{med[1]:22.4f}   B/A = {med[1] / med[0]:.3f}")
    print(f"{'node time per call [s]':28s}{profiles[0]['node_us'] / 1e6:22.4f}"
          f"{profiles[1]['node_us'] / 1e6:22.4f}")
    print(f"{'nodes run':28s}{profiles[0]['nodes']:22d}{profiles[1]['nodes']:22d}")
    ops = sorted(set(profiles[0]["shares"]) | set(profiles[1]["shares"]),
                 key=lambda op: -max(p["shares"].get(op, 0.0) for p in profiles))
    print(f"{'op type: share of node time':28s}")
    for op in ops:
        a, b = (p["shares"].get(op) for p in profiles)
        cell = [f"{x * 100:21.1f}%" if x is not None else f"{'-':>22s}" for x in (a, b)]
        print(f"  {op:26s}{cell[0]}{cell[1]}")
    if args.json:
        args.json.write_text(json.dumps({
            "feed": {"views": args.views, "rays": args.rays, "samples": args.samples,
                     "valid": args.valid, "threads": args.threads},
            "max_abs_difference": diff,
            "graphs": [{"model_dir": _shown(d), "renderer_graph": k, "call_s": t,
                        "median_call_s": m, **p}
                       for d, k, t, m, p in zip(args.model_dirs, kinds, times, med, profiles)],
        }, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
