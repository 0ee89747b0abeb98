"""iris-train: self-supervised training of IRIS on multi-view images (no camera labels).

Each step draws scenes, a random subset of their views in random order (view 0 of that order is the
canonical frame), splits the views at random into reference and target views, predicts cameras for
all of them, renders a random subset of target rays from the reference views only, and minimises the
photometric MSE. AdamW with linear warm-up and cosine decay; the encoder and camera head run at
``encoder_lr_scale`` (paper: 0.1x) of the renderer's learning rate; gradients clipped.

    iris-train --preset tiny --steps 20000 --out runs/tiny
    torchrun --nproc_per_node=2 -m iris_train.train --preset tiny --steps 100 --out runs/ddp

``--render-cameras solve`` renders with each training scene's whole-scene camera solve
(``pseudo_poses.load_or_solve``, the cameras ``IrisRuntime.encode(cameras="solve")`` gives the
renderer at inference) instead of the head's, and distils the head on the same cameras; with
``--init CKPT`` it fine-tunes a trained model (models/README.md has the command of the shipped one).

``--camera-head {tokens,correlation}`` picks the camera head of the model (``ModelConfig.camera_head``;
default: the preset's, or the head of the ``--init`` / ``--resume`` checkpoint). ``--init`` from a
"tokens" checkpoint with ``--camera-head correlation`` loads every weight the two models share and
starts the correlation head's own parameters fresh (``load_init_weights``).

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
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.nn as nn

from iris_runtime.cameras import DEPTH_TARGET
from iris_runtime.errors import InputError
from iris_runtime.manifest import CAMERAS, camera_name

from . import pseudo_poses
from .batches import draw_batch
from .config import CAMERA_HEADS, ModelConfig, TrainConfig, preset
from .losses import PhotometricLoss
from .model import IrisModel, build_model, read_checkpoint, save_checkpoint
from .scene_sets import colour_size_scenes, per_scene, training_scenes


def lr_factor(step: int, cfg: TrainConfig) -> float:
    if step < cfg.warmup:
        return (step + 1) / cfg.warmup
    progress = min(1.0, (step - cfg.warmup) / max(1, cfg.steps - cfg.warmup))
    return cfg.min_lr_ratio + (1 - cfg.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress))


def make_optimizer(model: IrisModel, cfg: TrainConfig, extra: list | None = None) -> torch.optim.AdamW:
    """AdamW over the model (encoder + camera head at ``encoder_lr_scale``, the fine-feature
    stem and the colour-deviation map at ``fine_lr_scale``) and ``extra`` training-only
    parameters (at the renderer's rate)."""
    cameras = list(model.camera_head.parameters())
    if model.camera_encoder is not None:
        cameras += list(model.camera_encoder.parameters())
    if cfg.freeze_cameras:
        for p in cameras:
            p.requires_grad_(False)
        cameras = []
    slow = list(model.encoder.parameters()) + cameras
    # The parts a fine-tune may start fresh beside a trained field (FRESH_WHEN_CHANGED's
    # renderer parts) learn at fine_lr_scale.
    fine = [] if model.fine_features is None else list(model.fine_features.parameters())
    if model.field.deviation_to_maps is not None:
        fine += list(model.field.deviation_to_maps.parameters())
    fresh = {id(p) for p in fine}
    fast = [p for p in [*model.field.parameters(), *model.renderer.parameters(), *(extra or [])]
            if id(p) not in fresh]

    def split(params):   # no weight decay on norms and biases
        return ([p for p in params if p.ndim >= 2], [p for p in params if p.ndim < 2])

    groups = []
    # Their groups only where the model has such parts: an older run's optimiser state resumes.
    parts = [(slow, cfg.encoder_lr_scale), (fast, 1.0)]
    if fine:
        parts.append((fine, cfg.fine_lr_scale))
    for params, scale in parts:
        decay, no_decay = split(params)
        groups += [{"params": decay, "weight_decay": cfg.weight_decay, "lr_scale": scale},
                   {"params": no_decay, "weight_decay": 0.0, "lr_scale": scale}]
    return torch.optim.AdamW(groups, lr=cfg.lr, betas=(0.9, 0.95))


def _last_focal(model: IrisModel):
    """The focal bias of the camera head's output (what the focal is for a zero token): a cheap
    log line showing whether the focal drifts to a bound."""
    head = model.camera_head
    with torch.no_grad():
        z = head.focal_mlp[-1].bias
        return torch.exp(head.log_focal_min + head.log_focal_range * torch.sigmoid(z)).tolist()


def model_config(cfg: TrainConfig, start: dict | None = None) -> ModelConfig:
    """The run's model config: preset ``cfg.preset`` with the camera head ``cfg.camera_head``,
    or, when that is "", the head of the checkpoint the run starts from (``start``: its config
    dict; a checkpoint without the field has the token head), else the preset's own."""
    base = preset(cfg.preset)
    if cfg.blend_angle:
        base = dataclasses.replace(base, blend_angle=cfg.blend_angle)
    if cfg.map_scale:
        base = dataclasses.replace(base, map_scale=cfg.map_scale)
    if cfg.colour_deviation:
        base = dataclasses.replace(base, colour_deviation=True)
    if cfg.far:
        # The unit stays the preset's: the scene's median depth where the preset puts it.
        base = dataclasses.replace(base, far=cfg.far, median_depth=base.median_depth or
                                   base.near + (base.unit_range[1] - base.near) * DEPTH_TARGET)
    if cfg.camera_head or not isinstance(start, dict):
        return dataclasses.replace(base, camera_head=cfg.camera_head or base.camera_head)
    # The checkpoint's cameras as they are: its head, and its own camera encoder if it has one.
    return dataclasses.replace(base, camera_head=start.get("camera_head", "tokens"),
                               camera_encoder=bool(start.get("camera_encoder", False)),
                               correlation_scale=start.get("correlation_scale",
                                                           base.correlation_scale))


#: The model settings that hold no weights: a fine-tune (``--init``) may change them freely.
WEIGHTLESS = ("blend_angle", "near", "far", "samples", "median_depth")
#: The model settings a fine-tune (``--init``) may change, each with the state-dict prefix of the
#: parameters that are its own: those start fresh (or are dropped) when the setting changes.
FRESH_WHEN_CHANGED = {"camera_head": "camera_head.", "correlation_scale": "camera_head.",
                      "map_scale": "fine_features.", "colour_deviation": "field.deviation_to_maps."}
#: Of those, the settings that change the shapes of their part's parameters (another
#: correlation grid: the correlation net's first layer; another map scale: the stem's convs).
#: A key of another shape outside these is a mismatch, not a fresh start.
RESHAPES = ("correlation_scale", "map_scale")
#: How ``_load_init``'s note names each part that starts fresh.
PART_NAMES = {"camera_head.": "camera head", "fine_features.": "fine-feature stem",
              "field.deviation_to_maps.": "colour-deviation map"}


def load_init_weights(model: IrisModel, payload: dict, what: str = "init") -> list[str]:
    """Load checkpoint ``payload`` (``read_checkpoint``) into ``model`` for a fine-tune; return
    the state-dict keys left at their fresh initialisation (sorted; empty unless a part changes).

    The checkpoint's model config must be ``model.cfg`` up to ``blend_angle`` (no weights) and
    the settings of ``FRESH_WHEN_CHANGED``: the camera head's (a "tokens" checkpoint into a
    "correlation" model, another correlation grid), ``map_scale`` (a coarse checkpoint into a
    model with the fine-feature stem) and ``colour_deviation``. Same settings: every weight
    loads (strict). Otherwise every weight the two models share by name and shape loads; the
    parameters of a changed setting's part that the checkpoint lacks (or holds in another shape,
    for the settings of ``RESHAPES``) stay fresh, and those the model lacks are dropped. Any
    other missing or unexpected key, or key of another shape, is a ``ValueError`` naming them
    (``what``: its prefix)."""
    try:
        source = ModelConfig.from_dict(payload["config"])
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: unreadable model config ({exc})") from None
    # Settings that hold no weights (the colour blend's angular weighting, the sampled depth
    # range and the cameras' unit): a fine-tune may change them.
    source = dataclasses.replace(source, **{k: getattr(model.cfg, k) for k in WEIGHTLESS})
    mine = {k: getattr(model.cfg, k) for k in FRESH_WHEN_CHANGED}
    if dataclasses.replace(source, **mine) != model.cfg:
        raise ValueError(f"{what} holds another model config than this run's (only "
                         f"{', '.join(WEIGHTLESS)} and {', '.join(FRESH_WHEN_CHANGED)} may differ)")
    state = payload["model"]
    if dataclasses.replace(source, **mine) == source:
        model.load_state_dict(state)
        return []
    own = model.state_dict()
    missing, unexpected = set(own) - set(state), set(state) - set(own)
    reshaped = {k for k in set(own) & set(state) if own[k].shape != state[k].shape}
    changed = {k for k in FRESH_WHEN_CHANGED if getattr(source, k) != mine[k]}
    fresh_parts = tuple({FRESH_WHEN_CHANGED[k] for k in changed})
    reshaped_parts = tuple({FRESH_WHEN_CHANGED[k] for k in changed if k in RESHAPES})
    outside = sorted({k for k in missing | unexpected if not k.startswith(fresh_parts)}
                     | {k for k in reshaped if not k.startswith(reshaped_parts)})
    if outside:
        raise ValueError(f"{what}: the checkpoint does not match the model outside the parts "
                         f"its changed settings own ({', '.join(fresh_parts)}): missing, "
                         f"unexpected or of other shapes {outside[:5]}")
    result = model.load_state_dict({k: v for k, v in state.items()
                                    if k in own and k not in reshaped}, strict=False)
    assert not result.unexpected_keys and set(result.missing_keys) == missing | reshaped
    return sorted(missing | reshaped)


def _setup_distributed() -> tuple[int, int]:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("gloo")
    return (dist.get_rank() if world > 1 else 0), world


def _load_init(loss_module: PhotometricLoss, payload: dict, init: Path, verbose: bool) -> None:
    """Start a fine-tune from checkpoint ``payload`` (read from ``init``): its weights
    (``load_init_weights``) and its warp auxiliary's head when it has one."""
    fresh = load_init_weights(loss_module.model, payload, f"init: {str(init)!r}")
    if fresh and verbose:
        parts = dict(PART_NAMES)
        parts["camera_head."] = f"{loss_module.model.cfg.camera_head!r} camera head"
        new = " and ".join(v for k, v in parts.items() if any(f.startswith(k) for f in fresh))
        print(f"iris-train: --init {init}: {len(fresh)} tensors of the new {new} start fresh",
              file=sys.stderr)
    if loss_module.sample_logit is not None and payload.get("aux"):
        loss_module.sample_logit.load_state_dict(payload["aux"])


def _load_resume(loss_module: PhotometricLoss, optimizer: torch.optim.Optimizer, payload: dict,
                 ckpt_path: Path) -> tuple[int, float]:
    """Continue the run of checkpoint ``payload`` (read from ``ckpt_path``): model, warp
    auxiliary and optimiser state -> (the step to continue from, the seconds trained so far).
    ``ValueError`` when the checkpoint has another camera head than the run's model."""
    model = loss_module.model
    resumed = payload["config"] if isinstance(payload["config"], dict) else {}
    resumed_head = resumed.get("camera_head", "tokens")
    if resumed_head != model.cfg.camera_head:
        raise ValueError(f"resume: {str(ckpt_path)!r} has the {resumed_head!r} camera head, "
                         f"not {model.cfg.camera_head!r} (--camera-head)")
    model.load_state_dict(payload["model"])
    if loss_module.sample_logit is not None:
        loss_module.sample_logit.load_state_dict(payload["aux"])
    optimizer.load_state_dict(payload["optimizer"])
    return int(payload["step"]), float(payload.get("elapsed", 0.0))


def _camera_targets(cfg: TrainConfig, mcfg: ModelConfig, scenes) -> tuple:
    """-> (teachers, solutions), scene index -> the scene's ``PseudoPoses`` / ``SolvedCameras``
    (``pseudo_poses``, cached per scene), for ``draw_batch``: the solved cameras when the
    renderer trains on them (``render_cameras="solve"``), else the pair teacher when a
    teacher term has a weight; None for the other. ``ValueError`` for another
    ``render_cameras``."""
    render_cameras = camera_name(cfg.render_cameras)     # "epipolar": the former "solve"
    if render_cameras not in CAMERAS[:2]:        # "refined" needs a trained head first
        raise ValueError(f"render_cameras: expected one of {CAMERAS[:2]}, got "
                         f"{cfg.render_cameras!r}")
    if render_cameras == "solve":
        depth_range = mcfg.unit_range
        return None, per_scene(scenes,
                               lambda sc, i: pseudo_poses.load_or_solve(sc, i, depth_range),
                               lambda images: pseudo_poses.solve_scene(images, depth_range))
    if cfg.teacher_weight or cfg.teacher_translation_weight or cfg.teacher_focal_weight:
        return per_scene(scenes, pseudo_poses.load_or_estimate, pseudo_poses.estimate), None
    return None, None


def _optimise(step_module: nn.Module, model: IrisModel, optimizer: torch.optim.Optimizer,
              batch: tuple, cfg: TrainConfig, factor: float) -> tuple[float, dict]:
    """One optimiser step on ``batch`` at ``factor`` times each group's learning rate, gradients
    clipped -> (the loss, its terms)."""
    for group in optimizer.param_groups:
        group["lr"] = cfg.lr * factor * group["lr_scale"]
    loss, terms = step_module(*batch)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
    optimizer.step()
    return float(loss.detach()), terms


def _rank0_decides(flag: bool, world: int) -> bool:
    """Rank 0's ``flag`` on every rank: so that every rank stops after the same step (a rank
    that ran one step further would wait forever in DDP's all-reduce)."""
    if world == 1:
        return flag
    value = torch.tensor([float(flag)])
    dist.broadcast(value, src=0)
    return bool(value.item())


def train(cfg: TrainConfig, out: Path, resume: bool = False, scenes=None, threads: int | None = None,
          max_seconds: float | None = None, init: Path | None = None) -> Path:
    """Run (or resume) training; returns the path of the last checkpoint. ``init``: start from
    this checkpoint's weights (a fine-tune: fresh optimiser, step 0; its model config must be
    the preset's up to the camera head, ``load_init_weights``); ``resume`` from ``out/last.pt``
    takes precedence. The model config: ``model_config``."""
    rank, world = _setup_distributed()
    if threads:
        torch.set_num_threads(threads)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / "last.pt"
    resuming = resume and ckpt_path.exists()
    init_payload = read_checkpoint(init) if init is not None and not resuming else None
    resume_payload = read_checkpoint(ckpt_path) if resuming else None
    start = resume_payload or init_payload
    mcfg = model_config(cfg, start["config"] if start is not None else None)
    torch.manual_seed(cfg.seed)
    model = build_model(mcfg)
    loss_module = PhotometricLoss(model, cfg)
    optimizer = make_optimizer(model, cfg, loss_module.aux_parameters())
    start_step, elapsed_before = 0, 0.0
    if init_payload is not None:
        _load_init(loss_module, init_payload, init, verbose=rank == 0)
    if resume_payload is not None:
        start_step, elapsed_before = _load_resume(loss_module, optimizer, resume_payload, ckpt_path)
    model.train()
    if scenes is None:
        scenes = training_scenes(cfg, mcfg)
    colour_scenes = colour_size_scenes(cfg) if cfg.colour_size else None
    teachers, solutions = _camera_targets(cfg, mcfg, scenes)
    step_module: nn.Module = loss_module
    if world > 1:
        step_module = nn.parallel.DistributedDataParallel(step_module)
    log_path = out / "log.jsonl"
    progress = None
    if rank == 0:
        (out / "train_config.json").write_text(json.dumps(dataclasses.asdict(cfg), indent=2))
        from tqdm import tqdm
        progress = tqdm(total=cfg.steps, initial=start_step, desc="iris-train", dynamic_ncols=True,
                        disable=None)
    t0 = time.time()
    ema_loss, rays_done = None, 0
    for step in range(start_step, cfg.steps):
        factor = lr_factor(step, cfg)
        # One generator per (seed, rank, step): a resumed run draws exactly the batches it would have.
        batch = draw_batch(scenes, cfg, mcfg, np.random.default_rng([cfg.seed, rank, step]), teachers,
                           solutions, colour_scenes)
        loss_value, terms = _optimise(step_module, model, optimizer, batch, cfg, factor)
        ema_loss = loss_value if ema_loss is None else 0.98 * ema_loss + 0.02 * loss_value
        rays_done += sum(int(d.shape[0]) for d in batch[4]) * world
        elapsed = time.time() - t0
        out_of_time = _rank0_decides(max_seconds is not None and elapsed > max_seconds, world)
        if rank == 0:
            progress.update(1)
            progress.set_postfix(loss=f"{ema_loss:.4f}", rays_s=f"{rays_done / max(elapsed, 1e-9):.0f}")
            if step % cfg.log_every == 0 or step == cfg.steps - 1:
                record = {"step": step, "loss": loss_value, "psnr": -10 * math.log10(max(loss_value, 1e-10)),
                          "loss_ema": ema_loss, "lr": cfg.lr * factor,
                          "time": elapsed_before + elapsed, "rays_per_s": rays_done / max(elapsed, 1e-9),
                          "terms": terms, "focal": [float(x) for x in _last_focal(model)]}
                with log_path.open("a") as f:
                    f.write(json.dumps(record) + "\n")
            done = step == cfg.steps - 1
            if (step + 1) % cfg.ckpt_every == 0 or done or out_of_time:
                save_checkpoint(ckpt_path, model, optimizer=optimizer.state_dict(), step=step + 1,
                                aux=loss_module.aux_state(),
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
    parser.add_argument("--init", type=Path, default=None,
                        help="fine-tune: start from this checkpoint's weights (fresh optimiser)")
    parser.add_argument("--max-minutes", type=float, default=None,
                        help="stop (with a checkpoint) after this wall time; --resume continues")
    for field in dataclasses.fields(TrainConfig):
        if field.name == "camera_head":
            parser.add_argument("--camera-head", choices=CAMERA_HEADS, default=field.default,
                                help="camera head of the model (default: the --init/--resume "
                                     "checkpoint's, else the preset's)")
            continue
        if isinstance(field.default, bool):
            parser.add_argument("--" + field.name.replace("_", "-"), default=field.default,
                                action=argparse.BooleanOptionalAction)
            continue
        parser.add_argument("--" + field.name.replace("_", "-"), type=type(field.default),
                            default=field.default, help=f"(default: {field.default})")
    args = parser.parse_args(argv)
    cfg = TrainConfig(**{f.name: getattr(args, f.name) for f in dataclasses.fields(TrainConfig)})
    try:
        preset(cfg.preset)   # fail early on a bad preset name
    except InputError as exc:
        parser.error(str(exc))
    path = train(cfg, args.out, resume=args.resume, threads=args.threads, init=args.init,
                 max_seconds=None if args.max_minutes is None else 60 * args.max_minutes)
    if int(os.environ.get("RANK", "0")) == 0:
        print(f"checkpoint: {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
