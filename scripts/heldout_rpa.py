"""Cheap held-out camera score of a checkpoint: RPA from the encoder only (no rendering).

    python scripts/heldout_rpa.py runs/x/last.pt [--scenes 16] [--json out.json]

Protocol as iris-eval's (8 frames; frames 1, 4, 6 are queries located in the frame of the other
five, which are encoded isolated), Seq order. Prints RPA@5/15/30 over all pairs of the 8 frames,
the median rotation and translation-direction errors, the median true rotation (what identity
cameras would score), the spread of the predicted camera centres and the predicted focal against
the true one, and the errors by quarter of the true baselines (shortest first). ``--fit N``
adds the head's fit to the teacher on N training scenes (label-free): a head that fits its
training scenes no better than the held-out ones needs evidence, not data. ``--capture`` adds
the capture-like held-out scenes (wide fields of view, hand-held paths): off the classic
distribution. Used to pick
recipes in docs/TRAINING.md: it runs in seconds, so it can score a checkpoint while another run
trains.
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


def by_baseline(rot: np.ndarray, trans: np.ndarray, baseline: np.ndarray) -> list[dict]:
    """Median rotation and translation-direction errors of the pairs in each quarter of the
    baseline lengths ``baseline [P]`` (shortest first): where a head's error comes from."""
    edges = np.quantile(baseline, [0.0, 0.25, 0.5, 0.75, 1.0])
    out = []
    for k in range(4):
        m = (baseline >= edges[k]) & ((baseline < edges[k + 1]) if k < 3 else True)
        out.append({"baseline": [float(edges[k]), float(edges[k + 1])],
                    "median_rotation_error": float(np.median(rot[m])),
                    "median_translation_error": float(np.median(trans[m])),
                    "rpa@15": float(np.mean(np.maximum(rot[m], trans[m]) < 15))})
    return out


def _baselines(world_from_cam: np.ndarray) -> np.ndarray:
    c = world_from_cam[:, :3, 3]
    i, j = np.triu_indices(len(c), 1)
    return np.linalg.norm(c[i] - c[j], axis=1)


def fit(model, scenes, solutions, indices) -> dict:
    """How well the head fits training scenes: RPA of its cameras of ``scenes[i]`` (all solved
    views, all references) against the teacher's (``solutions(i)``, ``SolvedCameras``) for i in
    ``indices``, and the errors by quarter of the teacher's baselines. Label-free."""
    rot, trans, base = [], [], []
    for i in indices:
        solved = solutions(i)
        order = np.flatnonzero(solved.solved)
        if len(order) < 2:
            continue
        x = torch.as_tensor(scenes[i].images[order]).permute(0, 3, 1, 2).float() / 255.0
        with torch.no_grad():
            _, pred, _ = model.encode_batch(x[None])
        teacher = solved.rebased(order)
        r, t = relative_pose_errors(pred[0].double().numpy(), teacher)
        rot.append(r), trans.append(t), base.append(_baselines(teacher))
    rot, trans, base = map(np.concatenate, (rot, trans, base))
    err = np.maximum(rot, trans)
    return {**{f"rpa@{t}": float(np.mean(err < t)) for t in (5, 15, 30)},
            "median_rotation_error": float(np.median(rot)),
            "median_translation_error": float(np.median(trans)),
            "by_baseline": by_baseline(rot, trans, base)}


def capture_heldout_scenes(n: int):
    """The first ``n`` capture-like held-out scenes (iris-eval's synthetic:capture-heldout),
    rendered at 256x256 and area-averaged to 64x64 as the training scenes are."""
    from iris_train.data import CAPTURE_HELDOUT_SEEDS
    return SyntheticScenes(list(CAPTURE_HELDOUT_SEEDS)[:n], size=(64, 64), kind="capture",
                           render_size=(256, 256))


def score(model, scenes) -> dict:
    refs, targets = split_frames(8)
    order = list(refs) + list(targets)             # references first: view 0 = frame 0
    rot, trans, true_rot, spread, focal_ratio, base = [], [], [], [], [], []
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
        rot.append(r), trans.append(t), true_rot.append(r0), base.append(_baselines(gt))
        spread.append(float(np.linalg.norm(pred[:, :3, 3] - pred[:, :3, 3].mean(0), axis=1).mean()))
        focal_ratio.append(float(focal[0, 0]) / (data.K[0, 0] / data.images.shape[2]))
    rot, trans, base = np.concatenate(rot), np.concatenate(trans), np.concatenate(base)
    err = np.maximum(rot, trans)
    return {**{f"rpa@{t}": float(np.mean(err < t)) for t in (5, 15, 30)},
            "median_rotation_error": float(np.median(rot)),
            "median_translation_error": float(np.median(trans)),
            "median_true_rotation": float(np.median(np.concatenate(true_rot))),
            "centre_spread": float(np.mean(spread)),
            "focal_ratio": float(np.median(focal_ratio)),
            "by_baseline": by_baseline(rot, trans, base)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint")
    parser.add_argument("--scenes", type=int, default=16)
    parser.add_argument("--json", default=None)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--fit", type=int, default=0, metavar="N",
                        help="also the fit to the teacher on N classic training scenes (every "
                             "20th seed, 256x256 renders' solve; fit())")
    parser.add_argument("--capture", action="store_true",
                        help="also the capture-like held-out scenes (iris-eval's "
                             "synthetic:capture-heldout, rendered at 256x256 and area-averaged "
                             "to 64x64 as the training scenes are), under 'capture_heldout'")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model = load_model(args.checkpoint)
    result = {"step": read_checkpoint(args.checkpoint).get("step"),
              **score(model, SyntheticScenes(HELDOUT_SEEDS[:args.scenes]))}
    if args.capture:
        result["capture_heldout"] = score(model, capture_heldout_scenes(args.scenes))
    if args.fit:
        from iris_train import pseudo_poses
        train = SyntheticScenes(range(20 * args.fit), size=(64, 64), render_size=(256, 256))
        result["train_fit"] = fit(model, train, lambda i: pseudo_poses.load_or_solve(
            train, i, pseudo_poses.DEFAULT_DEPTH_RANGE), range(0, 20 * args.fit, 20))
    print(json.dumps(result))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=1)


if __name__ == "__main__":
    main()
