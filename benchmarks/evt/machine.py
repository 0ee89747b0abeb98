"""What the machine and the renderer graph can do: versions, matmul peak, FLOPs, ORT profile."""
from __future__ import annotations

import json
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

#: tcmalloc, preloaded into the second torch anchor (torch's default allocator makes its time vary
#: from run to run).
TCMALLOC = "/usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4"


def machine_facts(threads: int) -> dict:
    import onnxruntime as ort
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    facts = {"date_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()), "cpu": cpu,
             "logical_cpus": os.cpu_count(), "usable_cpus": len(os.sched_getaffinity(0)),
             "threads": threads, "onnxruntime": ort.__version__, "numpy": np.__version__,
             "python": platform.python_version(), "load_avg_start": os.getloadavg(),
             "tcmalloc": TCMALLOC if Path(TCMALLOC).exists() else None}
    try:
        import torch
        facts["torch"] = torch.__version__
    except ImportError:
        facts["torch"] = None
    return facts


def matmul_peak(n: int = 4096, runs: int = 3) -> dict:
    """float32 GFLOP/s of one large numpy matmul (median of ``runs`` after a warm-up)."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((n, n), dtype=np.float32)
    b = rng.standard_normal((n, n), dtype=np.float32)
    a @ b
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        a @ b
        times.append(time.perf_counter() - t)
    med = statistics.median(times)
    return {"n": n, "seconds": times, "gflops": 2 * n ** 3 / med / 1e9}


def best_peak(measurements: list[dict]) -> dict:
    """The fastest of several ``matmul_peak`` measurements (the machine's speed drifts by 10-30 %
    over minutes here; the highest peak is the hardest denominator), with every measurement's
    GFLOP/s under ``"measurements"``."""
    best = max(measurements, key=lambda m: m["gflops"])
    return {**best, "measurements": [m["gflops"] for m in measurements]}


def renderer_flops(cfg: dict, work: dict) -> float:
    """Multiply-add FLOPs (2 per MAC) of the renderer graph for the calls summarised in ``work``
    (``RenderResult.work``). Matmul-like work only (sampling matmul, linear layers, attention
    products); norms, activations and softmax are left out (a few % at these widths)."""
    W = cfg["field_width"]
    C = W * (1 + 2 * cfg["view_blocks"])
    hw = (cfg["image_height"] // cfg["patch_size"]) * (cfg["image_width"] // cfg["patch_size"])
    P = 3 * (1 + 2 * cfg["pos_freqs"]) + 3 * (1 + 2 * cfg["dir_freqs"])
    hidden = int(W * cfg["mlp_ratio"])
    Bv, Br = cfg["view_blocks"], cfg["ray_blocks"]
    mlp = 4 * W * hidden
    per_point_view = 2 * hw * C + Bv * (2 * 4 * 2 * W + 4 * W)      # dense sampling, cue->kv, logits+sum
    per_point = Bv * (4 * W * W + mlp) + Br * (2 * P * W + 8 * W * W + mlp)
    per_ray_pair = Br * 4 * W                                       # QK^T and AV
    per_ray = 2 * (W * W + 3 * W)
    return (per_point_view * work["point_views"] + per_point * work["points"]
            + per_ray_pair * work["ray_pairs"] + per_ray * work["rays"])


#: ONNX Runtime ops that run subgraphs: the profiler reports their kernel time including the
#: nodes they run, and reports those nodes again under their own op types.
CONTAINER_OPS = ("If", "Scan", "Loop")


def node_shares(shares: list) -> list[tuple[str, float]]:
    """``ort_profile``'s raw ``shares`` without the container ops (``CONTAINER_OPS``), renormalised:
    each node's time counted once."""
    kept = [(op, share) for op, share in shares if op not in CONTAINER_OPS]
    total = sum(share for _, share in kept) or 1.0
    return [(op, share / total) for op, share in kept]


def ort_profile(rt, scene, pose, threads: int) -> dict:
    """Per-op-type share of ORT node time for one exact render (ORT's built-in profiler).

    The runtime has no profiling switch, so its renderer session is swapped for a profiling one
    for this one render (``IrisRuntime._sessions``: a private attribute, on purpose confined to
    this function)."""
    import onnxruntime as ort
    from iris_runtime.manifest import read_graph_bytes
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.enable_profiling = True
    with tempfile.TemporaryDirectory() as tmp:
        opts.profile_file_prefix = str(Path(tmp) / "prof")
        sess = ort.InferenceSession(read_graph_bytes(rt.manifest.graphs["renderer"]), opts,
                                    providers=["CPUExecutionProvider"])
        saved = rt._sessions.get("renderer")
        rt._sessions["renderer"] = sess
        try:
            rt.render(scene, pose)
        finally:
            if saved is not None:
                rt._sessions["renderer"] = saved
            else:
                rt._sessions.pop("renderer")
        prof = sess.end_profiling()
        events = json.loads(Path(prof).read_text())
    by_op: dict[str, float] = {}
    for e in events:
        if e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time"):
            op = e.get("args", {}).get("op_name", "?")
            by_op[op] = by_op.get(op, 0.0) + e.get("dur", 0)
    total = sum(by_op.values()) or 1.0
    shares = sorted(((op, d / total) for op, d in by_op.items()), key=lambda x: -x[1])
    # Raw: container ops included (``node_shares`` drops them for the report).
    return {"shares": shares, "note": "one 64x64 frame, first held-out scene"}
