"""The batches of an ``iris-train`` step: random scenes, a random subset of their views in random
order (view 0 of that order is the canonical frame), split at random into reference and target
views, random target pixels and stratified sample depths (``draw_batch``); with the run's
cameras from the camera solve, only solved views and their cameras (``draw_solved``). One
``numpy`` generator draws everything, so a batch is a function of the generator's seed.
"""
from __future__ import annotations

import cv2
import numpy as np
import torch

from iris_runtime.geometry import sample_depths

from .config import ModelConfig, TrainConfig


def _as_batch(images: list) -> torch.Tensor:
    """uint8 ``[V, H, W, 3]`` per scene -> float ``[B, V, 3, H, W]`` in [0, 1]."""
    return torch.as_tensor(np.stack(images)).permute(0, 1, 4, 2, 3).float() / 255.0


def _teacher_in_order(pp, order: np.ndarray) -> tuple:
    """A scene's pair teacher restricted to the views ``order``, in that order:
    ``(cam_from_cam [n, n, 4, 4], trusted [n, n], focal)``."""
    sel = np.ix_(order, order)
    return (torch.as_tensor(pp.cam_from_cam[sel], dtype=torch.float32),
            torch.as_tensor(pp.trusted[sel]), pp.focal)


#: Draws of a scene before a step gives up looking for one with enough solved views.
MAX_SCENE_DRAWS = 100


def draw_solved(scenes, solutions, rng: np.random.Generator, n_views: int):
    """A random scene with at least ``n_views`` solved views and a random order of ``n_views`` of
    them -> ``(index, order, (world_from_cam [n, 4, 4], focal [2]) in the order's frame)``."""
    for _ in range(MAX_SCENE_DRAWS):
        index = int(rng.integers(len(scenes)))
        sc = solutions(index)
        views = np.flatnonzero(sc.solved)
        if len(views) >= n_views:
            order = rng.permutation(views)[:n_views]
            return index, order, (torch.as_tensor(sc.rebased(order), dtype=torch.float32),
                                  torch.full((2,), sc.focal, dtype=torch.float32))
    raise RuntimeError(f"no scene with {n_views} solved views in {MAX_SCENE_DRAWS} draws")


def draw_batch(scenes, cfg: TrainConfig, mcfg: ModelConfig, rng: np.random.Generator, teachers=None,
               solutions=None, colour_scenes=None):
    """Random scenes, views, split, target pixels and stratified depths for one step; with
    ``teachers`` (scene index -> PseudoPoses), each scene's teacher in the drawn view order; with
    ``solutions`` (scene index -> SolvedCameras), only solved views are drawn and each scene's
    solved cameras come along in the drawn order (else None); with ``colour_scenes`` (the same
    scenes at ``cfg.colour_size``), the rendered scenes' views come from it, the model's images
    are those area-downsampled, target pixels index the larger grid and the larger views come
    last (``PhotometricLoss.forward``'s ``colour_images``; else None)."""
    n_views = int(rng.integers(cfg.views_min, cfg.views_max + 1))
    n_tgt = int(rng.integers(cfg.targets_min, cfg.targets_max + 1))
    H, W = mcfg.image_height, mcfg.image_width
    S = cfg.train_samples or mcfg.samples
    images, ref, tgt, pixels, depths, teacher, solved = [], [], [], [], [], [], []
    colour_images = []
    if colour_scenes is not None:
        H = W = cfg.colour_size
    for _ in range(cfg.scenes_per_step):
        if solutions is not None:
            index, order, cams = draw_solved(scenes, solutions, rng, n_views)
            solved.append(cams)
            data = scenes[index]
        else:
            index = int(rng.integers(len(scenes)))
            data = scenes[index]
            order = rng.permutation(data.images.shape[0])[:n_views]    # random order: "Rand"
        if colour_scenes is None:
            images.append(data.images[order])
        else:
            large = colour_scenes[index].images[order]
            colour_images.append(large)
            images.append(np.stack([cv2.resize(v, (mcfg.image_width, mcfg.image_height),
                                               interpolation=cv2.INTER_AREA) for v in large]))
        if teachers is not None:
            teacher.append(_teacher_in_order(teachers(index), order))
        # View 0 of the drawn order is the canonical frame, so it is always a reference.
        roles = 1 + rng.permutation(n_views - 1)
        tgt.append(torch.as_tensor(np.sort(roles[:n_tgt])))
        ref.append(torch.as_tensor(np.sort(np.concatenate([[0], roles[n_tgt:]]))))
        n = cfg.rays_per_scene // n_tgt
        pixels.append(torch.as_tensor(rng.integers(0, H * W, size=(n_tgt, n))))
        depths.append(torch.as_tensor(sample_depths(mcfg.near, mcfg.far, S, n_tgt * n,
                                                    stratified=True, rng=rng, dtype=np.float32)))
    pose_batch = None
    if cfg.teacher_scenes and (solutions is not None or teachers is not None):
        pose_batch = _draw_pose_batch(scenes, cfg.teacher_scenes, n_tgt, rng, teachers, solutions)
    return (_as_batch(images), ref, tgt, pixels, depths, (teacher if teachers is not None else None), pose_batch,
            solved if solutions is not None else None,
            _as_batch(colour_images) if colour_scenes is not None else None)


def _draw_pose_batch(scenes, n_scenes: int, n_tgt: int, rng: np.random.Generator, teachers=None,
                     solutions=None) -> tuple:
    """``TrainConfig.teacher_scenes`` extra scenes for the camera terms only, all their views
    in random order, the last ``n_tgt`` of them queries as in rendering ->
    ``(images [P, V, 3, H, W], is_reference [P, V], targets)``: per scene its solved cameras
    (``solutions``, every view solved) or else its pair teacher (``teachers``) in that order."""
    pose_images, pose_targets = [], []
    for _ in range(n_scenes):
        if solutions is not None:                    # every view solved
            index, order, target = draw_solved(scenes, solutions, rng, scenes[0].images.shape[0])
        else:
            index = int(rng.integers(len(scenes)))
            order = rng.permutation(scenes[index].images.shape[0])
            target = _teacher_in_order(teachers(index), order)
        pose_images.append(scenes[index].images[order])
        pose_targets.append(target)
    V = pose_images[0].shape[0]
    pose_ref = torch.ones(n_scenes, V, dtype=torch.bool)
    pose_ref[:, V - n_tgt:] = False          # the last n_tgt views are queries, as in rendering
    return _as_batch(pose_images), pose_ref, pose_targets
