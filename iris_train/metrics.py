"""Evaluation metrics in numpy: PSNR, SSIM, relative pose accuracy (RPA), depth rank correlation.

numpy + OpenCV only (no torch), so that a model served by ``iris_runtime`` can be scored in an
environment without torch.

Images are float arrays ``[H, W, 3]`` in [0, 1]. Poses are ``world_from_cam`` 4x4 (camera-to-world,
OpenCV axes; docs/ARCHITECTURE.md). Angles are in degrees; RPA values are fractions in [0, 1].

Pose error (appendix "Definition of Pose Error" of the IRIS paper), for all pairs i < j::

    cam_from_world_k = inv(world_from_cam_k)
    T_{i<-j} = cam_from_world_i @ inv(cam_from_world_j)                  (predicted and ground truth)
    e_R = arccos((tr(R^T R_hat) - 1) / 2)                                (rotation geodesic angle)
    c_t = <t, t_hat> / (|t| |t_hat|);  e_t = min(arccos c_t, 180 deg - arccos c_t)
    e_pose = max(e_R, e_t);  RPA@tau = fraction of pairs with e_pose < tau

The translation angle is sign-ambiguous (a reversed baseline costs nothing) and scale-free, so the
metric is invariant to any similarity transform of the predicted world (and of the ground truth).

**Zero translations** (the paper leaves them undefined): a relative translation counts as zero when
its norm is at most ``ZERO_TRANSLATION_RTOL`` times the largest camera-centre norm of its pose set
(rounding noise of ``inv`` and the matrix product scales with the coordinates). Then

- both zero (e.g. a pure rotation, correctly predicted as one): ``e_t = 0``;
- exactly one zero: ``e_t = 90`` degrees, the largest sign-ambiguous error. A method that predicts
  no baseline where there is one (identity poses, for instance) gets no credit for its direction,
  and neither does one that invents a baseline where the cameras only rotate.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

__all__ = ["psnr", "capped_psnr", "ssim", "relative_pose_errors", "rpa", "depth_spearman",
           "PSNR_CAP", "RPA_THRESHOLDS", "ZERO_TRANSLATION_RTOL", "DEPTH_SPEARMAN_MIN_PIXELS"]

#: Reported PSNRs are capped at this (dB): identical images have an infinite PSNR, which a mean
#: over images or a JSON report cannot hold (``capped_psnr``).
PSNR_CAP = 100.0

#: Default RPA thresholds in degrees (the paper's RPA@5/15/30).
RPA_THRESHOLDS = (5, 15, 30)
#: Relative translations at most this times the scene's coordinate scale count as zero (see above).
ZERO_TRANSLATION_RTOL = 1e-9
#: ``depth_spearman`` needs at least this many valid pixels (else nan).
DEPTH_SPEARMAN_MIN_PIXELS = 3

# SSIM constants of Wang et al. 2004 (and scikit-image's ``gaussian_weights=True``).
_SSIM_SIGMA = 1.5
_SSIM_K1 = 0.01
_SSIM_K2 = 0.03
_SSIM_TRUNCATE = 3.5                                     # -> 11-tap window at sigma 1.5
_SSIM_RADIUS = int(_SSIM_TRUNCATE * _SSIM_SIGMA + 0.5)   # 5


def _check_images(pred: np.ndarray, gt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    pred = np.asarray(pred, dtype=np.float64)
    gt = np.asarray(gt, dtype=np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt must have the same shape, got {pred.shape} and {gt.shape}")
    if pred.ndim not in (2, 3):
        raise ValueError(f"images: expected [H, W] or [H, W, C], got shape {pred.shape}")
    return pred, gt


def psnr(pred: np.ndarray, gt: np.ndarray, data_range: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB of ``pred`` against ``gt`` (same shape; values in
    ``[0, data_range]``). Identical images give ``inf``."""
    pred, gt = _check_images(pred, gt)
    mse = np.mean((pred - gt) ** 2)
    if mse == 0:
        return float("inf")
    return float(10.0 * np.log10(data_range ** 2 / mse))


def capped_psnr(pred: np.ndarray, gt: np.ndarray, data_range: float = 1.0) -> float:
    """``psnr`` capped at ``PSNR_CAP`` dB (finite for identical images)."""
    return min(psnr(pred, gt, data_range), PSNR_CAP)


def ssim(pred: np.ndarray, gt: np.ndarray, data_range: float = 1.0) -> float:
    """Structural similarity (Wang et al. 2004) of ``pred`` and ``gt`` ``[H, W, 3]`` (or ``[H, W]``).

    Gaussian window (sigma 1.5, 11 taps), K1 = 0.01, K2 = 0.03, population (co)variances; the SSIM
    map is averaged over the interior (a 5-pixel border, where the window leaves the image, is
    ignored) and over channels. Matches scikit-image's ``structural_similarity(...,
    channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False)``. Images must be at least 11x11.
    """
    pred, gt = _check_images(pred, gt)
    if pred.ndim == 2:
        pred, gt = pred[..., None], gt[..., None]
    H, W = pred.shape[:2]
    win = 2 * _SSIM_RADIUS + 1
    if H < win or W < win:
        raise ValueError(f"ssim needs images of at least {win}x{win}, got {H}x{W}")

    def blur(x):
        # Border mode is irrelevant: the cropped interior never sees the border.
        out = cv2.GaussianBlur(x, (win, win), _SSIM_SIGMA, borderType=cv2.BORDER_REFLECT)
        return out.reshape(x.shape)     # OpenCV drops a trailing channel axis of size 1

    C1 = (_SSIM_K1 * data_range) ** 2
    C2 = (_SSIM_K2 * data_range) ** 2
    ux, uy = blur(pred), blur(gt)
    vx = blur(pred * pred) - ux * ux
    vy = blur(gt * gt) - uy * uy
    vxy = blur(pred * gt) - ux * uy
    S = ((2 * ux * uy + C1) * (2 * vxy + C2)) / ((ux * ux + uy * uy + C1) * (vx + vy + C2))
    r = _SSIM_RADIUS
    return float(S[r:H - r, r:W - r].mean(axis=(0, 1)).mean())


def _check_poses(T: np.ndarray, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise ValueError(f"{name}: expected world_from_cam [B, 4, 4], got shape {T.shape}")
    if not np.isfinite(T).all():
        raise ValueError(f"{name}: contains NaN or inf")
    return T


def _relative_poses(world_from_cam: np.ndarray, i: np.ndarray, j: np.ndarray):
    """``T_{i<-j} = cam_from_world_i inv(cam_from_world_j)`` for index arrays i, j -> R [P,3,3], t [P,3]
    and the zero-translation tolerance of this pose set."""
    cam_from_world = np.linalg.inv(world_from_cam)
    T = cam_from_world[i] @ np.linalg.inv(cam_from_world[j])
    scale = np.abs(world_from_cam[:, :3, 3]).max(initial=0.0)
    # Centres of a few units carry rounding noise of ~1e-16 units; a scene entirely at the origin
    # has exactly-zero relative translations (tolerance 0, compared with <=).
    return T[:, :3, :3], T[:, :3, 3], ZERO_TRANSLATION_RTOL * scale


def relative_pose_errors(pred_world_from_cam: np.ndarray, gt_world_from_cam: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Rotation and translation-direction errors in degrees over all pairs i < j.

    ``pred_world_from_cam, gt_world_from_cam [B, 4, 4]`` (B >= 2, frame k of one is frame k of the
    other) -> ``rot_err_deg [P], trans_err_deg [P]`` with P = B(B-1)/2, pairs in the order of
    ``np.triu_indices(B, 1)``. See the module docstring for the definition and the zero-translation
    convention. Predicted rotations need not be exactly orthonormal (the cosine is clipped).
    """
    pred = _check_poses(pred_world_from_cam, "pred_world_from_cam")
    gt = _check_poses(gt_world_from_cam, "gt_world_from_cam")
    if pred.shape != gt.shape:
        raise ValueError(f"pred and gt must hold the same number of poses, got {pred.shape[0]} "
                         f"and {gt.shape[0]}")
    B = pred.shape[0]
    if B < 2:
        raise ValueError(f"relative pose errors need at least 2 poses, got {B}")
    i, j = np.triu_indices(B, 1)
    R_hat, t_hat, tol_hat = _relative_poses(pred, i, j)
    R, t, tol = _relative_poses(gt, i, j)

    cos_r = (np.einsum("pij,pij->p", R, R_hat) - 1.0) / 2.0          # tr(R^T R_hat) = sum R*R_hat
    rot = np.degrees(np.arccos(np.clip(cos_r, -1.0, 1.0)))

    n, n_hat = np.linalg.norm(t, axis=-1), np.linalg.norm(t_hat, axis=-1)
    zero, zero_hat = n <= tol, n_hat <= tol_hat
    cos_t = np.einsum("pi,pi->p", t, t_hat) / np.maximum(n * n_hat, np.finfo(np.float64).tiny)
    ang = np.degrees(np.arccos(np.clip(cos_t, -1.0, 1.0)))
    trans = np.minimum(ang, 180.0 - ang)
    trans = np.where(zero | zero_hat, 90.0, trans)
    trans = np.where(zero & zero_hat, 0.0, trans)
    return rot, trans


def rpa(pred_world_from_cam: np.ndarray, gt_world_from_cam: np.ndarray,
        thresholds=RPA_THRESHOLDS) -> dict[str, float]:
    """Relative pose accuracy: ``{"rpa@5": fraction of pairs with max(e_R, e_t) < 5 deg, ...}``."""
    rot, trans = relative_pose_errors(pred_world_from_cam, gt_world_from_cam)
    err = np.maximum(rot, trans)
    return {f"rpa@{tau:g}": float(np.mean(err < tau)) for tau in thresholds}


def _average_ranks(x: np.ndarray) -> np.ndarray:
    """Ranks 1..n of ``x [n]``, ties sharing their mean rank (scipy.stats.rankdata "average")."""
    order = np.argsort(x, kind="mergesort")
    xs = x[order]
    # Start index of each run of equal values; a run [a, b) gets the mean rank (a + 1 + b) / 2.
    starts = np.flatnonzero(np.concatenate([[True], xs[1:] != xs[:-1]]))
    ends = np.concatenate([starts[1:], [len(xs)]])
    run_rank = (starts + 1 + ends) / 2.0
    ranks = np.empty(len(x), dtype=np.float64)
    ranks[order] = np.repeat(run_rank, ends - starts)
    return ranks


def depth_spearman(pred_depth: np.ndarray, true_depth: np.ndarray) -> float:
    """Spearman rank correlation of a predicted depth map with the true one, over the pixels that
    see geometry.

    ``pred_depth, true_depth [H, W]`` (any real dtype, same shape). Valid pixels: ``true_depth > 0``
    (0 = no geometry, as in ``SceneData.depth``) where both maps are finite. On those pixels:
    Pearson correlation of the average ranks (ties share their mean rank), which is what
    ``scipy.stats.spearmanr`` computes. Rank-based, so the prediction's unit (pose-free models have
    their own scale) and any monotone reparametrisation of it do not matter.

    Returns a float in [-1, 1], or **nan** when it is undefined: fewer than
    ``DEPTH_SPEARMAN_MIN_PIXELS`` (3) valid pixels, or either map constant over them (zero rank
    variance). Never warns.
    """
    pred = np.asarray(pred_depth, dtype=np.float64)
    true = np.asarray(true_depth, dtype=np.float64)
    if pred.shape != true.shape:
        raise ValueError(f"pred_depth and true_depth must have the same shape, got {pred.shape} "
                         f"and {true.shape}")
    if pred.ndim != 2:
        raise ValueError(f"depth maps: expected [H, W], got shape {pred.shape}")
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(true) & np.isfinite(pred) & (true > 0)
    if int(valid.sum()) < DEPTH_SPEARMAN_MIN_PIXELS:
        return float("nan")
    a = _average_ranks(pred[valid])
    b = _average_ranks(true[valid])
    a -= a.mean()
    b -= b.mean()
    denom = math.sqrt(float(a @ a) * float(b @ b))
    if not denom > 0:
        return float("nan")
    return float(np.clip((a @ b) / denom, -1.0, 1.0))
