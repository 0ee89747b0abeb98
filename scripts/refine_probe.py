"""Refined cameras against the solve on all 8 views of synthetic scenes, from a checkpoint's head:
RPA@15 over the 28 pairs and seconds per scene (one thread). A probe for choosing the
refinement's settings (docs/CAMERAS.md, "Refining the model's cameras"); iris-eval and
benchmarks/encode_cost.py give the protocol figures.

    python scripts/refine_probe.py CKPT --set capture            # capture-like held-out, 256x256
    python scripts/refine_probe.py CKPT --set heldout --size 64  # held-out at the model's 64x64
    python scripts/refine_probe.py CKPT --set capture --solve    # the solve instead
    python scripts/refine_probe.py CKPT --set capture --true-focal

The head sees each scene's 64x64 copies (area-averaged); its focal is carried to the photos.
"""
from __future__ import annotations

import argparse
import time

import cv2
import numpy as np
import torch

from iris_runtime.cameras import refine_cameras, solve_cameras
from iris_train import data as D
from iris_train import load_model
from iris_train.metrics import relative_pose_errors

DEPTH_RANGE = (0.1, 1.0)


def rpa15(pred: np.ndarray, truth: np.ndarray, threshold: float = 15.0) -> float:
    """RPA@15 (or at ``threshold`` degrees) over every pair; a pair with an unposed view counts
    as wrong."""
    posed = np.isfinite(pred).all(axis=(1, 2))
    rot, trans = relative_pose_errors(np.where(posed[:, None, None], pred, np.eye(4)), truth)
    i, j = np.triu_indices(len(truth), 1)
    return float(np.mean(np.where(posed[i] & posed[j], np.maximum(rot, trans), 180.0)
                         < threshold))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoint")
    ap.add_argument("--set", choices=["heldout", "capture"], default="capture")
    ap.add_argument("--size", type=int, default=256, help="the photos' side (rendered at 256)")
    ap.add_argument("--solve", action="store_true", help="solve_cameras instead of refining")
    ap.add_argument("--true-focal", action="store_true", help="start from the true focal")
    args = ap.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    model = load_model(args.checkpoint)
    seeds = list(D.CAPTURE_HELDOUT_SEEDS if args.set == "capture" else D.HELDOUT_SEEDS)
    scenes = D.SyntheticScenes(seeds, size=(args.size, args.size), render_size=(256, 256),
                               kind="capture" if args.set == "capture" else None)
    scores, seconds = [], []
    for i, seed in enumerate(seeds):
        scene = scenes[i]
        small = np.stack([cv2.resize(p, (64, 64), interpolation=cv2.INTER_AREA)
                          for p in scene.images])
        with torch.no_grad():
            _, head, focal = model.encode_batch(
                torch.as_tensor(small).permute(0, 3, 1, 2).float()[None] / 255.0)
        true_focal = scene.K[0, 0] / scene.images.shape[2]
        start_focal = (true_focal if args.true_focal else float(focal[0, 0])) * args.size
        t0 = time.perf_counter()
        solved = solve_cameras(list(scene.images), DEPTH_RANGE) if args.solve else \
            refine_cameras(list(scene.images), head[0].double().numpy(), start_focal,
                           DEPTH_RANGE)
        seconds.append(time.perf_counter() - t0)
        scores.append(0.0 if solved is None
                      else rpa15(solved.world_from_cam, D.relative_to_first(scene.world_from_cam)))
        print(f"{seed} {scene.meta.get('kind')}: RPA@15 {scores[-1]:.2f}, head focal "
              f"{float(focal[0, 0]) / true_focal:.2f} x the true one, {seconds[-1]:.2f} s",
              flush=True)
    print(f"mean RPA@15 {np.mean(scores):.3f}, median {np.median(seconds):.2f} s a scene")


if __name__ == "__main__":
    main()
