"""Distil the camera head on the camera solve alone, no rendering: does a head generalise?

    python scripts/head_distill.py --out runs/hd-corr --camera-head correlation \\
        --init models/iris-tiny-rgb.pt --classic 400 --capture 1216 --max-minutes 20

Each step draws ``--batch`` training scenes with their cached solved cameras
(``iris_train.pseudo_poses.load_or_solve``, the teacher of ``iris-train --render-cameras
epipolar``; no camera label is read), 4-8 of their solved views in random order (view 0 of the
order is the canonical frame), encodes them all as references and minimises
``iris_train.train.solve_losses`` (rotation ``1 - cos``, squared centre distance, squared log
focal; weights 10, 10, 1 as in F1's distillation). Only the encoder and the camera head train.

Every ``--eval-every`` steps and at the end: the head's held-out score, ``scripts/heldout_rpa.py``'s
``score`` (the 16 held-out scenes or the first ``--heldout-scenes``, iris-eval's split, encoder only, true poses used to score
only), appended to ``OUT/log.jsonl`` with the training losses. ``OUT/last.pt`` is a model
checkpoint (``iris_train.load_model``, ``iris-export``) with the distillation's settings.

The scenes: classic training seeds ``0 .. --classic - 1`` rendered at 256x256 and capture-like
seeds ``0 .. --capture - 1`` (as ``iris-train --classic-render-size 256 --capture-scenes N``
draws them); ``python -m iris_train.pseudo_poses --train N --classic-render-size 256 --capture M
--solve`` fills the cache first (otherwise each missing scene is solved when first drawn).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

import numpy as np  # noqa: E402
import torch  # noqa: E402

WEIGHTS = {"solve_rot": 10.0, "solve_trans": 10.0, "solve_focal": 1.0}


def training_sets(classic: int, capture: int):
    """-> list of (SyntheticScenes, solutions: index -> SolvedCameras)."""
    from iris_train import pseudo_poses
    from iris_train.data import SyntheticScenes
    from iris_train.train import CAPTURE_RENDER_SIZE
    size, depth_range = (64, 64), pseudo_poses.DEFAULT_DEPTH_RANGE
    sets = []
    if classic:
        sets.append(SyntheticScenes(range(classic), size=size, render_size=(256, 256)))
    if capture:
        sets.append(SyntheticScenes(range(capture), size=size, kind="capture",
                                    render_size=CAPTURE_RENDER_SIZE))
    cache: dict = {}

    def solutions_of(k):
        def solutions(i):
            if (k, i) not in cache:
                cache[k, i] = pseudo_poses.load_or_solve(sets[k], i, depth_range)
            return cache[k, i]
        return solutions
    return [(s, solutions_of(k)) for k, s in enumerate(sets)]


def draw(sets, batch: int, rng: np.random.Generator):
    """``images [B, V, 3, 64, 64]``, solved ``world_from_cam [B, V, 4, 4]``, ``focal [B, 2]``."""
    from iris_train.train import _draw_solved
    n_views = int(rng.integers(4, 9))
    images, cams, focals = [], [], []
    for _ in range(batch):
        scenes, solutions = sets[int(rng.integers(len(sets)))]
        index, order, (T, f) = _draw_solved(scenes, solutions, rng, n_views)
        images.append(scenes[index].images[order])
        cams.append(T)
        focals.append(f)
    x = torch.as_tensor(np.stack(images)).permute(0, 1, 4, 2, 3).float() / 255.0
    return x, torch.stack(cams), torch.stack(focals)


def build(args):
    import dataclasses

    from iris_train import build_model, read_checkpoint
    from iris_train.config import ModelConfig
    from iris_train.train import load_init_weights
    payload = read_checkpoint(args.init)
    cfg = dataclasses.replace(ModelConfig.from_dict(payload["config"]),
                              camera_head=args.camera_head)
    model = build_model(cfg)
    fresh = load_init_weights(model, payload)
    return model, fresh


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--init", type=Path, default=REPO / "models" / "iris-tiny-rgb.pt")
    ap.add_argument("--camera-head", default="correlation", choices=("tokens", "correlation"))
    ap.add_argument("--classic", type=int, default=400)
    ap.add_argument("--capture", type=int, default=0)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--lr", type=float, default=3e-4, help="camera head (the encoder: x0.3)")
    ap.add_argument("--steps", type=int, default=100_000)
    ap.add_argument("--max-minutes", type=float, default=20.0)
    ap.add_argument("--eval-every", type=int, default=200)
    ap.add_argument("--heldout-scenes", type=int, default=16, help="held-out scenes scored")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    from heldout_rpa import score

    from iris_train.data import HELDOUT_SEEDS, SyntheticScenes
    from iris_train.model import save_checkpoint
    from iris_train.train import solve_losses
    model, fresh = build(args)
    sets = training_sets(args.classic, args.capture)
    heldout = SyntheticScenes(HELDOUT_SEEDS[:args.heldout_scenes])
    head = list(model.camera_head.parameters())
    opt = torch.optim.AdamW([{"params": head, "lr": args.lr},
                             {"params": list(model.encoder.parameters()), "lr": 0.3 * args.lr}],
                            weight_decay=0.01)
    args.out.mkdir(parents=True, exist_ok=True)
    log = open(args.out / "log.jsonl", "a")
    rng = np.random.default_rng(args.seed)
    t0, step, running = time.time(), 0, {}

    def evaluate():
        model.eval()
        result = score(model, heldout)
        model.train()
        entry = {"step": step, "minutes": round((time.time() - t0) / 60, 2), "heldout": result,
                 "train": {k: v / max(running.get("n", 1), 1) for k, v in running.items()
                           if k != "n"}}
        log.write(json.dumps(entry) + "\n")
        log.flush()
        print(f"step {step} {entry['minutes']} min: held-out RPA@15 {result['rpa@15']:.3f} "
              f"@30 {result['rpa@30']:.3f} rot {result['median_rotation_error']:.1f} "
              f"train {entry['train']}", flush=True)
        save_checkpoint(args.out / "last.pt", model, step=step,
                        distill=vars(args) | {"out": str(args.out), "init": str(args.init),
                                              "fresh": fresh})
        running.clear()

    model.train()
    evaluate()
    while step < args.steps and time.time() - t0 < 60 * args.max_minutes:
        images, cams, focal = draw(sets, args.batch, rng)
        _, world_from_cam, pred_focal = model.encode_batch(images)
        terms: dict = {}
        for b in range(images.shape[0]):
            for k, v in solve_losses(world_from_cam[b], pred_focal[b], cams[b], focal[b]).items():
                terms.setdefault(k, []).append(v)
        means = {k: torch.stack(v).mean() for k, v in terms.items()}
        loss = sum(WEIGHTS[k] * v for k, v in means.items())
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        step += 1
        for k, v in means.items():
            running[k] = running.get(k, 0.0) + float(v.detach())
        running["n"] = running.get("n", 0) + 1
        if step % args.eval_every == 0:
            evaluate()
    if step % args.eval_every:
        evaluate()
    return 0


if __name__ == "__main__":
    sys.exit(main())
