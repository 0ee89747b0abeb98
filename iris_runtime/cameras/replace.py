"""A model's predicted cameras replaced by the camera solve of the same photos (what
``IrisRuntime.encode(images, cameras="solve")`` and ``iris-eval``'s torch backend do), or
refined by them (``cameras="refined"``: ``refine.refine_cameras`` started from the model's).

The photos are solved near their own resolution (``images.camera_copies``), and the solved focal
is carried through the centre crop and resize that brought them to the model's resolution. View 0
defines the frame: when the solve cannot pose it, the model's cameras are kept whole.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..images import camera_copies
from .features import canonical_order
from .refine import RefineOptions, refine_cameras
from .solve import CameraSolve, solve_cameras

__all__ = ["ModelCameras", "replace_model_cameras", "refine_model_cameras", "canonical_start"]


@dataclass(frozen=True)
class ModelCameras:
    """world_from_cam [V, 4, 4] (view 0 = I), focal [2] (fx/W, fy/H) and K [3, 3] at the model's
    resolution; source "solve" (every view posed by the solve), "refined" (every view's
    camera refined from the model's), "mixed" (the unposed views keep the model's camera) or
    "model"; status per view (``STATUSES``); camera_size (H, W) the
    solve ran at (None with source "model"); solve the ``CameraSolve`` (None with "model")."""
    world_from_cam: np.ndarray
    focal: np.ndarray
    K: np.ndarray
    source: str
    status: tuple[str, ...]
    camera_size: tuple[int, int] | None
    solve: CameraSolve | None


def replace_model_cameras(photos, world_from_cam, focal, image_size: tuple[int, int],
                          depth_range: tuple[float, float]) -> ModelCameras:
    """The model's cameras (``world_from_cam [V, 4, 4]``, ``focal`` [2] fx/W, fy/H at the model's
    ``image_size`` (H, W)) replaced by ``solve_cameras`` of ``photos`` (V uint8 RGB arrays, any
    size: the ones the model's inputs were cut from), in the renderer's ``depth_range``."""
    model, model_focal, model_K = _model(world_from_cam, focal, image_size)
    copies, model_from_camera = camera_copies([np.asarray(p) for p in photos], image_size)
    return _replaced(solve_cameras(copies, depth_range), "solve", model, model_focal, model_K,
                     model_from_camera, image_size)


def refine_model_cameras(photos, world_from_cam, focal, image_size: tuple[int, int],
                         depth_range: tuple[float, float], *,
                         refinement: RefineOptions | None = None) -> ModelCameras:
    """As ``replace_model_cameras``, but the cameras are ``refine_cameras`` of the photos started
    from the model's: the same photos' copies, the model's focal carried to their pixels. Where
    the refinement cannot constrain the cameras or finds no start to agree with (it returns
    None), or leaves view 0 (the frame) unposed, the solve replaces them. ``refinement``: the
    refinement's settings (default ``RefineOptions()``)."""
    model, model_focal, model_K = _model(world_from_cam, focal, image_size)
    copies, model_from_camera = camera_copies([np.asarray(p) for p in photos], image_size)
    camera_K = np.linalg.inv(model_from_camera) @ model_K
    solve = refine_cameras(copies, model, float(camera_K[0, 0]), depth_range,
                           refinement=refinement)
    if solve is None or solve.status[0] == "unposed":
        return _replaced(solve_cameras(copies, depth_range), "solve", model, model_focal,
                         model_K, model_from_camera, image_size)
    return _replaced(solve, "refined", model, model_focal, model_K, model_from_camera, image_size)


def canonical_start(photos, world_from_cam, focal, encode) -> tuple[np.ndarray, np.ndarray]:
    """The camera head's cameras of ``photos`` as it predicts them with the photos in
    ``canonical_order``, put back in the photos' order and re-based on view 0, and its focal:
    the start ``refine_model_cameras`` then does not depend on the order the photos came in (the
    head's cameras do: view 0 is their frame). ``world_from_cam [V, 4, 4]``, ``focal`` [2]: the
    head's in the given order, used as they are when that order is the canonical one;
    ``encode(perm) -> (world_from_cam [V, 4, 4], focal [2])``: the head on the photos taken in
    the order ``perm``."""
    perm = canonical_order([np.asarray(p) for p in photos])
    if np.array_equal(perm, np.arange(len(perm))):
        return np.asarray(world_from_cam, np.float64), np.asarray(focal, np.float64)
    poses, head_focal = encode(perm)
    out = np.empty((len(perm), 4, 4))
    out[perm] = np.asarray(poses, np.float64)
    out = np.linalg.inv(out[0]) @ out
    out[0] = np.eye(4)
    return out, np.asarray(head_focal, np.float64)


def _model(world_from_cam, focal, image_size):
    H, W = image_size
    model = np.array(world_from_cam, dtype=np.float64)
    model_focal = np.asarray(focal, dtype=np.float64).reshape(2)
    model_K = np.array([[model_focal[0] * W, 0.0, W / 2.0], [0.0, model_focal[1] * H, H / 2.0],
                        [0.0, 0.0, 1.0]])
    return model, model_focal, model_K


def _replaced(solve: CameraSolve, source: str, model, model_focal, model_K, model_from_camera,
              image_size) -> ModelCameras:
    """``solve``'s cameras at the model's resolution, the model's where it posed none, and the
    model's whole when it could not pose view 0 (which defines the frame)."""
    H, W = image_size
    V = len(model)
    if solve.status[0] == "unposed":
        return ModelCameras(model, model_focal, model_K, "model", ("unposed",) * V, None, None)
    posed = solve.posed
    poses = np.where(posed[:, None, None], solve.world_from_cam, model)
    poses[0] = np.eye(4)
    K = model_from_camera @ solve.K
    return ModelCameras(poses, np.array([K[0, 0] / W, K[1, 1] / H]), K,
                        source if posed.all() else "mixed", solve.status, solve.image_size,
                        solve)
