"""Record or check the runtime's outputs bit for bit, across its knobs.

A refactor of ``iris_runtime`` must not change a single output bit. This script renders a fixed set
of cases through the public API (every quality preset, top-k by ray and by point, odd chunk sizes,
a resized and a rescaled output, explicit intrinsics, a pose that sees nothing, ``locate`` and the
solve's cameras) and either writes them to an ``.npz`` or compares against one::

    python scripts/runtime_golden.py MODEL_DIR --write before.npz     # on the old code
    python scripts/runtime_golden.py MODEL_DIR --check before.npz     # on the new code

``--check`` exits 1 and names every array that differs (with its max abs difference).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def cases(model_dir: str, threads: int = 1) -> dict[str, np.ndarray]:
    from iris_runtime import IrisRuntime
    rt = IrisRuntime(model_dir, threads=threads)
    h, w = rt.image_size
    rng = np.random.default_rng(0)
    images = rng.random((4, h, w, 3), dtype=np.float32)
    # A smooth pattern, so that the camera solve has something to match.
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    for i in range(4):
        images[i, ..., 0] = 0.5 + 0.5 * np.sin(9 * (xx + 0.03 * i) + 3 * yy)
        images[i, ..., 1] = 0.5 + 0.5 * np.cos(7 * yy - 2 * (xx + 0.03 * i))
    out: dict[str, np.ndarray] = {}
    scene = rt.encode(images, cameras="model")
    out["scene.world_from_cam"] = np.asarray(scene.world_from_cam)
    out["scene.focal"] = np.asarray(scene.focal)
    pose = np.asarray(scene.world_from_cam[1], dtype=np.float64)
    away = np.eye(4)
    away[:3, :3] = np.diag([-1.0, 1.0, -1.0])           # looks backwards: no reference sees it
    away[2, 3] = -5.0
    calls = {
        "exact": dict(),
        "balanced": dict(quality="balanced"),
        "fast": dict(quality="fast"),
        "topk_ray2": dict(top_k=2, top_k_by="ray"),
        "topk_point2": dict(top_k=2, top_k_by="point"),
        "samples24": dict(samples=24),
        "chunk37": dict(chunk_rays=37),
        "size48x40": dict(height=48, width=40),
        "scale_half_cubic": dict(scale=0.5, upsample="cubic"),
        "intrinsics": dict(intrinsics=np.array([[70.0, 0, 30.0], [0, 70.0, 33.0], [0, 0, 1]])),
    }
    if "renderer_int8" in rt.manifest.graphs:
        calls["int8"] = dict(precision="int8")
    for name, kw in calls.items():
        r = rt.render(scene, pose, depth=True, **kw)
        out[f"{name}.image"], out[f"{name}.rgb"], out[f"{name}.depth"] = r.image, r.image_float, r.depth
    r = rt.render(scene, away, depth=True)
    out["away.rgb"], out["away.depth"] = r.image_float, r.depth
    out["pose_index.image"] = rt.render(scene, 2)
    out["from_images.image"] = rt.render(images, pose)
    out["locate"] = rt.locate(scene, images[3])
    try:
        epi = rt.encode(images, cameras="solve")
        out["solve.world_from_cam"] = np.asarray(epi.world_from_cam)
        out["solve.image"] = rt.render(epi, np.asarray(epi.world_from_cam[1]))
    except Exception as exc:                              # recorded, so the check compares it too
        out["solve.error"] = np.array(type(exc).__name__)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model_dir")
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--write", type=Path)
    group.add_argument("--check", type=Path)
    args = parser.parse_args(argv)
    out = cases(args.model_dir)
    if args.write:
        np.savez(args.write, **out)
        print(f"wrote {len(out)} arrays to {args.write}")
        return 0
    ref = np.load(args.check)
    bad = []
    for key in sorted(set(ref.files) | set(out)):
        if key not in ref.files or key not in out:
            bad.append(f"{key}: only in {'new' if key in out else 'reference'}")
            continue
        a, b = ref[key], np.asarray(out[key])
        if a.shape != b.shape or a.dtype != b.dtype:
            bad.append(f"{key}: {a.dtype}{a.shape} -> {b.dtype}{b.shape}")
        elif a.tobytes() != b.tobytes():
            diff = np.abs(a.astype(np.float64) - b.astype(np.float64)).max() \
                if a.dtype.kind in "fiu" else float("nan")
            bad.append(f"{key}: differs (max abs {diff:.3g})")
    for line in bad:
        print("DIFF", line)
    print(f"{len(out) - len(bad)}/{len(out)} arrays bitwise equal")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
