"""iris-train: self-supervised training of IRIS on multi-view images (no camera labels).

Each step draws scenes, a random subset of their views in random order (view 0 of that order is the
canonical frame), splits the views at random into reference and target views, predicts cameras for
all of them, renders a random subset of target rays from the reference views only, and minimises the
photometric MSE. AdamW with linear warm-up and cosine decay; the encoder and camera head run at
``encoder_lr_scale`` (paper: 0.1x) of the renderer's learning rate; gradients clipped.

    iris-train --preset tiny --steps 20000 --out runs/tiny
    torchrun --nproc_per_node=2 -m iris_train.train --preset tiny --steps 100 --out runs/ddp

Multi-process runs use DistributedDataParallel with the gloo backend (CPU); each rank draws its
own scenes. Checkpoints (``last.pt``, atomic) carry the model config, the training config, the
optimiser state and the step, so ``--resume`` continues a run exactly where it stopped.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.nn as nn

from iris_runtime.errors import InputError
from iris_runtime.geometry import sample_depths

from . import geometry as G
from .config import ModelConfig, preset
from .model import IrisModel, Scene, build_model, read_checkpoint, save_checkpoint


@dataclass(frozen=True)
class TrainConfig:
    preset: str = "tiny"
    steps: int = 20_000
    scenes_per_step: int = 2          # per process
    views_min: int = 4                # views drawn per scene (all predicted, split ref/target)
    views_max: int = 7
    targets_min: int = 1
    targets_max: int = 2
    rays_per_scene: int = 384         # random target rays per scene and step
    lr: float = 1e-3                  # renderer (latent field + ray renderer)
    encoder_lr_scale: float = 0.1     # encoder and camera head (paper: 0.1x)
    weight_decay: float = 0.05
    warmup: int = 500
    min_lr_ratio: float = 0.1
    grad_clip: float = 1.0
    train_scenes: int = 3000          # synthetic training seeds 0 .. train_scenes-1
    seed: int = 0
    log_every: int = 10
    ckpt_every: int = 250

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in d.items() if k in known})


class PhotometricLoss(nn.Module):
    """Wraps the model so that one forward call computes a step's loss (what DDP needs)."""

    def __init__(self, model: IrisModel):
        super().__init__()
        self.model = model

    def forward(self, images: torch.Tensor, ref: list[torch.Tensor], tgt: list[torch.Tensor],
                pixels: list[torch.Tensor], depths: list[torch.Tensor]):
        """``images [B, V, 3, H, W]``; per scene b: reference/target view indices, target pixel
        indices ``[T, n]`` into H*W, stratified sample depths ``[T*n, S]``."""
        model = self.model
        H, W = images.shape[-2:]
        B, V = images.shape[:2]
        is_reference = torch.ones(B, V, dtype=torch.bool)
        for b in range(B):
            is_reference[b, tgt[b]] = False
        # Targets are queries: the references' features and cameras never see a target image.
        features, world_from_cam, focal = model.encode_batch(images, is_reference)
        maps = [model.field.prepare(features[b, ref[b]]) for b in range(images.shape[0])]
        uv_all = G.pixel_centres(H, W, dtype=images.dtype)
        errs = []
        for b in range(images.shape[0]):
            scene = Scene(maps[b], world_from_cam[b, ref[b]], focal[b], (H, W))
            K = scene.intrinsics()
            target_rgb = images[b, tgt[b]].flatten(2).transpose(1, 2)               # [T, HW, 3]
            idx = pixels[b]                                                         # [T, n]
            origins, directions = G.rays_from_pixels(uv_all[idx], K, world_from_cam[b, tgt[b]])
            rgb, _ = model.render_rays(scene, origins.reshape(-1, 3), directions.reshape(-1, 3),
                                       depths[b], need_weights=False)
            gt = torch.gather(target_rgb, 1, idx[..., None].expand(-1, -1, 3)).reshape(-1, 3)
            errs.append(((rgb - gt) ** 2).mean())
        return torch.stack(errs).mean()


def lr_factor(step: int, cfg: TrainConfig) -> float:
    if step < cfg.warmup:
        return (step + 1) / cfg.warmup
    progress = min(1.0, (step - cfg.warmup) / max(1, cfg.steps - cfg.warmup))
    return cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))


def make_optimizer(model: IrisModel, cfg: TrainConfig) -> torch.optim.AdamW:
    slow = list(model.encoder.parameters()) + list(model.camera_head.parameters())
    fast = list(model.field.parameters()) + list(model.renderer.parameters())

    def split(params):   # no weight decay on norms and biases
        return ([p for p in params if p.ndim >= 2], [p for p in params if p.ndim < 2])

    groups = []
    for params, scale in ((slow, cfg.encoder_lr_scale), (fast, 1.0)):
        decay, no_decay = split(params)
        groups += [{"params": decay, "weight_decay": cfg.weight_decay, "lr_scale": scale},
                   {"params": no_decay, "weight_decay": 0.0, "lr_scale": scale}]
    return torch.optim.AdamW(groups, lr=cfg.lr, betas=(0.9, 0.95))


def draw_batch(scenes, cfg: TrainConfig, mcfg: ModelConfig, rng: np.random.Generator):
    """Random scenes, views, split, target pixels and stratified depths for one step."""
    n_views = int(rng.integers(cfg.views_min, cfg.views_max + 1))
    n_tgt = int(rng.integers(cfg.targets_min, cfg.targets_max + 1))
    H, W = mcfg.image_height, mcfg.image_width
    images, ref, tgt, pixels, depths = [], [], [], [], []
    for _ in range(cfg.scenes_per_step):
        data = scenes[int(rng.integers(len(scenes)))]
        order = rng.permutation(data.images.shape[0])[:n_views]        # random order: "Rand"
        images.append(data.images[order])
        # View 0 of the drawn order is the canonical frame, so it is always a reference.
        roles = 1 + rng.permutation(n_views - 1)
        tgt.append(torch.as_tensor(np.sort(roles[:n_tgt])))
        ref.append(torch.as_tensor(np.sort(np.concatenate([[0], roles[n_tgt:]]))))
        n = cfg.rays_per_scene // n_tgt
        pixels.append(torch.as_tensor(rng.integers(0, H * W, size=(n_tgt, n))))
        depths.append(torch.as_tensor(sample_depths(mcfg.near, mcfg.far, mcfg.samples, n_tgt * n,
                                                    stratified=True, rng=rng, dtype=np.float32)))
    batch = torch.as_tensor(np.stack(images)).permute(0, 1, 4, 2, 3).float() / 255.0
    return batch, ref, tgt, pixels, depths


def _setup_distributed() -> tuple[int, int]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("gloo")
    return (dist.get_rank() if world > 1 else 0), world


def train(cfg: TrainConfig, out: Path, resume: bool = False, scenes=None, threads: int | None = None,
          max_seconds: float | None = None) -> Path:
    """Run (or resume) training; returns the path of the last checkpoint."""
    rank, world = _setup_distributed()
    if threads:
        torch.set_num_threads(threads)
    mcfg = preset(cfg.preset)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / "last.pt"
    torch.manual_seed(cfg.seed)
    model = build_model(mcfg)
    optimizer = make_optimizer(model, cfg)
    start_step, elapsed_before = 0, 0.0
    if resume and ckpt_path.exists():
        payload = read_checkpoint(ckpt_path)
        model.load_state_dict(payload["model"])
        optimizer.load_state_dict(payload["optimizer"])
        start_step = int(payload["step"])
        elapsed_before = float(payload.get("elapsed", 0.0))
    model.train()
    if scenes is None:
        from .data import SyntheticScenes
        scenes = SyntheticScenes(range(cfg.train_scenes), size=(mcfg.image_height, mcfg.image_width))
    step_module: nn.Module = PhotometricLoss(model)
    if world > 1:
        step_module = nn.parallel.DistributedDataParallel(step_module)
    log_path = out / "log.jsonl"
    if rank == 0:
        (out / "train_config.json").write_text(json.dumps(dataclasses.asdict(cfg), indent=2))
    progress = None
    if rank == 0:
        from tqdm import tqdm
        progress = tqdm(total=cfg.steps, initial=start_step, desc="iris-train", dynamic_ncols=True,
                        disable=None)
    t0 = time.time()
    ema_loss, rays_done = None, 0
    step = start_step
    for step in range(start_step, cfg.steps):
        factor = lr_factor(step, cfg)
        for group in optimizer.param_groups:
            group["lr"] = cfg.lr * factor * group["lr_scale"]
        # One generator per (seed, rank, step): a resumed run draws exactly the batches it would have.
        batch = draw_batch(scenes, cfg, mcfg, np.random.default_rng([cfg.seed, rank, step]))
        loss = step_module(*batch)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
        optimizer.step()
        loss_value = float(loss.detach())
        ema_loss = loss_value if ema_loss is None else 0.98 * ema_loss + 0.02 * loss_value
        rays_done += sum(int(d.shape[0]) for d in batch[4]) * world
        if rank == 0:
            elapsed = time.time() - t0
            if progress is not None:
                progress.update(1)
                progress.set_postfix(loss=f"{ema_loss:.4f}", rays_s=f"{rays_done / max(elapsed, 1e-9):.0f}")
            if step % cfg.log_every == 0 or step == cfg.steps - 1:
                record = {"step": step, "loss": loss_value, "psnr": -10 * math.log10(max(loss_value, 1e-10)),
                          "loss_ema": ema_loss, "lr": cfg.lr * factor,
                          "time": elapsed_before + elapsed, "rays_per_s": rays_done / max(elapsed, 1e-9)}
                with log_path.open("a") as f:
                    f.write(json.dumps(record) + "\n")
            done = step == cfg.steps - 1
            out_of_time = max_seconds is not None and elapsed > max_seconds
            if (step + 1) % cfg.ckpt_every == 0 or done or out_of_time:
                save_checkpoint(ckpt_path, model, optimizer=optimizer.state_dict(), step=step + 1,
                                elapsed=elapsed_before + elapsed, train_config=dataclasses.asdict(cfg))
            if out_of_time:
                break
    if progress is not None:
        progress.close()
    if world > 1:
        dist.barrier()
        dist.destroy_process_group()
    return ckpt_path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="iris-train", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="run directory (checkpoints, log.jsonl)")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/last.pt if it exists")
    parser.add_argument("--threads", type=int, default=None, help="torch intra-op threads per process")
    parser.add_argument("--max-minutes", type=float, default=None,
                        help="stop (with a checkpoint) after this wall time; --resume continues")
    for field in dataclasses.fields(TrainConfig):
        parser.add_argument("--" + field.name.replace("_", "-"), type=type(field.default),
                            default=field.default, help=f"(default: {field.default})")
    args = parser.parse_args(argv)
    cfg = TrainConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig)})
    try:
        preset(cfg.preset)   # fail early on a bad preset name
    except InputError as exc:
        parser.error(str(exc))
    path = train(cfg, args.out, resume=args.resume, threads=args.threads,
                 max_seconds=None if args.max_minutes is None else 60 * args.max_minutes)
    if int(os.environ.get("RANK", "0")) == 0:
        print(f"checkpoint: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
