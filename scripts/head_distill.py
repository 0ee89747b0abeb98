"""Distil the camera head on the camera solve alone, no rendering: does a head generalise?

    python scripts/head_distill.py --out runs/hd-corr --camera-head correlation \\
        --init models/iris-tiny-rgb.pt --classic 400 --capture 1216 --max-minutes 20

Each step draws ``--batch`` training scenes with their cached solved cameras
(``iris_train.pseudo_poses.load_or_solve``, the teacher of ``iris-train --render-cameras
solve``; no camera label is read), 4-8 of their solved views in random order (view 0 of the
order is the canonical frame), encodes them all as references and minimises
``iris_train.losses.solve_losses`` (rotation ``1 - cos``, squared centre distance, squared log
focal; weights 10, 10, 1 as in F1's distillation). Only the camera head and the encoder it reads
train: the model's encoder, or with ``--separate-encoder`` (or an init that has one) the head's
own, which leaves the renders as the init's.

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
import torch.nn.functional as F  # noqa: E402

WEIGHTS = {"solve_rot": 10.0, "solve_trans": 10.0, "solve_focal": 1.0, "solve_dir": 0.0}


def direction_loss(world_from_cam: torch.Tensor, solved: torch.Tensor) -> torch.Tensor:
    """``1 - cos`` of the angle between the predicted and the solved baseline ``c_i - c_j`` of
    every pair of views i < j (``world_from_cam``, ``solved`` ``[V, 4, 4]`` in one frame), the
    scale-free quantity RPA's translation error measures; the centre term alone weighs a
    direction error by the baseline's length, so short baselines, most of a scene's pairs,
    barely count in it."""
    V = world_from_cam.shape[0]
    i, j = torch.triu_indices(V, V, 1)
    c, c_s = world_from_cam[:, :3, 3], solved[:, :3, 3]
    cos = F.cosine_similarity(c[i] - c[j], c_s[i] - c_s[j], dim=-1, eps=1e-8)
    return (1 - cos).mean()


def training_sets(classic: int, capture: int):
    """-> list of (SyntheticScenes, solutions: index -> SolvedCameras)."""
    from iris_train import pseudo_poses
    from iris_train.data import SyntheticScenes
    from iris_train.scene_sets import CAPTURE_RENDER_SIZE
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


def augment(images: torch.Tensor, world_from_cam: torch.Tensor, focal: torch.Tensor,
            rng: np.random.Generator, max_roll_deg: float):
    """One scene's ``images [V, 3, H, W]`` (square), cameras ``[V, 4, 4]`` (view 0 = I) and
    ``focal [2]`` as another scene the same cameras would see: mirrored left-right with
    probability 1/2 (the world mirrored too: ``T -> S T S``, S = diag(-1, 1, 1, 1)), each view
    rolled about its optical axis by its own angle in [-max_roll, max_roll], and all views zoomed
    by ``1 / (cos + sin)(max_roll)`` so that no rolled view shows a corner outside the photo (a
    corner would tell the roll by itself); the focal grows by the zoom, the cameras are re-based
    on the rolled view 0. Exact for a pinhole with the principal point at the centre."""
    import math

    import torch.nn.functional as F
    V = images.shape[0]
    if rng.random() < 0.5:
        S = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))
        images, world_from_cam = images.flip(-1), S @ world_from_cam @ S
    a = math.radians(max_roll_deg)
    zoom = 1.0 / (math.cos(a) + math.sin(a))
    theta = torch.as_tensor(rng.uniform(-a, a, V), dtype=torch.float32)
    c, s = torch.cos(theta), torch.sin(theta)
    # The rolled camera sees normalised image point Q p where the old one saw p (Q: rotation by
    # theta in the image plane), so the new image at p' samples the old at Q^T p' (times zoom).
    Qt = torch.stack([torch.stack([c, s], -1), torch.stack([-s, c], -1)], -2)     # [V, 2, 2]
    grid = F.affine_grid(torch.cat([Qt * zoom, torch.zeros(V, 2, 1)], -1), list(images.shape),
                         align_corners=False)
    images = F.grid_sample(images, grid, mode="bilinear", align_corners=False)
    roll = torch.eye(4).repeat(V, 1, 1)
    roll[:, :2, :2] = Qt.transpose(-1, -2)                        # cam'_from_cam = Q (in 3D)
    world_from_cam = world_from_cam @ torch.linalg.inv(roll)       # world_from_cam'
    world_from_cam = torch.linalg.inv(world_from_cam[0]) @ world_from_cam
    return images, world_from_cam, focal / zoom


def _source_coords(Qt: torch.Tensor, focal: torch.Tensor, zoom: float, u: torch.Tensor):
    """Where the rotated cameras' normalised image points ``u [N, 2]`` (``[-1, 1]``, the
    ``grid_sample`` convention) were in the original photos: rays ``(u / (2 f zoom), 1)`` turned
    by ``Qt [V, 3, 3]`` (cam_from_cam') and projected -> ``[V, N, 2]`` (NaN behind)."""
    d = torch.cat([u / (2 * focal * zoom), torch.ones(len(u), 1)], dim=1)     # [N, 3]
    src = d[None] @ Qt.transpose(1, 2)                                          # [V, N, 3]
    z = src[..., 2:]
    return torch.where(z > 1e-6, 2 * focal * src[..., :2] / z.clamp_min(1e-6), torch.nan)


def augment_rotation(photos: np.ndarray, world_from_cam: torch.Tensor, focal: torch.Tensor,
                     size: tuple[int, int], rng: np.random.Generator, max_deg: float):
    """One scene's ``photos`` uint8 ``[V, h, w, 3]`` (the render the teacher solved, a whole
    multiple of ``size``), cameras ``[V, 4, 4]`` (view 0 = I) and ``focal [2]`` (fx/W, fy/H) as
    the photos the same cameras would take turned about their centres: each view by its own
    rotation (random axis, angle uniform in [0, ``max_deg``]), the image warped by the rotation's
    homography, and all views zoomed by the least common factor that keeps every warped view
    inside its photo (a border would tell the rotation by itself). Mirrored left-right with
    probability 1/2 (the world too: ``T -> S T S``). Exact for a pinhole with the principal
    point at the centre; warped at the render's size, then area-averaged to ``size`` and
    quantised as the training photos are. -> images ``[V, 3, H, W]``, cameras re-based on view
    0, focal (times the zoom), zoom.

    Unlike the scene's own views, a pure rotation moves no camera centre, so the head sees image
    motion with the rotation changed and the translation direction not: the two are pulled apart
    (docs/TRAINING.md), and no rotation can be memorised per scene."""
    import torch.nn.functional as F
    V, h, w = photos.shape[:3]
    x = torch.as_tensor(photos).permute(0, 3, 1, 2).float() / 255.0
    if rng.random() < 0.5:
        S = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))
        x, world_from_cam = x.flip(-1), S @ world_from_cam @ S
    import cv2
    axis = rng.normal(size=(V, 3))
    turn = axis / np.linalg.norm(axis, axis=1, keepdims=True) * rng.uniform(
        0, np.radians(max_deg), (V, 1))                                        # axis-angle
    Q = torch.as_tensor(np.stack([cv2.Rodrigues(v)[0] for v in turn]),
                        dtype=torch.float32)                                    # cam'_from_cam
    Qt = Q.transpose(1, 2)
    corners = torch.tensor([[-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [1.0, 1.0]])
    zoom = 1.0
    while zoom < 3.0:
        c = _source_coords(Qt, focal, zoom, corners)
        if torch.isfinite(c).all() and c.abs().max() <= 1.0:
            break
        zoom *= 1.02
    ys = (torch.arange(h) + 0.5) * (2.0 / h) - 1.0
    xs = (torch.arange(w) + 0.5) * (2.0 / w) - 1.0
    u = torch.stack([xs.repeat(h), ys.repeat_interleave(w)], dim=-1)           # [hw, 2]
    grid = _source_coords(Qt, focal, zoom, u).nan_to_num(2.0).reshape(V, h, w, 2)
    x = F.grid_sample(x, grid, mode="bilinear", padding_mode="border", align_corners=False)
    x = F.avg_pool2d(x, h // size[0])
    x = torch.round(x * 255.0) / 255.0
    rot = torch.eye(4).repeat(V, 1, 1)
    rot[:, :3, :3] = Qt                                                         # cam_from_cam'
    world_from_cam = world_from_cam @ rot
    world_from_cam = torch.linalg.inv(world_from_cam[0]) @ world_from_cam
    return x, world_from_cam, focal * zoom, zoom


def draw(sets, batch: int, rng: np.random.Generator, max_roll_deg: float = 0.0,
         max_rotation_deg: float = 0.0, rotation_fraction: float = 1.0, shares=None):
    """``images [B, V, 3, 64, 64]``, solved ``world_from_cam [B, V, 4, 4]``, ``focal [B, 2]``,
    ``zoomed [B]`` bool (``augment``-ed when ``max_roll_deg`` > 0; with ``max_rotation_deg`` > 0,
    each scene ``augment_rotation``-ed with probability ``rotation_fraction``; ``zoomed``: those
    turned and zoomed, whose focal is not the scene's any more). Each scene comes from one of
    ``sets``, drawn with probabilities ``shares`` (None: alike)."""
    from iris_train.batches import draw_solved
    n_views = int(rng.integers(4, 9))
    images, cams, focals, zoomed = [], [], [], []
    for _ in range(batch):
        # (Without shares, the draw the runs recorded in docs/TRAINING.md made: same seed, same
        # scenes.)
        k = rng.integers(len(sets)) if shares is None else rng.choice(len(sets), p=shares)
        scenes, solutions = sets[int(k)]
        index, order, (T, f) = draw_solved(scenes, solutions, rng, n_views)
        zoom = 1.0
        if max_rotation_deg > 0 and rng.random() < rotation_fraction:
            photos = scenes.cached(int(scenes.seeds[index])).images[order]
            x, T, f, zoom = augment_rotation(photos, T, f, scenes.size, rng, max_rotation_deg)
        else:
            x = torch.as_tensor(scenes[index].images[order]).permute(0, 3, 1, 2).float() / 255.0
        if max_roll_deg > 0:
            x, T, f = augment(x, T, f, rng, max_roll_deg)
        images.append(x)
        cams.append(T)
        focals.append(f)
        zoomed.append(zoom > 1.0)
    return torch.stack(images), torch.stack(cams), torch.stack(focals), torch.tensor(zoomed)


def build(args):
    import dataclasses

    from iris_train import build_model, read_checkpoint
    from iris_train.config import ModelConfig
    from iris_train.train import load_init_weights
    payload = read_checkpoint(args.init)
    cfg = ModelConfig.from_dict(payload["config"])
    cfg = dataclasses.replace(cfg, camera_head=args.camera_head,
                              correlation_scale=args.correlation_scale or cfg.correlation_scale)
    model = build_model(cfg)
    fresh = load_init_weights(model, payload)
    if args.separate_encoder and not cfg.camera_encoder:
        # The camera head gets an encoder of its own, the init's encoder to start.
        separate = build_model(dataclasses.replace(cfg, camera_encoder=True))
        state = model.state_dict()
        separate.load_state_dict(state | {"camera_encoder." + k[len("encoder."):]: v
                                          for k, v in state.items() if k.startswith("encoder.")})
        model = separate
    # The renderer is the --init checkpoint's, untouched: its training record (the cameras it
    # was trained with, which the export's default follows) goes with it.
    return model, fresh, payload.get("train_config")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--init", type=Path, default=REPO / "models" / "iris-tiny-rgb.pt")
    ap.add_argument("--camera-head", default="correlation", choices=("tokens", "correlation"))
    ap.add_argument("--correlation-scale", type=int, default=0, choices=(0, 2, 4),
                    help="the correlation grid in token grids (0: the --init checkpoint's)")
    ap.add_argument("--classic", type=int, default=400)
    ap.add_argument("--capture", type=int, default=0)
    ap.add_argument("--capture-share", type=float, default=None,
                    help="with --classic and --capture: the share of the batch's scenes drawn "
                         "from the capture-like ones (default: half, as each set is drawn alike)")
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--lr", type=float, default=3e-4, help="camera head (the encoder: x0.3)")
    ap.add_argument("--separate-encoder", action="store_true",
                    help="train the camera head on an encoder of its own (ModelConfig."
                         "camera_encoder, the init's encoder to start): the renders stay the "
                         "init's")
    ap.add_argument("--steps", type=int, default=100_000)
    ap.add_argument("--lr-schedule", default="constant", choices=("constant", "cosine"),
                    help="cosine: the learning rate falls to 1%% of --lr over --steps (anneals a "
                         "continued run; keep --max-minutes long enough to reach the end)")
    ap.add_argument("--warmup", type=int, default=0,
                    help="steps of linear warm-up (a continued run starts with fresh Adam moments)")
    ap.add_argument("--max-minutes", type=float, default=20.0)
    ap.add_argument("--eval-every", type=int, default=200)
    ap.add_argument("--augment-roll", type=float, default=0.0,
                    help="augment: mirror and roll each view by up to this many degrees (0: off)")
    ap.add_argument("--augment-rotation", type=float, default=0.0,
                    help="augment: turn each view about its centre by up to this many degrees "
                         "(homography of the render, zoomed to stay inside; 0: off)")
    ap.add_argument("--rotation-fraction", type=float, default=1.0,
                    help="with --augment-rotation: the fraction of scenes turned (the others "
                         "train the focal)")
    ap.add_argument("--direction-weight", type=float, default=0.0,
                    help="weight of the baseline-direction term (direction_loss; 0: off)")
    ap.add_argument("--heldout-scenes", type=int, default=16, help="held-out scenes scored")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.capture_share is not None and not 0.0 < args.capture_share < 1.0:
        ap.error(f"--capture-share: expected a share in (0, 1), got {args.capture_share}")
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    from heldout_rpa import capture_heldout_scenes, score

    from iris_train.data import HELDOUT_SEEDS, SyntheticScenes
    from iris_train.model import save_checkpoint
    from iris_train.losses import solve_losses
    model, fresh, train_config = build(args)
    sets = training_sets(args.classic, args.capture)
    shares = ([1 - args.capture_share, args.capture_share]
              if args.classic and args.capture and args.capture_share is not None else None)
    heldout = SyntheticScenes(HELDOUT_SEEDS[:args.heldout_scenes])
    capture_heldout = capture_heldout_scenes(args.heldout_scenes) if args.capture else None
    head = list(model.camera_head.parameters())
    # The encoder the head reads: its own where it has one (the renderer's stays as it was).
    encoder = model.camera_encoder if model.camera_encoder is not None else model.encoder
    opt = torch.optim.AdamW([{"params": head, "lr": args.lr},
                             {"params": list(encoder.parameters()), "lr": 0.3 * args.lr}],
                            weight_decay=0.01)
    args.out.mkdir(parents=True, exist_ok=True)
    log = open(args.out / "log.jsonl", "a")
    rng = np.random.default_rng(args.seed)
    t0, step, running = time.time(), 0, {}

    def evaluate():
        model.eval()
        result = score(model, heldout)
        if capture_heldout is not None:
            result["capture_heldout"] = score(model, capture_heldout)
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
                                              "fresh": fresh},
                        **({"train_config": train_config} if train_config else {}))
        running.clear()

    base_lr = [g["lr"] for g in opt.param_groups]

    def set_lr():
        factor = min(1.0, (step + 1) / args.warmup) if args.warmup else 1.0
        if args.lr_schedule == "cosine":
            factor *= 0.01 + 0.99 * 0.5 * (1 + np.cos(np.pi * min(step / args.steps, 1.0)))
        for g, lr in zip(opt.param_groups, base_lr):
            g["lr"] = lr * factor

    model.train()
    evaluate()
    while step < args.steps and time.time() - t0 < 60 * args.max_minutes:
        images, cams, focal, zoomed = draw(sets, args.batch, rng, args.augment_roll,
                                           args.augment_rotation, args.rotation_fraction, shares)
        _, world_from_cam, pred_focal = model.encode_batch(images)
        terms: dict = {}
        for b in range(images.shape[0]):
            for k, v in solve_losses(world_from_cam[b], pred_focal[b], cams[b], focal[b]).items():
                if k == "solve_focal" and zoomed[b]:
                    continue       # the zoom moves the focal off the scenes' own distribution
                terms.setdefault(k, []).append(v)
            if args.direction_weight > 0:
                terms.setdefault("solve_dir", []).append(direction_loss(world_from_cam[b], cams[b]))
        means = {k: torch.stack(v).mean() for k, v in terms.items()}
        weights = WEIGHTS | {"solve_dir": args.direction_weight}
        loss = sum(weights[k] * v for k, v in means.items())
        set_lr()
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
