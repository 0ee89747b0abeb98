"""Step 4 of the camera solve: 3D points of tracks seen by posed views, and the checks a point
must pass to be kept (in front of its cameras, reprojected within a few pixels, seen under a
wide enough angle to carry depth)."""
from __future__ import annotations

import numpy as np

from .bundle import reprojection_errors

__all__ = ["triangulate", "max_ray_angles", "camera_centres"]


def camera_centres(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Centres [V, 3] in the world of cam_from_world poses ``R [V, 3, 3]``, ``t [V, 3]``."""
    return -np.einsum("vji,vj->vi", R, t)


def max_ray_angles(points: np.ndarray, centres: np.ndarray, use: np.ndarray) -> np.ndarray:
    """The largest angle (degrees) [P] between two rays from the cameras ``centres [V, 3]`` that
    see each point ``points [P, 3]`` (``use [P, V]``); 0 for points seen once."""
    d = points[:, None, :] - centres[None]
    d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-300)
    cos = np.einsum("pvi,pwi->pvw", d, d)
    both = use[:, :, None] & use[:, None, :]
    cos = np.where(both, cos, 1.0)
    return np.degrees(np.arccos(np.clip(cos.min(axis=(1, 2)), -1.0, 1.0)))


def triangulate(R: np.ndarray, t: np.ndarray, focal: float, centre: np.ndarray, uv: np.ndarray,
                use: np.ndarray, *, max_error: float, min_angle: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Points [T, 3] of tracks observed at ``uv [T, V, 2]`` by the views ``use [T, V]`` marks
    (cam_from_world ``R [V, 3, 3]``, ``t [V, 3]``, ``focal`` pixels, principal point ``centre``),
    by the linear (DLT) solution on normalised coordinates, and ``ok [T]``: seen by two views
    or more, in front of every one of them, reprojected within ``max_error`` pixels in each, and
    seen under ``min_angle`` degrees or more."""
    T, V = use.shape
    x = (np.nan_to_num(uv) - centre) / focal                        # [T, V, 2]
    Pm = np.concatenate([R, t[:, :, None]], axis=2)                # [V, 3, 4]
    A = np.concatenate([x[..., 0:1, None] * Pm[None, :, 2:3] - Pm[None, :, 0:1],
                        x[..., 1:2, None] * Pm[None, :, 2:3] - Pm[None, :, 1:2]], axis=2)  # [T, V, 2, 4]
    A = np.where(use[..., None, None], A, 0.0).reshape(T, 2 * V, 4)
    ok = use.sum(1) >= 2
    X = np.zeros((T, 3))
    if ok.any():
        _, _, Vt = np.linalg.svd(A[ok])
        h = Vt[:, -1]
        good = np.abs(h[:, 3]) > 1e-12
        Xi = np.zeros((len(h), 3))
        Xi[good] = h[good, :3] / h[good, 3:]
        X[ok] = Xi
        ok[np.flatnonzero(ok)[~good]] = False
    err, z = reprojection_errors(R, t, focal, centre, X, uv)
    ok &= np.all(~use | ((z > 0) & (err <= max_error)), axis=1)
    if min_angle > 0:                     # every angle passes 0 (arccos lies in [0, pi])
        ok &= max_ray_angles(X, camera_centres(R, t), use) >= min_angle
    return X, ok
