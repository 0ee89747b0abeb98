"""Subprocess entries of the error-against-time benchmark, run as a module:

    python -m benchmarks.evt.child torch-anchor --checkpoint CKPT --scenes N --runs R \\
        --threads T --size S --out anchor.npz            # with LD_PRELOAD=<tcmalloc>
    python -m benchmarks.evt.child memory --model-dir DIR --quality balanced --threads T \\
        --size 512 --images refs.npy --workers W         # prints one JSON line

Why subprocesses: tcmalloc has to be preloaded before the process starts, and peak RSS
(``VmHWM``) has to be that of a fresh process that never imported torch. So this module imports
numpy only at module level; each entry imports what it needs. ``command`` and ``environment``
build the launch for the parent (``measure``).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

#: The repository root: on the child's PYTHONPATH so that ``-m benchmarks.evt.child`` resolves
#: from any working directory.
REPO = Path(__file__).resolve().parents[2]
MODULE = "benchmarks.evt.child"


def command(entry: str, **options) -> list[str]:
    """``[python, -m, benchmarks.evt.child, entry, --option value, ...]`` (paths made absolute)."""
    cmd = [sys.executable, "-m", MODULE, entry]
    for key, value in options.items():
        if isinstance(value, Path):
            value = value.resolve()
        cmd += [f"--{key.replace('_', '-')}", str(value)]
    return cmd


def environment(**extra: str) -> dict:
    """The parent's environment with the repository first on PYTHONPATH, plus ``extra``."""
    path = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)
    return dict(os.environ, PYTHONPATH=path, **extra)


# ----------------------------------------------------------------------------------------------
# torch-anchor: the torch eager anchor, in a process started with tcmalloc preloaded
# ----------------------------------------------------------------------------------------------

def torch_anchor(args) -> None:
    """Same scenes and frames as the in-process anchor; timings + outputs to an npz."""
    from iris_train.evaluate import split_frames
    from iris_train.model import load_model

    from .measure import heldout_scenes, torch_render_frames
    model = load_model(args.checkpoint)
    scenes = heldout_scenes(args.scenes)
    refs, targets = split_frames(8)
    meds, alls, outs = torch_render_frames(model, [s.images for s in scenes], list(refs),
                                           list(targets), args.threads, args.runs, args.size)
    np.savez(args.out, meds=np.array(meds), alls=np.array(alls), outs=np.stack(outs),
             preload=np.array(os.environ.get("LD_PRELOAD", "")))


# ----------------------------------------------------------------------------------------------
# memory: peak RSS of one render from 16 reference views, in a fresh torch-free process
# ----------------------------------------------------------------------------------------------

def hwm_mb() -> float:
    """VmHWM in MB: the peak RSS of this process image (ru_maxrss would carry the parent's peak
    over exec)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    raise RuntimeError("no VmHWM in /proc/self/status")


def memory(args) -> None:
    from iris_runtime import IrisRuntime
    images = np.load(args.images)                   # 16 reference frames, uint8 [16, H, W, 3]
    rt = IrisRuntime(args.model_dir, threads=args.threads, workers=args.workers)
    before = hwm_mb()
    scene = rt.encode(list(images), cameras="model")
    after_encode = hwm_mb()
    pose = scene.world_from_cam[1].copy()
    pose[:3, 3] += [0.01, 0.0, 0.0]
    t = time.perf_counter()
    res = rt.render(scene, pose, height=args.size, width=args.size, depth=True,
                    quality=args.quality)
    secs = time.perf_counter() - t
    peak = hwm_mb()
    if sys.modules.get("torch") is not None:     # the number would include torch's footprint
        raise RuntimeError("the memory child imported torch; its peak RSS is not the runtime's")
    print(json.dumps({"quality": args.quality, "views": 16, "size": [args.size, args.size],
                      "seconds": secs, "workers": args.workers,
                      "rss_before_mb": before, "rss_after_encode_mb": after_encode,
                      "peak_rss_mb": peak, "work": res.work,
                      "finite": bool(np.isfinite(res.image_float).all())}))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog=f"python -m {MODULE}", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="entry", required=True)
    t = sub.add_parser("torch-anchor", help="torch eager timings + outputs to an npz")
    t.add_argument("--checkpoint", type=Path, required=True)
    t.add_argument("--scenes", type=int, required=True)
    t.add_argument("--runs", type=int, required=True)
    t.add_argument("--threads", type=int, required=True)
    t.add_argument("--size", type=int, required=True)
    t.add_argument("--out", type=Path, required=True)
    m = sub.add_parser("memory", help="peak RSS of one render, as one JSON line on stdout")
    m.add_argument("--model-dir", type=Path, required=True)
    m.add_argument("--quality", required=True)
    m.add_argument("--threads", type=int, required=True)
    m.add_argument("--size", type=int, required=True)
    m.add_argument("--images", type=Path, required=True, help="uint8 [16, H, W, 3] .npy")
    m.add_argument("--workers", type=int, required=True)
    args = ap.parse_args(argv)
    {"torch-anchor": torch_anchor, "memory": memory}[args.entry](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
