"""Per-point top-k on the renderer that takes each point's own views (``renderer_views``) against
the view-major renderer with the other views masked, end to end through ``IrisRuntime``.

    python benchmarks/selected_views.py MODEL_DIR [--views 5,16 --top-k 2,4 --runs 3]

``MODEL_DIR``: an iris-export output with ``renderer_views.onnx`` (the default "fast" renderer
graphs). The masked side is a copy of it without that graph (a temporary directory). First
held-out scene, ``--views`` references (+ 1 target), 64x64, camera-head cameras; per (views, k):
max abs difference of the two renders, the (point, view) pairs fed, and the median seconds of the
whole render and of the renderer graph (interleaved runs). Quiet machine only.
"""
from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from iris_runtime import IrisRuntime  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model_dir", type=Path)
    ap.add_argument("--views", default="5,16")
    ap.add_argument("--top-k", default="2,4")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    from iris_train.data import HELDOUT_SEEDS, SyntheticScenes
    with tempfile.TemporaryDirectory() as tmp:
        plain = Path(tmp) / "masked"
        shutil.copytree(args.model_dir, plain)
        doc = json.loads((plain / "iris.json").read_text())
        (plain / doc["graphs"].pop("renderer_views")["file"]).unlink()
        (plain / "iris.json").write_text(json.dumps(doc))
        rts = {"selected": IrisRuntime(args.model_dir, threads=args.threads),
               "masked": IrisRuntime(plain, threads=args.threads)}
        for nv in (int(v) for v in args.views.split(",")):
            sc = SyntheticScenes([HELDOUT_SEEDS[0]], n_views=nv + 1)[0]
            enc = rts["selected"].encode(list(sc.images), cameras="model")
            scene, pose = enc.subset([i for i in range(nv + 1) if i != 1]), enc.world_from_cam[1]
            for k in (int(x) for x in args.top_k.split(",")):
                kw = dict(top_k=k, top_k_by="point", depth=True)
                first = {n: rt.render(scene, pose, **kw) for n, rt in rts.items()}
                wall = {n: [] for n in rts}
                graph = {n: [] for n in rts}
                for _ in range(args.runs):
                    for n, rt in rts.items():
                        t = time.perf_counter()
                        res = rt.render(scene, pose, **kw)
                        wall[n].append(time.perf_counter() - t)
                        graph[n].append(res.timings["renderer"])
                diff = float(np.abs(first["selected"].image_float
                                    - first["masked"].image_float).max())
                pv = {n: r.work["point_views"] for n, r in first.items()}
                med = {n: (statistics.median(wall[n]), statistics.median(graph[n])) for n in rts}
                print(f"V={nv:2d} k={k}: max |selected - masked| {diff:.1e}; (point, view) pairs "
                      f"{pv['selected']} vs {pv['masked']}; s/frame {med['selected'][0]:.3f} vs "
                      f"{med['masked'][0]:.3f} (renderer graph {med['selected'][1]:.3f} vs "
                      f"{med['masked'][1]:.3f})", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
