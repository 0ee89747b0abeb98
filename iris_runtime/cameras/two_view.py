"""Step 2 of the camera solve: the geometry of one pair of photos, with model selection.

As COLMAP's two-view geometry does, each pair gets a fundamental matrix F (which needs no focal,
so its inliers do not depend on a guessed one) and a homography H; a pair that H explains about
as well as F sees a plane or a pure rotation, whose translation cannot be trusted
("planar_or_panoramic"). The relative pose (essential matrix at the current focal, sign of the
translation by cheirality) and the pair's triangulation angle let the mapper pick a pair to
start from. Conventions: ``cam2_from_cam1`` maps camera 1's coordinates to camera 2's (OpenCV
axes), the translation of unit length; pixels centred at +0.5 (docs/ARCHITECTURE.md).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["TwoViewGeometry", "estimate_two_view", "estimate_from_distinct", "relative_pose",
           "essential_pose",
           "intrinsics", "triangulation_angles", "fundamental_matrix", "sampson_distances",
           "pixel_scale", "CONFIGS", "MIN_INLIERS", "MIN_E_F_INLIER_RATIO", "MAX_H_INLIER_RATIO",
           "ESTIMATOR", "CONFIDENCE", "REFERENCE_SIZE", "MAX_ERROR"]

#: Pair configurations: a general 3D scene with a usable translation (its essential matrix at
#: the focal guess explains the matches), matches only F explains, a plane or a rotation, or too
#: few consistent matches to say.
CONFIGS = ("general", "uncalibrated", "planar_or_panoramic", "degenerate")
#: Fewest matches consistent with F for a pair to count (COLMAP's default).
MIN_INLIERS = 15
#: E must keep this fraction of F's inliers for the pair to count as calibrated (COLMAP: 0.95;
#: lower here because the focal is a guess until the bundle adjustment).
MIN_E_F_INLIER_RATIO = 0.8
#: A pair whose homography keeps at least this fraction of F's inliers is planar or panoramic
#: (COLMAP's default).
MAX_H_INLIER_RATIO = 0.8
#: OpenCV's robust estimator for F, H and E (local optimisation and a final fit on all inliers).
ESTIMATOR = cv2.USAC_ACCURATE
CONFIDENCE = 0.9999
#: Every pixel threshold of the solve is given for photos of this longer side; larger photos
#: scale them (``pixel_scale``), as keypoints are located to a fixed fraction of the photo.
REFERENCE_SIZE = 320
#: Inlier threshold of F, H and E (pixels at ``REFERENCE_SIZE``).
MAX_ERROR = 1.0


def pixel_scale(image_size: tuple[int, int]) -> float:
    """The factor on pixel thresholds for photos of ``image_size`` (H, W): longer side /
    ``REFERENCE_SIZE``, at least 1."""
    return max(1.0, max(image_size) / REFERENCE_SIZE)


@dataclass(frozen=True)
class TwoViewGeometry:
    """What two photos' matches say about their cameras.

    config:              one of ``CONFIGS``
    inliers:             int64 [M, 2], the matches consistent with E (or F, "uncalibrated")
    num_h_inliers:       matches consistent with the homography
    cam2_from_cam1:      float64 [4, 4] at the focal it was estimated with (unit translation),
                         or None when no essential matrix was found
    triangulation_angle: median angle (degrees) between the two rays of the inliers that
                         triangulate in front of both cameras; 0 without a pose
    """
    config: str
    inliers: np.ndarray
    num_h_inliers: int
    cam2_from_cam1: np.ndarray | None
    triangulation_angle: float


def intrinsics(focal: float, image_size: tuple[int, int]) -> np.ndarray:
    """``K [3, 3]`` of a focal in pixels, square pixels, principal point at the image centre."""
    H, W = image_size
    return np.array([[focal, 0.0, W / 2.0], [0.0, focal, H / 2.0], [0.0, 0.0, 1.0]])


def triangulation_angles(rays1: np.ndarray, centre1: np.ndarray, rays2: np.ndarray,
                         centre2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angles (radians) [N] at the midpoint of two rays per match, and whether that midpoint lies
    in front of both cameras [N] bool. rays [N, 3] world directions, centres [3]."""
    w = centre1 - centre2
    aa, ab, bb = (rays1 * rays1).sum(1), (rays1 * rays2).sum(1), (rays2 * rays2).sum(1)
    det = aa * bb - ab * ab
    ok = det > 1e-12 * aa * bb
    det = np.where(ok, det, 1.0)
    s = (ab * (rays2 @ w) - bb * (rays1 @ w)) / det
    u = (aa * (rays2 @ w) - ab * (rays1 @ w)) / det
    X = 0.5 * (centre1 + s[:, None] * rays1 + centre2 + u[:, None] * rays2)
    d1, d2 = X - centre1, X - centre2
    cos = (d1 * d2).sum(1) / np.maximum(np.linalg.norm(d1, axis=1) * np.linalg.norm(d2, axis=1),
                                        1e-300)
    return np.arccos(np.clip(cos, -1.0, 1.0)), ok & (s > 0) & (u > 0)


def _robust(estimate, *args):
    """Run one of OpenCV's robust estimators from a fixed seed; (model, bool mask) or
    (None, None) when it finds none (OpenCV raises on some degenerate samples)."""
    cv2.setRNGSeed(0)
    try:
        model, mask = estimate(*args)
    except cv2.error:
        return None, None
    if model is None or model.shape != (3, 3) or mask is None:
        return None, None
    return model, mask.ravel().astype(bool)


def relative_pose(p: np.ndarray, q: np.ndarray, focal: float, image_size: tuple[int, int],
                  max_error: float) -> tuple[np.ndarray | None, float]:
    """``cam2_from_cam1 [4, 4]`` (unit translation) of matched pixels ``p -> q [N, 2]`` from the
    essential matrix at ``focal`` (sign by cheirality), and the median triangulation angle
    (degrees) of the matches in front of both cameras; (None, 0) when there is none."""
    K = intrinsics(focal, image_size)
    E, mask = _robust(lambda *a: cv2.findEssentialMat(*a), p, q, K, ESTIMATOR, CONFIDENCE,
                      max_error)
    if E is None or mask.sum() < 5:
        return None, 0.0
    _, R, t, good = cv2.recoverPose(E, p, q, K, mask=mask.astype(np.uint8))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t.ravel() / max(np.linalg.norm(t), 1e-300)
    good = good.ravel().astype(bool)
    if not good.any():
        return T, 0.0
    return T, median_triangulation_angle(p[good], q[good], T, K)


def median_triangulation_angle(p: np.ndarray, q: np.ndarray, cam2_from_cam1: np.ndarray,
                               K: np.ndarray) -> float:
    """The median angle (degrees) between the two rays of the matched pixels ``p -> q [N, 2]``
    that triangulate in front of both cameras (``cam2_from_cam1 [4, 4]``, intrinsics ``K``);
    0 when none does."""
    R = cam2_from_cam1[:3, :3]
    Kinv = np.linalg.inv(K)
    r1 = np.c_[p, np.ones(len(p))] @ Kinv.T
    r2 = np.c_[q, np.ones(len(q))] @ Kinv.T @ R                      # in camera 1
    ang, front = triangulation_angles(r1, np.zeros(3), r2, -R.T @ cam2_from_cam1[:3, 3])
    return float(np.degrees(np.median(ang[front]))) if front.any() else 0.0


def essential_pose(p: np.ndarray, q: np.ndarray, focal: float, image_size: tuple[int, int],
                   max_error: float) -> tuple[np.ndarray, np.ndarray] | None:
    """``(inliers bool [N], cam2_from_cam1 [4, 4])``: the matched pixels ``p -> q [N, 2]``
    consistent with their essential matrix at ``focal`` within ``max_error`` pixels, and its
    pose (the decomposition in front of both cameras, unit translation), or None when fewer than
    ``MIN_INLIERS`` are consistent."""
    if len(p) < MIN_INLIERS:
        return None
    K = intrinsics(focal, image_size)
    E, mask = _robust(lambda *a: cv2.findEssentialMat(*a), p, q, K, ESTIMATOR, CONFIDENCE,
                      max_error)
    if E is None or mask.sum() < MIN_INLIERS:
        return None
    _, R, t, _ = cv2.recoverPose(E, p, q, K, mask=mask.astype(np.uint8))
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t.ravel() / max(np.linalg.norm(t), 1e-300)
    return mask, T


def fundamental_matrix(cam2_from_cam1: np.ndarray, K: np.ndarray) -> np.ndarray:
    """``F [3, 3]`` of two cameras with intrinsics ``K`` related by ``cam2_from_cam1 [4, 4]``:
    x2^T F x1 = 0 for pixels x1, x2 of one point."""
    R, t = cam2_from_cam1[:3, :3], cam2_from_cam1[:3, 3]
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    Kinv = np.linalg.inv(K)
    return Kinv.T @ tx @ R @ Kinv


def sampson_distances(p: np.ndarray, q: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Sampson distances (pixels) [N] of matched pixels ``p -> q [N, 2]`` to ``F``."""
    ph, qh = np.c_[p, np.ones(len(p))], np.c_[q, np.ones(len(q))]
    Fp, Ftq = ph @ F.T, qh @ F
    num = np.sum(qh * Fp, axis=1) ** 2
    den = Fp[:, 0] ** 2 + Fp[:, 1] ** 2 + Ftq[:, 0] ** 2 + Ftq[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-300))


def estimate_two_view(uv1: np.ndarray, uv2: np.ndarray, matches: np.ndarray, focal: float,
                      image_size: tuple[int, int], max_error: float) -> TwoViewGeometry:
    """The two-view geometry of keypoints ``uv1 [N1, 2]``, ``uv2 [N2, 2]`` matched by ``matches
    int64 [M, 2]``, in photos of ``image_size`` (H, W) taken at about ``focal`` pixels.
    ``max_error``: the estimators' inlier threshold in pixels. Deterministic: every estimator
    starts from OpenCV's RNG seeded with 0.

    The essential matrix at ``focal`` (5 points, few degrees of freedom) keeps the fewest wrong
    matches; when it explains fewer than ``MIN_E_F_INLIER_RATIO`` of what F explains (the focal
    guess is off, or F fits a chance set), the pair keeps F's inliers as "uncalibrated"."""
    none = TwoViewGeometry("degenerate", np.zeros((0, 2), np.int64), 0, None, 0.0)
    if len(matches) < MIN_INLIERS:
        return none
    p, q = uv1[matches[:, 0]], uv2[matches[:, 1]]
    K = intrinsics(focal, image_size)
    _, e_mask = _robust(lambda *a: cv2.findEssentialMat(*a), p, q, K, ESTIMATOR, CONFIDENCE,
                        max_error)
    _, f_mask = _robust(lambda *a: cv2.findFundamentalMat(*a), p, q, ESTIMATOR, max_error,
                        CONFIDENCE)
    n_e = 0 if e_mask is None else int(e_mask.sum())
    n_f = 0 if f_mask is None else int(f_mask.sum())
    if max(n_e, n_f) < MIN_INLIERS:
        return none
    _, h_mask = _robust(lambda *a: cv2.findHomography(*a), p, q, ESTIMATOR, max_error, None,
                        2000, CONFIDENCE)
    n_h = 0 if h_mask is None else int(h_mask.sum())
    calibrated = n_e >= MIN_E_F_INLIER_RATIO * n_f and n_e >= MIN_INLIERS
    mask = e_mask if calibrated else f_mask
    config = ("planar_or_panoramic" if n_h >= MAX_H_INLIER_RATIO * mask.sum()
              else "general" if calibrated else "uncalibrated")
    T, angle = relative_pose(p[mask], q[mask], focal, image_size, max_error)
    return TwoViewGeometry(config, matches[mask], n_h, T, angle)


def estimate_from_distinct(uv1: np.ndarray, uv2: np.ndarray, matches: np.ndarray,
                           distinct: np.ndarray, focal: float, image_size: tuple[int, int],
                           max_error: float) -> TwoViewGeometry | None:
    """The pair's geometry from its distinct matches (``distinct`` bool [M]: keypoints without a
    near twin in their own photos, ``features.twin_distance``), or None when fewer than
    ``MIN_INLIERS`` of them agree on a general pose.

    On a repeated texture, matches one period off agree with one another and can outnumber the
    right ones (docs/CAMERAS.md, "Repeated patterns"). Here the pose comes from the distinct
    matches alone (their essential matrix, also where F would call them "uncalibrated") and the
    pair keeps every match, distinct or not, that the pose explains (Sampson distance)."""
    if distinct.sum() < MIN_INLIERS:
        return None
    md = matches[distinct]
    g = estimate_two_view(uv1, uv2, md, focal, image_size, max_error)
    if g.config == "uncalibrated":
        T, angle = relative_pose(uv1[md[:, 0]], uv2[md[:, 1]], focal, image_size, max_error)
        if T is None:
            return None
        g = TwoViewGeometry("general", g.inliers, g.num_h_inliers, T, angle)
    if g.config != "general" or len(g.inliers) < MIN_INLIERS:
        return None
    p, q = uv1[matches[:, 0]], uv2[matches[:, 1]]
    F = fundamental_matrix(g.cam2_from_cam1, intrinsics(focal, image_size))
    keep = sampson_distances(p, q, F) < max_error
    _, h_mask = _robust(lambda *a: cv2.findHomography(*a), p[keep], q[keep], ESTIMATOR,
                        max_error, None, 2000, CONFIDENCE)
    n_h = 0 if h_mask is None else int(h_mask.sum())
    return TwoViewGeometry("general", matches[keep], n_h, g.cam2_from_cam1,
                           g.triangulation_angle)
