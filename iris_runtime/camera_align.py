"""Umeyama's least-squares similarity (1991) between camera centres, with the degenerate cases
made well-defined (``align_similarity``), and the move of predicted poses into the true frame
(``apply_similarity``, ``align_poses``), so that a picture or an error compares like with like:
pose-free predictions have their own frame and scale. numpy only.

    aligned, (s, R, t) = align_poses(pred_world_from_cam, true_world_from_cam)

``iris_runtime.camera_plot`` draws the aligned cameras (and re-exports these names).
"""
from __future__ import annotations

import math

import numpy as np

from .errors import InputError
from .geometry import nearest_rotation

__all__ = ["align_similarity", "apply_similarity", "align_poses"]


def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def _rodrigues(axis: np.ndarray, theta: float) -> np.ndarray:
    """Rotation by ``theta`` about the unit ``axis``."""
    return (math.cos(theta) * np.eye(3) + math.sin(theta) * _skew(axis)
            + (1.0 - math.cos(theta)) * np.outer(axis, axis))


def _check_rotation(R, name: str) -> np.ndarray | None:
    if R is None:
        return None
    R = np.asarray(R, dtype=np.float64)
    if R.shape == (4, 4):
        R = R[:3, :3]
    if R.shape != (3, 3) or not np.isfinite(R).all():
        raise InputError(f"{name}: expected a finite 3x3 rotation (or 4x4 pose), got shape "
                         f"{R.shape}")
    return nearest_rotation(R)


def align_similarity(pred_centres, true_centres, *, pred_rotation=None, true_rotation=None
                     ) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity from predicted to true camera centres (Umeyama 1991).

    ``pred_centres, true_centres [N, 3]`` (row k of one is camera k of the other) -> ``(s, R, t)``
    with ``s >= 0``, ``R [3, 3]`` a rotation (det +1) and ``t [3]`` minimising
    ``sum_k |true_k - (s R pred_k + t)|^2``. Computed in float64.

    The minimiser is not unique in three degenerate cases; the result is then defined as follows
    (``pred_rotation`` / ``true_rotation``: rotation of the *first* camera, 3x3 or a 4x4 pose,
    optional; "R0" below is ``true_rotation @ pred_rotation.T``, the rotation that turns the first
    predicted camera into the first true one, or the identity when they are not given):

    - **the predicted centres are all equal** (a collapsed prediction; also N = 1), or the true ones
      are, or the two sets are exactly uncorrelated: the optimal scale is 0, every predicted centre
      maps to the true centroid (``t``), and R does not change the residual at all: ``s = 0``,
      ``R = R0``, ``t = mean(true_centres)``. So a collapsed prediction is drawn at the true
      centroid with its orientations turned by the first camera's rotation offset;
    - **the centres are collinear** (N = 2, cameras on a line): rotations about the line are free;
      of those, R is the one closest to R0 (closed form);
    - otherwise (planar or general position) the result is Umeyama's, unique.

    "All equal" means a spread (RMS distance from the centroid) of at most 1e-12 times the largest
    coordinate magnitude (so float rounding of large coordinates counts as collapsed).
    """
    P = np.asarray(pred_centres, dtype=np.float64)
    Q = np.asarray(true_centres, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or P.shape != Q.shape or P.shape[0] < 1:
        raise InputError(f"pred_centres, true_centres: expected two [N, 3] arrays with N >= 1, got "
                         f"shapes {P.shape} and {Q.shape}")
    if not (np.isfinite(P).all() and np.isfinite(Q).all()):
        raise InputError("pred_centres, true_centres: contain NaN or inf")
    Rp = _check_rotation(pred_rotation, "pred_rotation")
    Rq = _check_rotation(true_rotation, "true_rotation")
    R0 = np.eye(3) if Rp is None or Rq is None else Rq @ Rp.T

    # Umeyama is equivariant under scaling each set: solve for P / a, Q / b (a, b powers of two
    # near their magnitudes: exact, no overflow in the squares), then s = s' b / a, t = t' b.
    a = _power_of_two_scale(P)
    b = _power_of_two_scale(Q)
    s, R, t = _umeyama(P / a, Q / b, R0)
    return s * b / a, R, t * b


def _power_of_two_scale(X: np.ndarray) -> float:
    m = float(np.abs(X).max())
    return 2.0 ** math.ceil(math.log2(m)) if m > 0 else 1.0


def _umeyama(P: np.ndarray, Q: np.ndarray, R0: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    N = P.shape[0]
    mu_p, mu_q = P.mean(0), Q.mean(0)
    Pc, Qc = P - mu_p, Q - mu_q
    var_p = float(np.mean(np.sum(Pc * Pc, axis=1)))
    var_q = float(np.mean(np.sum(Qc * Qc, axis=1)))

    def collapsed(var, X):
        return not math.sqrt(var) > 1e-12 * max(float(np.abs(X).max()), 1e-300)

    Sigma = Qc.T @ Pc / N
    U, D, Vt = np.linalg.svd(Sigma)
    if collapsed(var_p, P) or collapsed(var_q, Q) or not D[0] > 0:
        return 0.0, R0, mu_q
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2] = -1.0
    R = (U * S) @ Vt
    s = float(np.sum(D * S) / var_p)
    if D[1] <= 1e-9 * D[0]:
        # Rank 1 (collinear centres): any rotation about the line's image is as good; take the
        # one closest to R0: maximise tr(Rot(a, th) M) with M = R R0^T over th.
        a = R @ Vt[0]
        a = a / np.linalg.norm(a)
        M = R @ R0.T
        c = float(np.trace(M) - a @ M @ a)
        b = float(np.trace(_skew(a) @ M))
        if abs(b) + abs(c) > 0:
            R = _rodrigues(a, math.atan2(b, c)) @ R
            R = nearest_rotation(R)
    t = mu_q - s * R @ mu_p
    return s, R, t


def apply_similarity(world_from_cam, s: float, R, t) -> np.ndarray:
    """Move poses ``world_from_cam [..., 4, 4]`` by ``x -> s R x + t``: rotations become
    ``R @ R_k``, centres ``s R c_k + t`` (a camera stays a rigid pose; its size is not scaled)."""
    T = np.array(world_from_cam, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T[..., :3, :3] = R @ T[..., :3, :3]
    T[..., :3, 3] = s * T[..., :3, 3] @ R.T + t
    T[..., 3, :] = (0.0, 0.0, 0.0, 1.0)
    return T


def align_poses(pred_world_from_cam, true_world_from_cam):
    """Predicted poses ``[N, 4, 4]`` moved into the frame of the true ones ``[N, 4, 4]`` by
    ``align_similarity`` of their centres (first cameras' rotations for the degenerate cases)
    -> ``(aligned [N, 4, 4], (s, R, t))``."""
    P = np.asarray(pred_world_from_cam, dtype=np.float64)
    Q = np.asarray(true_world_from_cam, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (4, 4) or P.shape != Q.shape or P.shape[0] < 1:
        raise InputError(f"pred_world_from_cam, true_world_from_cam: expected two [N, 4, 4] arrays "
                         f"with N >= 1, got shapes {P.shape} and {Q.shape}")
    s, R, t = align_similarity(P[:, :3, 3], Q[:, :3, 3], pred_rotation=P[0, :3, :3],
                               true_rotation=Q[0, :3, :3])
    return apply_similarity(P, s, R, t), (s, R, t)
