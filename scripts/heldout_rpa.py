"""Cheap held-out camera score of a checkpoint: RPA from the encoder only (no rendering).

    python scripts/heldout_rpa.py runs/x/last.pt [--scenes 16] [--json out.json]

Protocol as iris-eval's (8 frames; frames 1, 4, 6 are queries located in the frame of the other
five, which are encoded isolated), Seq order. Prints RPA@5/15/30 over all pairs of the 8 frames,
the median rotation and translation-direction errors, the median true rotation (what identity
cameras would score), the spread of the predicted camera centres and the predicted focal against
the true one. Used to pick recipes in docs/TRAINING.md: it runs in seconds, so it can score a
checkpoint while another run trains.
"""
from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from iris_train import load_model, read_checkpoint
from iris_train.data import HELDOUT_SEEDS, SyntheticScenes, relative_to_first
from iris_train.evaluate import split_frames
from iris_train.metrics import relative_pose_errors


def score(model, scenes) -> dict:
    refs, targets = split_frames(8)
    order = list(refs) + list(targets)             # references first: view 0 = frame 0
    rot, trans, true_rot, spread, focal_ratio = [], [], [], [], []
    for i in range(len(scenes)):
        data = scenes[i]
        x = torch.as_tensor(data.images[order]).permute(0, 3, 1, 2).float() / 255.0
        is_ref = torch.arange(8) < len(refs)
        with torch.no_grad():
            _, pred, focal = model.encode_batch(x[None], is_ref)
        pred = pred[0].double().numpy()
        gt = relative_to_first(data.world_from_cam[order])
        r, t = relative_pose_errors(pred, gt)
        r0, _ = relative_pose_errors(np.tile(np.eye(4), (8, 1, 1)), gt)
        rot.append(r), trans.append(t), true_rot.append(r0)
        spread.append(float(np.linalg.norm(pred[:, :3, 3] - pred[:, :3, 3].mean(0), axis=1).mean()))
        focal_ratio.append(float(focal[0, 0]) / (data.K[0, 0] / data.images.shape[2]))
    rot, trans = np.concatenate(rot), np.concatenate(trans)
    err = np.maximum(rot, trans)
    return {**{f"rpa@{t}": float(np.mean(err < t)) for t in (5, 15, 30)},
            "median_rotation_error": float(np.median(rot)),
            "median_translation_error": float(np.median(trans)),
            "median_true_rotation": float(np.median(np.concatenate(true_rot))),
            "centre_spread": float(np.mean(spread)),
            "focal_ratio": float(np.median(focal_ratio))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint")
    parser.add_argument("--scenes", type=int, default=16)
    parser.add_argument("--json", default=None)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model = load_model(args.checkpoint)
    result = {"step": read_checkpoint(args.checkpoint).get("step"),
              **score(model, SyntheticScenes(HELDOUT_SEEDS[:args.scenes]))}
    print(json.dumps(result))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
