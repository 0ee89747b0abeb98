"""How many rays per renderer call? Time per ray and peak memory of IrisRuntime.render against the
chunk size, expressed as the work budget R * S * V (rays x samples x reference views).

Each (views, budget) point runs in a fresh process (peak RSS is per process): encode V random
images, render one 48x48 view (2304 rays) near view 0 with ``chunk_rays = budget // (S * V)``,
after a one-ray warm-up render (sessions created, first-run costs paid). Reported: CPU seconds
per 1000 rays (``time.process_time``, 1 intra-op thread, so it is robust to other load on the
machine), wall seconds per 1000 rays, and the peak RSS increase over the process after the
warm-up (what the chunk costs).

    python benchmarks/runtime_chunks.py MODEL_DIR                   # an iris-export output
    python benchmarks/runtime_chunks.py --json benchmarks/results/runtime_chunks.json MODEL_DIR
"""
from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BUDGETS = (8 * 1024, 32 * 1024, 128 * 1024, 512 * 1024)
VIEWS = (2, 4, 8)

_CHILD = r"""
import json, resource, sys, time
import numpy as np
sys.path.insert(0, sys.argv[1])
from iris_runtime import IrisRuntime
model_dir, V, budget = sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
rt = IrisRuntime(model_dir, threads=1)
rng = np.random.default_rng(0)
H, W = rt.image_size
scene = rt.encode([rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(V)], cameras="model")
pose = np.eye(4); pose[:3, 3] = [0.02, -0.01, 0.03]
chunk = max(1, budget // (rt.samples * V))
rt.render(scene, pose, height=1, width=1)               # sessions, first-run costs
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
c0, w0 = time.process_time(), time.perf_counter()
res = rt.render(scene, pose, height=48, width=48, chunk_rays=chunk, depth=True)
c1, w1 = time.process_time(), time.perf_counter()
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"views": V, "budget": budget, "chunk_rays": chunk,
                  "cpu_s_per_1k_rays": (c1 - c0) / 2.304, "wall_s_per_1k_rays": (w1 - w0) / 2.304,
                  "renderer_share": res.timings["renderer"] / res.timings["total"],
                  "peak_rss_increase_mb": max(0, peak - base) / 1024.0}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("model_dir")
    ap.add_argument("--json", type=Path, help="also write the rows here")
    ap.add_argument("--views", type=int, nargs="+", default=list(VIEWS))
    ap.add_argument("--budgets", type=int, nargs="+", default=list(BUDGETS))
    args = ap.parse_args()
    rows = []
    print(f"{'V':>2} {'R*S*V':>7} {'rays':>5} {'cpu s/1k':>9} {'wall s/1k':>9} {'ORT %':>6} "
          f"{'+RSS MB':>8}")
    for V in args.views:
        for budget in args.budgets:
            out = subprocess.run([sys.executable, "-c", _CHILD, str(REPO), args.model_dir, str(V),
                                  str(budget)], capture_output=True, text=True, check=True)
            row = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append(row)
            print(f"{V:>2} {budget:>7} {row['chunk_rays']:>5} {row['cpu_s_per_1k_rays']:>9.3f} "
                  f"{row['wall_s_per_1k_rays']:>9.3f} {100 * row['renderer_share']:>6.1f} "
                  f"{row['peak_rss_increase_mb']:>8.0f}", flush=True)
    if args.json:
        manifest = json.loads((Path(args.model_dir) / "iris.json").read_text())
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({
            "machine": f"{platform.machine()}, {platform.processor() or '?'}, python "
                       f"{platform.python_version()}",
            "model": {k: manifest.get(k) for k in ("image_size", "field_channels", "samples")},
            "threads": 1, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
