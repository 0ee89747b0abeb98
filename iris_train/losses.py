"""The losses of an ``iris-train`` step: ``PhotometricLoss`` (the model wrapped so that one
forward call computes a step's loss, what DDP needs) and the camera terms it adds, the epipolar
teacher's (``teacher_losses``) and the solved cameras' (``solve_losses``). None reads a camera
label. The terms and their weights: ``TrainConfig``; the runs that chose them: docs/TRAINING.md.
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn

from . import geometry as G
from . import ibr
from .config import TrainConfig
from .model import IrisModel, Scene


def _add(terms: dict[str, list[torch.Tensor]], values: dict[str, torch.Tensor]) -> None:
    for name, value in values.items():
        terms.setdefault(name, []).append(value)


class PhotometricLoss(nn.Module):
    """Wraps the model so that one forward call computes a step's loss (what DDP needs).

    Terms (weights in ``TrainConfig``): the learned renderer's MSE on target rays; the explicit-warp
    auxiliary (``iris_train.ibr``), whose colour is reference RGB sampled at the same ray samples and
    blended by a learned per-sample logit, at full resolution and blurred; optionally the
    parameter-free plane sweep; and the epipolar teacher on the predicted relative cameras. None of
    them reads a camera label. ``forward`` returns the total and a dict of detached terms.
    """

    def __init__(self, model: IrisModel, cfg: TrainConfig):
        super().__init__()
        self.model = model
        self.cfg = cfg
        # Training-only head (saved as the checkpoint's "aux") of the paper renderer's warp
        # auxiliary; explicit-colour models use their own blend weights instead.
        self.sample_logit = None if model.cfg.explicit_rgb else nn.Linear(model.cfg.field_width, 1)

    def aux_parameters(self) -> list:
        return [] if self.sample_logit is None else list(self.sample_logit.parameters())

    def aux_state(self) -> dict:
        return {} if self.sample_logit is None else self.sample_logit.state_dict()

    def forward(self, images: torch.Tensor, ref: list[torch.Tensor], tgt: list[torch.Tensor],
                pixels: list[torch.Tensor], depths: list[torch.Tensor], teacher: list | None = None,
                pose_batch: tuple | None = None, solved: list | None = None,
                colour_images: torch.Tensor | None = None):
        """``images [B, V, 3, H, W]``; per scene b: reference/target view indices, target pixel
        indices ``[T, n]`` into H*W, stratified sample depths ``[T*n, S]``, and the teacher's
        ``(cam_from_cam [V, V, 4, 4], trusted [V, V], focal)`` in the drawn view order (or None);
        ``pose_batch``: ``(images [P, V, 3, H, W], is_reference [P, V], teachers)`` of extra scenes
        that only the teacher losses see (``TrainConfig.teacher_scenes``); ``solved``: per scene
        the solved cameras ``(world_from_cam [V, 4, 4], focal [2])`` in the drawn order, which the
        renderer then uses instead of the head's (``TrainConfig.render_cameras``);
        ``colour_images [B, V, 3, H', W']``: the same views at ``TrainConfig.colour_size``, the
        renderer's colours and targets (``pixels`` then index H'*W'), else ``images`` are."""
        model, cfg = self.model, self.cfg
        B, V = images.shape[:2]
        colour = images if colour_images is None else colour_images
        H, W = colour.shape[-2:]
        is_reference = torch.ones(B, V, dtype=torch.bool)
        for b in range(B):
            is_reference[b, tgt[b]] = False
        # Targets are queries: the references' features and cameras never see a target image.
        features, world_from_cam, focal = model.encode_batch(images, is_reference)
        # The blur spans the same part of the scene whatever the colours' size.
        dilation = 2 * (H // images.shape[-2])
        blurred = (ibr.blur(colour.flatten(0, 1), dilation).reshape(colour.shape)
                   if cfg.aux_blur_weight else None)
        uv_all = G.pixel_centres(H, W, dtype=images.dtype)
        terms: dict[str, list[torch.Tensor]] = {}
        for b in range(B):
            cams, cam_focal = world_from_cam[b], focal[b]
            if solved is not None:
                cams, cam_focal = solved[b]
                _add(terms, solve_losses(world_from_cam[b], focal[b], cams, cam_focal))
            # The scene's image size is the model's (its projections and validity); explicit
            # colours are sampled on a normalised grid, so they may come at any size.
            scene = Scene(model.field.prepare(features[b, ref[b]]), cams[ref[b]], cam_focal,
                          tuple(images.shape[-2:]),
                          colour[b, ref[b]] if model.cfg.explicit_rgb else None)
            _add(terms, self._render_terms(scene, cams[tgt[b]], colour[b], None if blurred is None
                                           else blurred[b], ref[b], tgt[b], uv_all[pixels[b]],
                                           pixels[b], depths[b]))
            if teacher is not None and teacher[b] is not None:
                _add(terms, teacher_losses(world_from_cam[b], focal[b], *teacher[b]))
        if pose_batch is not None:
            for losses in self._pose_terms(*pose_batch, solved=solved is not None):
                _add(terms, losses)
        weights = {"render": 1.0, "warp": cfg.aux_weight, "warp_blur": cfg.aux_blur_weight,
                   "sweep": cfg.plane_sweep_weight, "teacher_rot": cfg.teacher_weight,
                   "teacher_dir": cfg.teacher_translation_weight, "teacher_focal": cfg.teacher_focal_weight,
                   "solve_rot": cfg.solve_rotation_weight, "solve_trans": cfg.solve_translation_weight,
                   "solve_focal": cfg.solve_focal_weight, "distortion": cfg.distortion_weight}
        means = {k: torch.stack(v).mean() for k, v in terms.items()}
        total = sum(weights[k] * v for k, v in means.items())
        return total, {k: float(v.detach()) for k, v in means.items()}

    def _render_terms(self, scene: Scene, target_cams: torch.Tensor, colour: torch.Tensor,
                      blurred: torch.Tensor | None, ref: torch.Tensor, tgt: torch.Tensor,
                      uv: torch.Tensor, idx: torch.Tensor, depths: torch.Tensor) -> dict:
        """One scene's rendering terms: the renderer's MSE ("render") on the target rays through
        pixel centres ``uv [T, n, 2]`` (pixel indices ``idx [T, n]``) of the views ``tgt`` of
        ``colour [V, 3, H, W]`` (their cameras ``target_cams [T, 4, 4]``), the explicit-warp
        auxiliary at full resolution ("warp") and on ``blurred`` ("warp_blur"), and the plane
        sweep ("sweep"), each when its weight is set; ``depths [T*n, S]`` the sample depths."""
        model, cfg = self.model, self.cfg
        H, W = colour.shape[-2:]
        K = scene.intrinsics(H, W)
        origins, directions = G.rays_from_pixels(uv, K, target_cams)
        origins, directions = origins.reshape(-1, 3), directions.reshape(-1, 3)

        def gt_of(source):
            rgb = source[tgt].flatten(2).transpose(1, 2)                            # [T, HW, 3]
            return torch.gather(rgb, 1, idx[..., None].expand(-1, -1, 3)).reshape(-1, 3)

        gt = gt_of(colour)
        f, points, mask, colours = model.field_at(scene, origins, directions, depths)
        rgb, blend_weights = model.renderer(f, points, directions, mask.amax(-1), need_weights=False,
                                            colours=colours)
        out = {"render": ((rgb - gt) ** 2).mean()}
        if cfg.distortion_weight and model.cfg.explicit_rgb:
            span = (depths - model.cfg.near) / (model.cfg.far - model.cfg.near)
            out["distortion"] = distortion(blend_weights, span, 1.0 / depths.shape[-1])
        if cfg.aux_weight or cfg.aux_blur_weight:
            # The explicit-colour model's own blend weights (without its residual head), or,
            # for the paper's renderer, a training-only logit head on the point features.
            logits = (torch.log(blend_weights.clamp_min(1e-30)) if model.cfg.explicit_rgb
                      else self.sample_logit(f)[..., 0])                            # [R, S]
            levels = [(colour, gt, cfg.aux_weight)]
            if blurred is not None:
                levels.append((blurred, gt_of(blurred), cfg.aux_blur_weight))
            for level, (source, target, weight) in enumerate(levels):
                if not weight:
                    continue
                colours, valid = ibr.sample_reference_rgb(source[ref], points, K, scene.world_from_cam)
                mean, _, count = ibr.view_mean(colours, valid)
                out["warp_blur" if level else "warp"] = \
                    ((ibr.blend_render(logits, mean, count) - target) ** 2).mean()
        if cfg.plane_sweep_weight:
            sweep = ibr.plane_sweep_render(colour[ref], scene.world_from_cam, K, origins,
                                           directions, depths)
            out["sweep"] = ((sweep - gt) ** 2).mean()
        return out

    def _pose_terms(self, pose_images: torch.Tensor, pose_ref: torch.Tensor, targets: list,
                    solved: bool) -> list[dict]:
        """The camera terms of the extra scenes ``pose_images [P, V, 3, H, W]`` (references
        ``pose_ref [P, V]``), one dict per scene: against the solved cameras of ``targets`` when
        ``solved``, else against their pair teachers. The encoder is cheap next to the renderer,
        so the teacher's pairs per step multiply at a small cost."""
        _, world_from_cam, focal = self.model.encode_batch(pose_images, pose_ref)
        losses = solve_losses if solved else teacher_losses
        return [losses(world_from_cam[b], focal[b], *target) for b, target in enumerate(targets)]


def distortion(weights: torch.Tensor, s: torch.Tensor, interval: float) -> torch.Tensor:
    """Mip-NeRF 360's distortion loss, mean over rays: ``weights [R, S]`` of samples at
    normalised ray positions ``s [R, S]`` (each the centre of a stretch ``interval`` long):
    sum_ij w_i w_j |s_i - s_j| + sum_i w_i^2 interval / 3. Zero only for all the weight in one
    point; spreading it over the ray, or over two surfaces, costs in proportion to their
    distance."""
    spread = (weights[:, :, None] * weights[:, None, :]
              * (s[:, :, None] - s[:, None, :]).abs()).sum((1, 2))
    return (spread + (weights ** 2).sum(-1) * interval / 3).mean()


#: Translations shorter than this (model units; scene baselines are ~0.1-0.5) count as "no
#: direction yet": unit(t) = t / sqrt(|t|^2 + floor^2) keeps the direction loss's gradient bounded
#: while the cameras sit near one point (a smaller floor let it dwarf the rotation term's:
#: docs/TRAINING.md, "Diagnosis of R3").
DIRECTION_FLOOR = 0.05


def teacher_losses(world_from_cam: torch.Tensor, focal: torch.Tensor, cam_from_cam: torch.Tensor,
                   trusted: torch.Tensor, teacher_focal: float) -> dict[str, torch.Tensor]:
    """Epipolar pseudo-pose losses of one scene's predicted ``world_from_cam [V, 4, 4]`` and
    ``focal [2]``: over the trusted ordered pairs (a, b), rotation ``1 - cos`` of the angle between
    the predicted and the teacher's cam_b_from_cam_a, and ``|unit(t_pred) - t_teacher|^2 / 2`` on the
    translation direction (the teacher knows no scale; the photometric terms set it)."""
    pred = G.compose(G.invert_pose(world_from_cam)[None, :], world_from_cam[:, None])   # [a, b]: b <- a
    w = trusted.to(pred.dtype)
    n = w.sum().clamp_min(1.0)
    R_pred, R_t = pred[..., :3, :3], cam_from_cam[..., :3, :3]
    cos = ((R_pred * R_t).sum((-1, -2)) - 1) / 2
    t = pred[..., :3, 3]
    unit = t / torch.sqrt((t ** 2).sum(-1, keepdim=True) + DIRECTION_FLOOR ** 2)
    out = {"teacher_rot": ((1 - cos) * w).sum() / n,
           "teacher_dir": (((unit - cam_from_cam[..., :3, 3]) ** 2).sum(-1) / 2 * w).sum() / n}
    out["teacher_focal"] = ((torch.log(focal) - math.log(teacher_focal)) ** 2).mean()
    return out


def solve_losses(world_from_cam: torch.Tensor, focal: torch.Tensor, solved_world_from_cam: torch.Tensor,
                 solved_focal: torch.Tensor) -> dict[str, torch.Tensor]:
    """The camera head's predicted ``world_from_cam [V, 4, 4]`` and ``focal [2]`` against one scene's
    solved cameras in the same frame (view 0 = I, the solve's unit): per view 1..V-1, rotation
    ``1 - cos`` of the angle between the two and the squared distance of the centres; the squared
    log focal error."""
    R, R_s = world_from_cam[1:, :3, :3], solved_world_from_cam[1:, :3, :3]
    cos = ((R * R_s).sum((-1, -2)) - 1) / 2
    centre = ((world_from_cam[1:, :3, 3] - solved_world_from_cam[1:, :3, 3]) ** 2).sum(-1)
    return {"solve_rot": (1 - cos).mean(), "solve_trans": centre.mean(),
            "solve_focal": ((torch.log(focal) - torch.log(solved_focal)) ** 2).mean()}
