"""iris-eval: novel view synthesis (PSNR, SSIM) and relative pose accuracy (RPA) of an IRIS model.

    iris-eval runs/tiny/last.pt synthetic:heldout --json eval.json
    iris-eval out/ my_scenes/ --scenes 10 --grid grid.png      # an exported model, users' data

MODEL is a training checkpoint (``.pt``, run in torch) or an exported model directory (holding
``iris.json``, run with ``iris_runtime.IrisRuntime``: the numbers of what is served). DATA is
``synthetic:heldout`` (the held-out synthetic scenes ``iris_train.data.HELDOUT_SEEDS``, rendered
once and cached) or a folder of scene folders (``iris_train.data.load_dataset_folder``; cameras
optional). The metrics themselves (``iris_train.metrics``) are numpy + OpenCV only.

Protocol (DESIGN.md "Evaluation protocol", the paper's appendix scaled down):

- A scene has N = 8 frames (``--views``) in trajectory order. Scenes with more frames are
  subsampled evenly along the stored order; scenes with fewer are skipped.
- Fixed split: targets are frames ``TARGET_FRAMES = (1, 4, 6)``, references the others
  (0, 2, 3, 5, 7); for N != 8 see ``split_frames``.
- References are encoded isolated: the scene (features, cameras, focal) is ``encode`` of the
  reference frames alone, so no target image reaches it. The targets are *queries*: their poses
  are predicted from the target images in the references' frame by ``locate``
  (``IrisRuntime.locate`` for an exported model, ``IrisModel.locate`` for a checkpoint: one encoder
  run over references + targets in which a target sees the references and itself only). The
  targets are rendered from the references at their located poses, at the model's resolution,
  and compared with the target images: PSNR and SSIM (``iris_train.metrics``), per image,
  averaged over targets, then over scenes.
- Pose: RPA@5/15/30 of the N predicted poses (references from ``encode``, targets from
  ``locate``) against the ground truth over all frame pairs; and **locate RPA**
  (``locate_rpa@5/15/30``) over the pairs that involve at least one target (target-reference and
  target-target pairs: 18 of the 28 at N = 8), i.e. every pair whose relative pose depends on a
  located camera. The identity-pose baseline reports both too.
- Soft depth: ``depth_spearman`` (``iris_train.metrics.depth_spearman``), the Spearman rank
  correlation of each target's rendered soft depth with its true depth over the pixels that see
  geometry (true depth > 0), averaged over targets, then over scenes. Only scenes with a true
  depth count (the synthetic ones; users' folders have none: ``null`` when no scene has one); a
  target with fewer than 3 such pixels or a constant depth map is left out of its scene's mean.
- Two input orders: **Seq** (frames as stored) and **Rand** (a fixed per-scene permutation from
  ``RAND_SEED`` and the scene's index, ``presentation_order``). Targets and references are the same
  frames in both; in Rand the references are presented to ``encode`` in the order they take in the
  permutation, so the first reference of the permutation becomes the canonical frame (view 0 must
  be a reference; RPA does not depend on the world frame), and the targets are located in their
  permutation order (queries do not see each other, so that order does not matter).
- Baselines on the same scenes and frames: *nearest reference* (the reference image whose
  ground-truth camera is closest to the target's: rotation angle in radians + centre distance
  divided by the mean distance of the scene's camera centres from their centroid; see
  ``nearest_reference``) and *mean colour* (every pixel the mean RGB of the reference images)
  for NVS; *identity poses* (all cameras predicted at the canonical one) for RPA. With the
  zero-translation convention of ``iris_train.metrics`` identity poses score 0 on every pair
  whose cameras are not at the same place.
- Scenes without ground-truth cameras (users' folders) count towards the model's PSNR/SSIM and the
  mean-colour baseline only; pose metrics and the nearest-reference baseline average over the
  scenes with cameras (``null`` in the JSON when there are none).
- ``--cameras epipolar``: the references' cameras (and the focal) are the global epipolar solve
  of the reference images, scaled to the model's units (``iris_runtime.epipolar.refine_cameras``:
  ``IrisRuntime.encode(images, cameras="epipolar")`` for an exported model, the same function on
  the torch model's poses and focal for a checkpoint), and the targets are posed by
  ``iris_runtime.epipolar.locate_views`` against those fixed reference cameras (a target with
  fewer than two trusted links to the references keeps the model's located pose); ``--locate
  model`` keeps the model's ``locate`` for the targets instead. The JSON then says per order how
  many scenes got which camera source and the fraction of targets the epipolar solve posed.
- LPIPS is left out: it needs pretrained network weights that cannot be fetched here.

PSNR per image is capped at ``PSNR_CAP`` dB (an identical image would otherwise give inf).
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import warnings
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from iris_runtime.fileio import atomic_write_bytes, atomic_write_json

from .metrics import RPA_THRESHOLDS, depth_spearman, psnr, rpa, ssim

__all__ = ["evaluate", "split_frames", "rand_permutation", "presentation_order", "nearest_reference",
           "format_table",
           "load_scenes", "load_evaluable", "TARGET_FRAMES", "DEFAULT_VIEWS", "RAND_SEED", "ORDERS",
           "PSNR_CAP", "write_json", "save_grid", "main"]

#: Target frames of an 8-frame scene (the fixed split); the other frames are references.
TARGET_FRAMES = (1, 4, 6)
#: Frames per evaluation scene.
DEFAULT_VIEWS = 8
#: Seed of the per-scene "Rand" permutations (``rand_permutation``).
RAND_SEED = 2024
#: Input orders, in the order they are reported.
ORDERS = ("seq", "rand")
#: PSNR of one image is capped here (dB), so that a pixel-identical image stays finite.
PSNR_CAP = 100.0
#: Pixel size (H, W) of the camera picture in ``--grid``.
_CAMERA_PANEL_SIZE = (450, 700)
_RPA_KEYS = tuple(f"rpa@{t:g}" for t in RPA_THRESHOLDS)
_LOCATE_RPA_KEYS = tuple(f"locate_{k}" for k in _RPA_KEYS)


# ----------------------------------------------------------------------------------------------
# Protocol pieces
# ----------------------------------------------------------------------------------------------

def split_frames(n_views: int = DEFAULT_VIEWS) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """``(references, targets)`` frame indices of an ``n_views``-frame scene.

    For 8 frames the targets are ``TARGET_FRAMES``. For other N the same relative positions are
    used: target k of the 8-frame split maps to ``clamp(floor(k * N / 8 + 0.5), 1, N - 1)``
    (duplicates merged), so frame 0 is always a reference. Needs N >= 2.
    """
    if n_views < 2:
        raise ValueError(f"a scene needs at least 2 frames for the split, got {n_views}")
    if n_views == DEFAULT_VIEWS:
        targets = TARGET_FRAMES
    else:
        targets = tuple(sorted({min(max(math.floor(k * n_views / DEFAULT_VIEWS + 0.5), 1), n_views - 1)
                                for k in TARGET_FRAMES}))
    refs = tuple(i for i in range(n_views) if i not in targets)
    return refs, targets


def rand_permutation(n_views: int, scene_index: int, seed: int = RAND_SEED) -> np.ndarray:
    """The fixed "Rand" presentation order of scene ``scene_index``: ``order[p]`` = frame shown at
    position p. Reproducible: ``numpy.random.default_rng([seed, scene_index]).permutation``."""
    return np.random.default_rng([seed, scene_index]).permutation(n_views)


def presentation_order(order: str, references: Sequence[int], targets: Sequence[int],
                       scene_index: int, seed: int = RAND_SEED) -> tuple[list[int], list[int]]:
    """``(reference frames, target frames)`` in the order they are given to ``encode`` and
    ``locate``. "seq": as stored. "rand": the order they take in ``rand_permutation(N, scene_index,
    seed)`` (N = all frames), so the first reference of the permutation is view 0."""
    if order == "seq":
        return list(references), list(targets)
    if order != "rand":
        raise ValueError(f"order: expected one of {ORDERS}, got {order!r}")
    perm = rand_permutation(len(references) + len(targets), scene_index, seed).tolist()
    refs, tgts = set(references), set(targets)
    return [f for f in perm if f in refs], [f for f in perm if f in tgts]


def _locate_rpa(pred: np.ndarray, gt: np.ndarray, targets: Sequence[int]) -> dict[str, float]:
    """RPA over the frame pairs (i < j) that involve at least one of ``targets``."""
    from .metrics import relative_pose_errors
    rot, trans = relative_pose_errors(pred, gt)
    err = np.maximum(rot, trans)
    i, j = np.triu_indices(len(pred), 1)
    is_target = np.isin(np.arange(len(pred)), list(targets))
    pairs = is_target[i] | is_target[j]
    return {f"locate_rpa@{t:g}": float(np.mean(err[pairs] < t)) for t in RPA_THRESHOLDS}


def _rotation_angle(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    cos = (np.einsum("...ij,...ij->...", Ra, Rb) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


def nearest_reference(world_from_cam: np.ndarray, references: Sequence[int],
                      targets: Sequence[int]) -> list[int]:
    """For each target frame, the reference frame with the closest ground-truth camera.

    Distance = rotation angle between the two cameras in radians + distance between their centres
    divided by the scene's camera spread (mean distance of all ``world_from_cam [V, 4, 4]`` centres
    from their centroid; the centre term is dropped when all centres coincide). So one radian of
    turning weighs as much as moving by the typical camera spread, and the choice does not depend
    on the scene's scale or world frame. Ties go to the earlier reference.
    """
    T = np.asarray(world_from_cam, dtype=np.float64)
    centres = T[:, :3, 3]
    spread = np.linalg.norm(centres - centres.mean(0), axis=-1).mean()
    refs = np.asarray(references)
    out = []
    for t in targets:
        angle = _rotation_angle(T[t, :3, :3][None], T[refs, :3, :3])
        dist = np.linalg.norm(centres[refs] - centres[t], axis=-1)
        cost = angle + (dist / spread if spread > 0 else 0.0)
        out.append(int(refs[int(np.argmin(cost))]))
    return out


def _psnr(pred: np.ndarray, gt: np.ndarray) -> float:
    return min(psnr(pred, gt), PSNR_CAP)


def _nvs_scores(preds: Sequence[np.ndarray], gts: Sequence[np.ndarray]) -> dict[str, float]:
    return {"psnr": float(np.mean([_psnr(p, g) for p, g in zip(preds, gts)])),
            "ssim": float(np.mean([ssim(p, g) for p, g in zip(preds, gts)]))}


# ----------------------------------------------------------------------------------------------
# One interface over the torch model and the exported runtime
# ----------------------------------------------------------------------------------------------

class _TorchBackend:
    """``IrisModel`` in torch (a checkpoint)."""

    def __init__(self, model):
        self.model = model
        self.image_size = (model.cfg.image_height, model.cfg.image_width)
        self.depth_range = (model.cfg.near, model.cfg.far)
        self.last_source = "model"
        # A checkpoint loaded by load_evaluable knows the cameras it was trained with.
        self.default_cameras = getattr(model, "trained_cameras", "model")

    def encode(self, images: np.ndarray, cameras: str | None = None):
        """``cameras``: None = ``default_cameras``; ``"epipolar"``: the model's poses and focal replaced by
        ``iris_runtime.epipolar.refine_cameras`` of the images, as ``IrisRuntime.encode`` does."""
        import dataclasses

        import torch
        x = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float() / 255.0
        cameras = self.default_cameras if cameras is None else cameras
        with torch.no_grad():
            scene = self.model.encode(x)
        self.last_source = "model"
        if cameras == "epipolar":
            from iris_runtime.cameras import replace_model_cameras
            ref = replace_model_cameras(np.ascontiguousarray(images), self.poses(scene),
                                        _focal_of(scene), self.image_size, self.depth_range)
            scene = dataclasses.replace(
                scene, world_from_cam=torch.as_tensor(ref.world_from_cam).to(scene.world_from_cam),
                focal=torch.as_tensor(ref.focal).to(scene.focal))
            self.last_source = ref.source
        return scene

    def poses(self, scene) -> np.ndarray:
        return scene.world_from_cam.detach().double().numpy()

    def locate(self, scene, references: np.ndarray, queries: np.ndarray) -> np.ndarray:
        """Poses [Q, 4, 4] of ``queries`` in the frame of ``scene`` = ``encode(references)``."""
        import torch

        def to_tensor(images):
            return torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float() / 255.0
        with torch.no_grad():
            return self.model.locate(to_tensor(references), to_tensor(queries)).double().numpy()

    def render(self, scene, poses: np.ndarray):
        import torch
        H, W = self.image_size
        rgb, depth = self.model.render(scene, torch.as_tensor(poses, dtype=scene.field_maps.dtype), H, W)
        return rgb.double().numpy(), depth.double().numpy()


class _RuntimeBackend:
    """An exported model run by ``iris_runtime.IrisRuntime`` (numpy + onnxruntime)."""

    def __init__(self, runtime):
        self.rt = runtime
        self.image_size, self.depth_range = _runtime_geometry(runtime)
        self.last_source = "model"
        self.default_cameras = getattr(runtime, "default_cameras", "model")

    def encode(self, images: np.ndarray, cameras: str | None = None):
        cameras = self.default_cameras if cameras is None else cameras
        if cameras == self.default_cameras:     # (duck-typed runtimes need not know cameras=)
            scene = self.rt.encode(list(images))
        else:
            scene = self.rt.encode(list(images), cameras=cameras)
        self.last_source = getattr(scene, "camera_source", "model")
        return scene

    def poses(self, scene) -> np.ndarray:
        return np.asarray(scene.world_from_cam, dtype=np.float64)

    def locate(self, scene, references: np.ndarray, queries: np.ndarray) -> np.ndarray:
        """Poses [Q, 4, 4] of ``queries`` in ``scene``'s frame (the scene keeps its references)."""
        return np.asarray(self.rt.locate(scene, list(queries)), dtype=np.float64)

    def render(self, scene, poses: np.ndarray):
        H, W = self.image_size
        rgbs, depths = [], []
        for pose in poses:
            result = self.rt.render(scene, pose, height=H, width=W, depth=True)
            image = getattr(result, "image_float", None)
            if image is None:
                image = np.asarray(getattr(result, "image", result), dtype=np.float64) / 255.0
            rgbs.append(np.asarray(image, dtype=np.float64))
            depth = getattr(result, "depth", None)
            depths.append(np.zeros((H, W)) if depth is None else np.asarray(depth, dtype=np.float64))
        return np.stack(rgbs), np.stack(depths)


def _runtime_geometry(runtime) -> tuple[tuple[int, int], tuple[float, float]]:
    """Model resolution and depth range of an ``IrisRuntime`` (from its manifest)."""
    H, W = runtime.image_size
    return (int(H), int(W)), (float(runtime.near), float(runtime.far))


def _backend(model):
    try:
        from .model import IrisModel
    except ImportError:          # torch missing: only the runtime path is possible
        IrisModel = ()
    if isinstance(model, IrisModel):
        return _TorchBackend(model)
    return _RuntimeBackend(model)


# ----------------------------------------------------------------------------------------------
# Scenes
# ----------------------------------------------------------------------------------------------

def _prepare_scene(scene, views: int, image_size: tuple[int, int]):
    """-> ``(images uint8 [N, H, W, 3] at the model's size, world_from_cam [N, 4, 4] or None)``,
    or None when the scene has fewer than ``views`` frames."""
    images = np.asarray(scene.images)
    if images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise ValueError(f"scene images: expected uint8 [V, H, W, 3], got {images.dtype} {images.shape}")
    poses = getattr(scene, "world_from_cam", None)
    V = images.shape[0]
    if V < views:
        return None
    idx = np.round(np.linspace(0, V - 1, views)).astype(int)
    images = images[idx]
    if poses is not None:
        poses = np.asarray(poses, dtype=np.float64)[idx]
    if images.shape[1:3] != tuple(image_size):
        from iris_runtime.images import fit_to_model
        images = np.stack([fit_to_model(im, *image_size)[0] for im in images])
    return images, poses


def _true_depth_and_K(scene, views: int, image_size: tuple[int, int]):
    """-> ``(true depth float64 [N, H, W] at the model's size or None, K [3, 3] / [N, 3, 3] or None)``
    of the frames ``_prepare_scene`` keeps. A depth of another size gets the same centre crop as
    the images and a nearest-neighbour resize (no depths mixed across edges); K is left as stored
    (only its cx/fx, cy/fy are used, for the camera picture)."""
    depth = getattr(scene, "depth", None)
    K = getattr(scene, "K", None)
    V = np.asarray(scene.images).shape[0]
    idx = np.round(np.linspace(0, V - 1, views)).astype(int)
    if K is not None:
        K = np.asarray(K, dtype=np.float64)
        K = K[idx] if K.ndim == 3 else K
    if depth is None:
        return None, K
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 3 or depth.shape[0] != V:
        return None, K
    depth = depth[idx]
    if depth.shape[1:] != tuple(image_size):
        import cv2

        from iris_runtime.images import plan_crop_resize
        H, W = image_size
        plan = plan_crop_resize(depth.shape[1], depth.shape[2], H, W)
        depth = np.stack([cv2.resize(np.ascontiguousarray(d[plan.y0:plan.y0 + plan.crop_h,
                                                            plan.x0:plan.x0 + plan.crop_w]),
                                     (W, H), interpolation=cv2.INTER_NEAREST) for d in depth])
    return depth, K


def _depth_score(pred_depths: np.ndarray, true_depths: np.ndarray) -> float | None:
    """Mean ``depth_spearman`` over the targets where it is defined, or None."""
    values = [depth_spearman(p, t) for p, t in zip(pred_depths, true_depths)]
    values = [v for v in values if np.isfinite(v)]
    return float(np.mean(values)) if values else None


def _camera_panel(pred_poses: np.ndarray, pred_focal, gt_poses: np.ndarray | None, gt_K,
                  size: tuple[int, int]) -> np.ndarray:
    """Picture of the predicted cameras (``iris_runtime.camera_plot``), moved into the true frame
    by a similarity alignment of their centres when true cameras are known."""
    from iris_runtime.camera_plot import align_poses, draw_cameras
    if gt_poses is None:
        return draw_cameras(pred_poses, pred_focal, size=size, title="predicted cameras")
    aligned, (s, _, _) = align_poses(pred_poses, gt_poses)
    return draw_cameras(aligned, pred_focal, reference=gt_poses, reference_focal=gt_K, size=size,
                        title=f"predicted cameras, similarity-aligned to the true ones (scale {s:.3g})")


def _focal_of(encoded):
    """The normalised focal [fx/W, fy/H] of an encoded scene (torch or runtime), or None."""
    f = getattr(encoded, "focal", None)
    if f is None:
        return None
    if hasattr(f, "detach"):
        f = f.detach().cpu().double().numpy()
    return np.asarray(f, dtype=np.float64)


# ----------------------------------------------------------------------------------------------
# Evaluation
# ----------------------------------------------------------------------------------------------

def _mean_or_none(values: list[float]):
    return float(np.mean(values)) if values else None


def evaluate(model, scenes: Iterable, *, views: int = DEFAULT_VIEWS, seed: int = RAND_SEED,
             grid: str | os.PathLike | None = None, progress: bool = True,
             total: int | None = None, cameras: str | None = None, locate: str | None = None) -> dict:
    """Evaluate ``model`` (an ``IrisModel`` or an ``iris_runtime.IrisRuntime``) on ``scenes``.

    ``scenes``: objects with ``images`` uint8 ``[V, H, W, 3]`` (trajectory order) and
    ``world_from_cam`` ``[V, 4, 4]`` or None (no ground-truth cameras). Images of another size are
    brought to the model's resolution by ``iris_runtime.images.fit_to_model``. The Rand order of
    a scene is ``presentation_order("rand", ..., i, seed)`` (from ``rand_permutation(views, i,
    seed)``) with i its position in ``scenes``. ``grid``:
    write a PNG of the first scene (Seq order). ``total``: number of scenes, for the progress bar.

    Returns ``{"seq": R, "rand": R}`` with ``R = {"model": {"psnr", "ssim", "rpa@5", "rpa@15",
    "rpa@30", "locate_rpa@5", "locate_rpa@15", "locate_rpa@30", "depth_spearman"}, "baselines":
    {"nearest_reference": {"psnr", "ssim"}, "mean_colour": {"psnr", "ssim"}, "identity_poses":
    {"rpa@5", "rpa@15", "rpa@30", "locate_rpa@5", "locate_rpa@15", "locate_rpa@30"}}}``: means
    over scenes (see the module docstring for the protocol; ``depth_spearman`` is None when no
    scene has a true depth). Raises ``ValueError`` when no scene has ``views`` frames.

    ``cameras``: None (default): the cameras the model was trained with (an exported model's
    ``IrisRuntime.default_cameras``, a checkpoint's training config), or "model", or
    "epipolar": the references' cameras (and focal) are the
    global epipolar solve of the reference images scaled to the model's units
    (``iris_runtime.epipolar.refine_cameras``; ``IrisRuntime.encode(images, cameras="epipolar")``
    for an exported model, the same function on the torch model's outputs for a checkpoint).
    ``locate``: how the targets are posed, "model" (``locate``) or "epipolar"
    (``iris_runtime.epipolar.locate_views``: each target's pairwise poses to the references, its
    rotation and centre solved with the references' cameras fixed; a target with fewer than two
    trusted links keeps the model's located pose); default: the value of ``cameras``. With
    anything but model cameras each ``R`` also holds ``"cameras": {"references", "targets",
    "sources": {camera source: scenes}, "targets_epipolar": fraction of targets posed by the
    epipolar solve}``.
    """
    backend = _backend(model)
    cameras = backend.default_cameras if cameras is None else cameras
    if cameras not in ("model", "epipolar"):
        raise ValueError(f"cameras: expected 'model' or 'epipolar', got {cameras!r}")
    locate = cameras if locate is None else locate
    if locate not in ("model", "epipolar"):
        raise ValueError(f"locate: expected 'model' or 'epipolar', got {locate!r}")
    report_cameras = cameras != "model" or locate != "model"
    camera_stats = {order: {"sources": {}, "targets": []} for order in ORDERS}
    refs, targets = split_frames(views)
    refs_a, targets_a = np.asarray(refs), np.asarray(targets)
    training = getattr(model, "training", None)
    if training:
        model.eval()
    acc = {order: {"model": {k: [] for k in ("psnr", "ssim", *_RPA_KEYS, *_LOCATE_RPA_KEYS,
                                             "depth_spearman")},
                   "nearest_reference": {"psnr": [], "ssim": []},
                   "mean_colour": {"psnr": [], "ssim": []},
                   "identity_poses": {k: [] for k in (*_RPA_KEYS, *_LOCATE_RPA_KEYS)}}
           for order in ORDERS}
    n_used, n_skipped = 0, 0
    from tqdm import tqdm
    bar = tqdm(scenes, total=total, desc="iris-eval", unit="scene", disable=not progress,
               dynamic_ncols=True)
    try:
        for index, scene in enumerate(bar):
            prepared = _prepare_scene(scene, views, backend.image_size)
            if prepared is None:
                n_skipped += 1
                continue
            images, gt_poses = prepared
            true_depth, true_K = _true_depth_and_K(scene, views, backend.image_size)
            n_used += 1
            gt_images = images.astype(np.float64) / 255.0
            targets_gt = gt_images[targets_a]

            # Baselines: they see the same frames in either order, so compute them once.
            mean_rgb = gt_images[refs_a].reshape(-1, 3).mean(0)
            mean_scores = _nvs_scores([np.broadcast_to(mean_rgb, g.shape) for g in targets_gt], targets_gt)
            near_scores = None
            if gt_poses is not None:
                nearest = nearest_reference(gt_poses, refs, targets)
                near_scores = _nvs_scores(gt_images[nearest], targets_gt)

            for order in ORDERS:
                ref_order, target_order = presentation_order(order, refs, targets, index, seed)
                # References encoded isolated (view 0 = ref_order[0]); targets located as queries.
                encoded = backend.encode(images[ref_order], cameras=cameras)
                pred = np.empty((views, 4, 4))             # frame order
                pred[ref_order] = backend.poses(encoded)
                located = backend.locate(encoded, images[ref_order], images[target_order])
                solved = np.zeros(len(target_order), dtype=bool)
                if locate == "epipolar":
                    from iris_runtime.cameras import locate_views
                    epi, solved = locate_views(images[ref_order], pred[ref_order],
                                               float(_focal_of(encoded)[0]), images[target_order])
                    located = np.where(solved[:, None, None], epi, located)
                pred[target_order] = located
                stats = camera_stats[order]
                stats["sources"][backend.last_source] = stats["sources"].get(backend.last_source, 0) + 1
                stats["targets"].extend(solved.tolist())
                rgb, depth = backend.render(encoded, pred[targets_a])
                if not (np.isfinite(rgb).all() and np.isfinite(pred).all()):
                    raise ValueError(f"scene {index} ({order}): the model returned NaN or inf "
                                     "(poses or colours); nothing to score")
                rgb = np.clip(rgb, 0.0, 1.0)
                a = acc[order]
                for k, v in _nvs_scores(rgb, targets_gt).items():
                    a["model"][k].append(v)
                for k, v in mean_scores.items():
                    a["mean_colour"][k].append(v)
                if true_depth is not None:
                    score = _depth_score(depth, true_depth[targets_a])
                    if score is not None:
                        a["model"]["depth_spearman"].append(score)
                if gt_poses is not None:
                    # RPA does not depend on the world frame, so frame order serves both orders.
                    identity = np.broadcast_to(np.eye(4), gt_poses.shape)
                    for name, poses in (("model", pred), ("identity_poses", identity)):
                        for k, v in {**rpa(poses, gt_poses),
                                     **_locate_rpa(poses, gt_poses, targets)}.items():
                            a[name][k].append(v)
                    for k, v in near_scores.items():
                        a["nearest_reference"][k].append(v)
                if grid is not None and order == "seq" and n_used == 1:
                    save_grid(grid, gt_images[refs_a], targets_gt, rgb, depth, backend.depth_range,
                              refs, targets,
                              true_depths=None if true_depth is None else true_depth[targets_a],
                              cameras=_camera_panel(pred, _focal_of(encoded), gt_poses, true_K,
                                                    _CAMERA_PANEL_SIZE))
    finally:
        bar.close()
        if training:
            model.train()
    if n_used == 0:
        raise ValueError(f"no scene with at least {views} frames to evaluate"
                         + (f" ({n_skipped} skipped)" if n_skipped else ""))
    if n_skipped:
        warnings.warn(f"iris-eval: skipped {n_skipped} scene(s) with fewer than {views} frames")

    def summary(a, stats):
        out = {"model": {k: _mean_or_none(v) for k, v in a["model"].items()},
               "baselines": {name: {k: _mean_or_none(v) for k, v in a[name].items()}
                             for name in ("nearest_reference", "mean_colour", "identity_poses")}}
        if report_cameras:
            out["cameras"] = {"references": cameras, "targets": locate,
                              "sources": dict(sorted(stats["sources"].items())),
                              "targets_epipolar": _mean_or_none(stats["targets"])}
        return out
    return {order: summary(acc[order], camera_stats[order]) for order in ORDERS}


# ----------------------------------------------------------------------------------------------
# Output: table, JSON, grid
# ----------------------------------------------------------------------------------------------

def format_table(results: dict) -> str:
    """The results as a fixed-width text table (one row per order and method; "-" = not measured).
    DEPTH-RHO is ``depth_spearman``, LOC@t is ``locate_rpa@t``."""
    cols = ("psnr", "ssim", *_RPA_KEYS, *_LOCATE_RPA_KEYS, "depth_spearman")
    labels = {"depth_spearman": "DEPTH-RHO",
              **{k: f"LOC@{t:g}" for k, t in zip(_LOCATE_RPA_KEYS, RPA_THRESHOLDS)}}
    width = {c: max(9, len(labels.get(c, c)) + 1) for c in cols}
    head = f"{'order':<6} {'method':<18}" + "".join(f"{labels.get(c, c.upper()):>{width[c]}}"
                                                     for c in cols)
    lines = [head, "-" * len(head)]
    rows = (("IRIS", lambda r: r["model"]),
            ("nearest reference", lambda r: r["baselines"]["nearest_reference"]),
            ("mean colour", lambda r: r["baselines"]["mean_colour"]),
            ("identity poses", lambda r: r["baselines"]["identity_poses"]))
    for order in ORDERS:
        for name, get in rows:
            values = get(results[order])
            cells = []
            for c in cols:
                v, w = values.get(c), width[c]
                cells.append(f"{'-':>{w}}" if v is None else
                             f"{v:>{w}.2f}" if c == "psnr" else f"{v:>{w}.3f}")
            lines.append(f"{order.capitalize():<6} {name:<18}" + "".join(cells))
    return "\n".join(lines)


def write_json(path: str | os.PathLike, results: dict) -> None:
    """Write ``results`` as JSON atomically (temp file + rename); refuses NaN/inf."""
    atomic_write_json(path, results)


def save_grid(path: str | os.PathLike, references: np.ndarray, targets: np.ndarray,
              renders: np.ndarray, depths: np.ndarray, depth_range: tuple[float, float],
              ref_frames: Sequence[int] | None = None, target_frames: Sequence[int] | None = None,
              *, true_depths: np.ndarray | None = None, cameras: np.ndarray | None = None) -> None:
    """PNG of one scene: reference views; ground-truth targets; renders (with their PSNR); soft
    depth (turbo colour map over the model's [near, far]); the targets' true depth (same colour map
    and range; grey where there is no geometry; the soft depth's title then gives its Spearman
    correlation with it); and a picture of the cameras below (``cameras``: an RGB uint8 image, e.g.
    from ``iris_runtime.camera_plot.draw_cameras``). Images float ``[n, H, W, 3]`` in [0, 1],
    depths ``[n, H, W]``; ``*_frames`` label the columns with frame indices. Written atomically."""
    import matplotlib
    matplotlib.use("Agg")
    import io

    import matplotlib.pyplot as plt
    ref_frames = range(len(references)) if ref_frames is None else ref_frames
    target_frames = range(len(targets)) if target_frames is None else target_frames
    depth_titles = [f"{d.min():.2f}-{d.max():.2f}" for d in depths]
    if true_depths is not None:
        rhos = [depth_spearman(d, t) for d, t in zip(depths, true_depths)]
        depth_titles = [f"{t}, \u03c1 {r:.2f}" if np.isfinite(r) else t
                        for t, r in zip(depth_titles, rhos)]
    rows = [("references", references, [f"frame {i}" for i in ref_frames]),
            ("targets (GT)", targets, [f"frame {i}" for i in target_frames]),
            ("renders", renders, [f"{_psnr(np.clip(r, 0, 1), t):.1f} dB" for r, t in zip(renders, targets)]),
            ("soft depth", depths, depth_titles)]
    if true_depths is not None:
        masked = [np.ma.masked_where(~(np.asarray(t) > 0), t) for t in true_depths]
        rows.append(("true depth", masked,
                     [f"{t.min():.2f}-{t.max():.2f}" if t.count() else "no geometry" for t in masked]))
    ncols = max(len(r[1]) for r in rows)
    cam_rows = 3 if cameras is not None else 0
    fig = plt.figure(figsize=(1.4 * ncols, 1.5 * (len(rows) + cam_rows)))
    gs = fig.add_gridspec(len(rows) + cam_rows, ncols)
    cmap = matplotlib.colormaps["turbo"].with_extremes(bad="0.85")   # no geometry: grey

    def bare(ax):
        ax.set_xticks([])
        ax.set_yticks([])
        for spine in ax.spines.values():
            spine.set_visible(False)

    for r, (label, ims, titles) in enumerate(rows):
        for c in range(ncols):
            ax = fig.add_subplot(gs[r, c])
            bare(ax)
            if c < len(ims):
                if ims[c].ndim == 2:
                    ax.imshow(ims[c], cmap=cmap, vmin=depth_range[0], vmax=depth_range[1])
                else:
                    ax.imshow(np.clip(ims[c], 0, 1))
                ax.set_title(titles[c], fontsize=7)
            if c == 0:
                ax.set_ylabel(label, fontsize=8)
    if cameras is not None:
        ax = fig.add_subplot(gs[len(rows):, :])
        bare(ax)
        ax.imshow(np.asarray(cameras))
        ax.set_ylabel("cameras", fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


# ----------------------------------------------------------------------------------------------
# CLI
# ----------------------------------------------------------------------------------------------

def load_evaluable(path: str | os.PathLike, threads: int | None = None):
    """A checkpoint file -> ``IrisModel``; a directory with ``iris.json`` -> ``IrisRuntime``
    (``threads``: its ONNX Runtime intra-op threads)."""
    path = Path(path)
    if path.is_dir():
        if not (path / "iris.json").is_file():
            from iris_runtime.errors import ManifestError
            raise ManifestError(f"MODEL {str(path)!r} is a directory without iris.json "
                                "(expected an exported model directory or a .pt checkpoint)")
        from iris_runtime import IrisRuntime      # lazily: the runtime is optional here
        return IrisRuntime(path, threads=threads)
    from .model import load_model, read_checkpoint, trained_cameras
    model = load_model(path)
    model.trained_cameras = trained_cameras(read_checkpoint(path))
    return model


#: DATA values naming a synthetic set: the held-out scenes (the record) and the validation scenes
#: (where choices are made; iris_train.data.VALIDATION_SEEDS).
SYNTHETIC_SETS = ("synthetic:heldout", "synthetic:validation")


def load_scenes(data: str, image_size: tuple[int, int], views: int = DEFAULT_VIEWS,
                limit: int | None = None) -> tuple[Iterable, int]:
    """DATA argument -> (scenes, count). ``synthetic:heldout`` / ``synthetic:validation`` render
    the held-out / validation synthetic scenes lazily; anything else is a folder of scene folders (``iris_train.data.load_dataset_folder``)."""
    if data in SYNTHETIC_SETS:
        from . import data as D
        seeds = D.HELDOUT_SEEDS if data == "synthetic:heldout" else D.VALIDATION_SEEDS
        # Rendered on first use and cached on disk (iris_train.data.default_cache_dir).
        scenes = D.SyntheticScenes(list(seeds)[:limit], n_views=views, size=tuple(image_size))
        return (scenes[i] for i in range(len(scenes))), len(scenes)
    from iris_runtime.errors import InputError
    if data.startswith("synthetic:"):
        raise InputError(f"DATA {data!r}: the synthetic sets are {list(SYNTHETIC_SETS)}")
    path = Path(data)
    if not path.is_dir():
        raise InputError(f"DATA {data!r}: not one of {list(SYNTHETIC_SETS)} and not a folder")
    from .data import load_dataset_folder
    scenes = load_dataset_folder(path, size=tuple(image_size))[:limit]
    return scenes, len(scenes)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="iris-eval", description=__doc__.split("\n\n")[0],
                                     epilog="Protocol: see the module docstring of iris_train.evaluate.",
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", metavar="MODEL",
                        help="checkpoint (.pt) or exported model directory (with iris.json)")
    parser.add_argument("data", metavar="DATA",
                        help="'synthetic:heldout' (the record), 'synthetic:validation' (where "
                             "choices are made) or a folder of scene folders")
    parser.add_argument("--json", metavar="FILE", type=Path, default=None,
                        help='write {"seq": ..., "rand": ...} to FILE (atomically)')
    parser.add_argument("--scenes", metavar="N", type=int, default=None,
                        help="evaluate only the first N scenes")
    parser.add_argument("--views", metavar="N", type=int, default=DEFAULT_VIEWS,
                        help=f"frames per scene (default {DEFAULT_VIEWS}; targets {TARGET_FRAMES} at 8)")
    parser.add_argument("--seed", type=int, default=RAND_SEED,
                        help=f"seed of the Rand-order permutations (default {RAND_SEED})")
    parser.add_argument("--grid", metavar="FILE.png", type=Path, default=None,
                        help="write a PNG grid of the first scene (references, targets, renders, "
                             "soft and true depth, predicted vs true cameras)")
    parser.add_argument("--threads", type=int, default=None,
                        help="intra-op threads of torch (checkpoint) or ONNX Runtime (exported "
                             "model); default: the library's choice. On a busy machine 1 can be "
                             "much faster than oversubscribed cores")
    parser.add_argument("--cameras", choices=("model", "epipolar"), default=None,
                        help="cameras of the references: the model's or the global epipolar "
                             "solve of their images scaled to the model's units "
                             "(iris_runtime.epipolar.refine_cameras); default: the cameras the "
                             "model was trained with (its manifest's or checkpoint's)")
    parser.add_argument("--locate", choices=("model", "epipolar"), default=None,
                        help="poses of the targets: the model's locate, or the epipolar solve "
                             "against the references' cameras (iris_runtime.epipolar."
                             "locate_views; model fallback per target); default: as --cameras")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    if args.scenes is not None and args.scenes < 1:
        parser.error("--scenes must be at least 1")
    if args.views < 2:
        parser.error("--views must be at least 2")

    if args.threads is not None:
        if args.threads < 1:
            parser.error("--threads must be at least 1")
        if not Path(args.model).is_dir():
            import torch
            torch.set_num_threads(args.threads)
    from iris_runtime.errors import IrisError
    try:
        model = load_evaluable(args.model, threads=args.threads)
        backend = _backend(model)
        scenes, count = load_scenes(args.data, backend.image_size, args.views, args.scenes)
        results = evaluate(model, scenes, views=args.views, seed=args.seed, grid=args.grid,
                           progress=not args.no_progress, total=count, cameras=args.cameras,
                           locate=args.locate)
    except (IrisError, ValueError, FileNotFoundError) as exc:   # bad model, data or arguments
        print(f"iris-eval: error: {exc}", file=sys.stderr)
        return 2
    refs, targets = split_frames(args.views)
    print(f"iris-eval: {args.model} on {args.data}: {count} scene(s), {args.views} frames, "
          f"references {refs}, targets {targets}")
    print(format_table(results))
    if "cameras" in results["seq"]:
        for order in ORDERS:
            c = results[order]["cameras"]
            frac = c["targets_epipolar"]
            print(f"{order.capitalize()}: references' cameras {c['references']} (scenes by source: "
                  f"{c['sources']}), targets {c['targets']}"
                  + ("" if frac is None or c["targets"] == "model" else
                     f" ({100 * frac:.0f}% of targets posed by the epipolar solve)"))
    if args.json is not None:
        write_json(args.json, results)
        print(f"wrote {args.json}")
    if args.grid is not None:
        print(f"wrote {args.grid}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
