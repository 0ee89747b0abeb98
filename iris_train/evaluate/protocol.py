"""The fixed parts of the evaluation protocol: which frames are references and targets, the order
they are presented in, and the image baselines the renders are compared with.

numpy only. Shapes: images float ``[n, H, W, 3]`` in [0, 1]; poses ``world_from_cam [V, 4, 4]``
(OpenCV axes, camera-to-world).
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from iris_runtime.errors import InputError

from ..metrics import (PSNR_CAP, RPA_THRESHOLDS, capped_psnr,  # noqa: F401
                       relative_pose_errors, rpa, ssim)

__all__ = ["TARGET_FRAMES", "DEFAULT_VIEWS", "RAND_SEED", "ORDERS", "PSNR_CAP", "RPA_KEYS",
           "LOCATE_RPA_KEYS", "REFERENCE_RPA_KEYS", "HEAD_RPA_KEYS", "split_frames",
           "rand_permutation", "presentation_order", "nearest_reference", "best_reference",
           "locate_rpa", "reference_rpa", "capped_psnr", "nvs_scores"]

#: Target frames of an 8-frame scene (the fixed split); the other frames are references.
TARGET_FRAMES = (1, 4, 6)
#: Frames per evaluation scene.
DEFAULT_VIEWS = 8
#: Seed of the per-scene "Rand" permutations (``rand_permutation``).
RAND_SEED = 2024
#: Input orders, in the order they are reported.
ORDERS = ("seq", "rand")
RPA_KEYS = tuple(f"rpa@{t:g}" for t in RPA_THRESHOLDS)
LOCATE_RPA_KEYS = tuple(f"locate_{k}" for k in RPA_KEYS)
REFERENCE_RPA_KEYS = tuple(f"reference_{k}" for k in RPA_KEYS)
#: The camera head's RPA where other cameras replaced its own: reference pairs only (the head's
#: cameras of a scene are the references'; ``reference_rpa`` with prefix "head_reference_").
HEAD_RPA_KEYS = tuple(f"head_reference_{k}" for k in RPA_KEYS)


def split_frames(n_views: int = DEFAULT_VIEWS) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """``(references, targets)`` frame indices of an ``n_views``-frame scene.

    For 8 frames the targets are ``TARGET_FRAMES``. For other N the same relative positions are
    used: target k of the 8-frame split maps to ``clamp(floor(k * N / 8 + 0.5), 1, N - 1)``
    (duplicates merged), so frame 0 is always a reference. Needs N >= 2 (else ``InputError``).
    """
    if n_views < 2:
        raise InputError(f"views: a scene needs at least 2 frames for the split, got {n_views}")
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
        raise InputError(f"order: expected one of {ORDERS}, got {order!r}")
    perm = rand_permutation(len(references) + len(targets), scene_index, seed).tolist()
    refs, tgts = set(references), set(targets)
    return [f for f in perm if f in refs], [f for f in perm if f in tgts]


def locate_rpa(pred: np.ndarray, gt: np.ndarray, targets: Sequence[int]) -> dict[str, float]:
    """RPA over the frame pairs (i < j) that involve at least one of ``targets``."""
    rot, trans = relative_pose_errors(pred, gt)
    err = np.maximum(rot, trans)
    i, j = np.triu_indices(len(pred), 1)
    is_target = np.isin(np.arange(len(pred)), list(targets))
    pairs = is_target[i] | is_target[j]
    return {f"locate_rpa@{t:g}": float(np.mean(err[pairs] < t)) for t in RPA_THRESHOLDS}


def reference_rpa(pred: np.ndarray, gt: np.ndarray, references: Sequence[int],
                  prefix: str = "reference_") -> dict[str, float]:
    """RPA over the frame pairs (i < j) of two ``references``: ``{prefix + "rpa@5": ...}``;
    with ``locate_rpa``'s pairs, exactly the pairs of ``rpa``. ``pred, gt [V, 4, 4]`` over
    frames; rows of other frames are not read (they may be NaN)."""
    refs = sorted(int(r) for r in references)      # pairs i < j, as rpa over all frames
    return {f"{prefix}{k}": v for k, v in rpa(pred[refs], gt[refs]).items()}


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


def best_reference(images: np.ndarray, references: Sequence[int],
                   targets: Sequence[int]) -> list[int]:
    """For each target frame, the reference frame whose image has the highest PSNR
    (``capped_psnr``) against the target's: the best a method that only copies a reference photo
    could do, chosen knowing the target (an oracle, so a bar for scenes without true cameras).
    ``images`` float ``[V, H, W, 3]`` in [0, 1]. Ties go to the earlier reference."""
    refs = [int(r) for r in references]
    out = []
    for t in targets:
        scores = [capped_psnr(images[r], images[t]) for r in refs]
        out.append(refs[int(np.argmax(scores))])
    return out


def nvs_scores(preds: Sequence[np.ndarray], gts: Sequence[np.ndarray]) -> dict[str, float]:
    """Mean ``capped_psnr`` and mean SSIM of images ``preds`` against ``gts``."""
    return {"psnr": float(np.mean([capped_psnr(p, g) for p, g in zip(preds, gts)])),
            "ssim": float(np.mean([ssim(p, g) for p, g in zip(preds, gts)]))}
