"""Step 6 of the camera solve: the pose of a photo from its matches to known 3D points (PnP).

The mapper registers each new view this way, and ``locate_photos`` poses photos that were not
part of the solve against its points, which stay fixed (``IrisRuntime.locate``, the targets of
``iris-eval``). Matching a photo against every solved view's keypoints that see a point gives
2D-3D correspondences; OpenCV's PnP RANSAC (SQPnP on minimal samples) then Levenberg-Marquardt
on the inliers gives the pose. Conventions: OpenCV axes, ``cam_from_world`` (R, t) internally,
pixels centred at +0.5 (docs/ARCHITECTURE.md).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import InputError
from .features import (Features, canonical_order, contrast_threshold, distinct_keypoints, enlarge,
                       extract_features, match_features, scene_features)
from .tracks import build_tracks
from .triangulation import triangulate
from .two_view import (CONFIDENCE, MAX_ERROR, fundamental_matrix, intrinsics, pixel_scale,
                       sampson_distances)

__all__ = ["PointMap", "pose_from_points", "pose_distinct_first", "confident_iterations",
           "locate_photos", "point_map_from_cameras", "locate_views", "PNP_ERROR",
           "PNP_MIN_INLIERS", "PNP_MIN_INLIER_RATIO", "PNP_ITERATIONS", "MIN_TRIANGULATION_ANGLE"]

#: Reprojection threshold of a registration (pixels at ``two_view.REFERENCE_SIZE``).
PNP_ERROR = 4.0
#: Fewest 2D-3D inliers a posed view needs (COLMAP's relaxed ``abs_pose_min_num_inliers``).
PNP_MIN_INLIERS = 15
#: ... and the fraction of its 2D-3D correspondences they must be (COLMAP's default).
PNP_MIN_INLIER_RATIO = 0.25
#: RANSAC iterations of the PnP (the solve's; the refinement's salvage and witness run fewer,
#: ``refine.CappedPnP.max_iterations``).
PNP_ITERATIONS = 1000
#: Points of known cameras seen under a narrower angle (degrees) carry no depth.
MIN_TRIANGULATION_ANGLE = 1.5


@dataclass(frozen=True)
class PointMap:
    """The solved scene's 3D points and the keypoints that see them, what a new photo is matched
    against: ``points`` float64 [P, 3] (the world frame and unit of the cameras), and per
    observation ``view`` int64 [N], ``point`` int64 [N] (row of ``points``) and ``descriptors``
    uint8 [N, 128] (RootSIFT x 512, ``features.Features``), found in the photos enlarged
    ``enlargement`` times (``features.scene_features``): new photos are matched at that size."""
    points: np.ndarray
    view: np.ndarray
    point: np.ndarray
    descriptors: np.ndarray
    enlargement: int = 1

    def transformed(self, world_from_old: np.ndarray, scale: float = 1.0) -> "PointMap":
        """The same map with points x -> world_from_old (scale x) (a rigid map and a scale)."""
        X = scale * self.points @ world_from_old[:3, :3].T + world_from_old[:3, 3]
        return PointMap(X, self.view, self.point, self.descriptors, self.enlargement)


def confident_iterations(N: int, min_inliers: int, method: int,
                         max_iterations: int = PNP_ITERATIONS) -> int:
    """The RANSAC iterations after which a pose that ``min_inliers`` of ``N`` correspondences
    support, were there one, would have been drawn from an all-inlier sample with probability
    ``two_view.CONFIDENCE``: log(1 - CONFIDENCE) / log(1 - (min_inliers / N)^s), s the points
    of OpenCV's sample (4 for P3P and AP3P, else 5), rounded up (at most ``max_iterations``).
    OpenCV's adaptive stop never runs longer once its best pose has that many inliers, so a
    search capped here ends as the uncapped one does whenever it finds such a pose by then;
    where it has not, it gives up with the confidence the adaptive stop has in its result."""
    s = 4 if method in (cv2.SOLVEPNP_P3P, cv2.SOLVEPNP_AP3P) else 5
    drawn = (min(min_inliers, N) / N) ** s
    if drawn >= 1.0:
        return 1
    needed = np.log(1.0 - CONFIDENCE) / np.log1p(-drawn)
    return int(min(max_iterations, np.ceil(needed)))


def pose_from_points(points: np.ndarray, uv: np.ndarray, focal: float,
                     image_size: tuple[int, int], *, max_error: float,
                     min_inliers: int = PNP_MIN_INLIERS,
                     min_inlier_ratio: float = PNP_MIN_INLIER_RATIO,
                     method: int = cv2.SOLVEPNP_SQPNP, confident_stop: bool = False,
                     max_iterations: int = PNP_ITERATIONS):
    """cam_from_world ``(R [3, 3], t [3], inliers bool [N])`` of a photo whose pixels ``uv [N, 2]``
    see ``points [N, 3]``, or None when fewer than ``min_inliers`` (or ``min_inlier_ratio`` of
    them) reproject within ``max_error`` pixels. ``method``: OpenCV's PnP in the RANSAC (the
    pose is then refined on the inliers either way). ``confident_stop``: the RANSAC runs at most
    ``confident_iterations`` (else ``max_iterations``): a view with few correspondences and no
    pose gives up sooner. Deterministic (OpenCV's RNG seeded with 0)."""
    N = len(points)
    if N < max(min_inliers, 6):
        return None
    K = intrinsics(focal, image_size)
    obj, img = np.ascontiguousarray(points, np.float64), np.ascontiguousarray(uv, np.float64)
    iterations = confident_iterations(N, min_inliers, method, max_iterations) \
        if confident_stop else max_iterations
    cv2.setRNGSeed(0)
    try:
        ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, None, iterationsCount=iterations,
                                                 reprojectionError=max_error,
                                                 confidence=CONFIDENCE, flags=method)
    except cv2.error:
        return None
    if not ok or inl is None or len(inl) < min_inliers:
        return None
    R, t, inliers = _refine(obj, img, K, inl.ravel(), rvec, tvec, max_error)
    if inliers.sum() < max(min_inliers, min_inlier_ratio * N):
        return None
    return R, t, inliers


def _reprojects(obj: np.ndarray, img: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
                max_error: float) -> np.ndarray:
    """bool [N]: the points ``obj [N, 3]`` in front of camera (R, t) that reproject within
    ``max_error`` pixels of ``img [N, 2]``."""
    Y = obj @ R.T + t
    # A point on or behind the camera (z <= 0) divides to inf or NaN, one just in front of it
    # (a subnormal z) overflows: intended, since such points are not counted (z > 0 below, and
    # inf or NaN is never <= max_error).
    with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
        err = np.linalg.norm(K[0, 0] * Y[:, :2] / Y[:, 2:] + K[:2, 2] - img, axis=1)
    return (Y[:, 2] > 0) & (err <= max_error)


def _refine(obj, img, K, inliers, rvec, tvec, max_error):
    """``(R, t, inliers)``: the pose (``rvec, tvec``) refined by Levenberg-Marquardt on the
    correspondences ``inliers`` (indices or mask), and the correspondences it then explains."""
    rvec, tvec = cv2.solvePnPRefineLM(obj[inliers], img[inliers], K, None, rvec, tvec)
    R, t = cv2.Rodrigues(rvec)[0], tvec.ravel()
    return R, t, _reprojects(obj, img, K, R, t, max_error)


def pose_distinct_first(points: np.ndarray, uv: np.ndarray, distinct: np.ndarray, focal: float,
                        image_size: tuple[int, int], *, max_error: float,
                        min_inliers: int = PNP_MIN_INLIERS, method: int = cv2.SOLVEPNP_SQPNP,
                        confident_stop: bool = False, max_iterations: int = PNP_ITERATIONS):
    """``pose_from_points`` of the correspondences whose keypoints are distinct (``distinct``
    bool [N]: no near twin in their photo, ``features.distinct_keypoints``), then refined on
    every correspondence it explains; ``pose_from_points`` of all of them when the distinct ones
    give no pose. On a repeated texture a keypoint matched one period off points at a pose one
    period off, and such correspondences agree with one another (docs/CAMERAS.md), so the
    refined pose needs ``min_inliers`` of them, not a fraction: most may be shifted.
    ``method``, ``confident_stop``, ``max_iterations``: the RANSAC's, as in
    ``pose_from_points``."""
    if distinct.sum() >= min_inliers:
        first = pose_from_points(points[distinct], uv[distinct], focal, image_size,
                                 max_error=max_error, min_inliers=min_inliers, method=method,
                                 confident_stop=confident_stop, max_iterations=max_iterations)
        if first is not None:
            K = intrinsics(focal, image_size)
            obj = np.ascontiguousarray(points, np.float64)
            img = np.ascontiguousarray(uv, np.float64)
            inliers = _reprojects(obj, img, K, first[0], first[1], max_error)
            if inliers.sum() >= max(min_inliers, 6):
                R, t, inliers = _refine(obj, img, K, inliers, cv2.Rodrigues(first[0])[0],
                                        first[1].reshape(3, 1).copy(), max_error)
                if inliers.sum() >= max(min_inliers, 6):
                    return R, t, inliers
    return pose_from_points(points, uv, focal, image_size, max_error=max_error,
                            min_inliers=min_inliers, method=method,
                            confident_stop=confident_stop, max_iterations=max_iterations)


def correspondences(point_map: PointMap, features: Features) -> tuple[np.ndarray, np.ndarray]:
    """2D-3D correspondences of a photo's ``features`` against ``point_map``: ``(keypoint int64
    [N], point int64 [N])``, from its matches with each solved view's keypoints (ratio test and
    mutual check per view); a keypoint matched to several points keeps the one most views agree
    on (ties: the lowest point index)."""
    kps, pts = [], []
    for v in np.unique(point_map.view):
        rows = np.flatnonzero(point_map.view == v)
        ref = Features(np.zeros((len(rows), 2)), point_map.descriptors[rows], features.image_size)
        m = match_features(features, ref)
        kps.append(m[:, 0])
        pts.append(point_map.point[rows[m[:, 1]]])
    kp = np.concatenate(kps) if kps else np.zeros(0, np.int64)
    pt = np.concatenate(pts) if pts else np.zeros(0, np.int64)
    if len(kp) == 0:
        return kp, pt
    pairs, votes = np.unique(np.stack([kp, pt], 1), axis=0, return_counts=True)
    order = np.lexsort((pairs[:, 1], -votes, pairs[:, 0]))     # per keypoint: most votes first
    pairs = pairs[order]
    first = np.r_[True, pairs[1:, 0] != pairs[:-1, 0]]
    return pairs[first, 0], pairs[first, 1]


def locate_photos(point_map: PointMap, focal: float, image_size: tuple[int, int], photos
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Poses of ``photos`` (uint8 [H, W, 3] or [H, W] of ``image_size``, taken with the solved
    camera: ``focal`` pixels, principal point centred) against the fixed ``point_map``.

    Returns ``(world_from_cam float64 [Q, 4, 4]`` (NaN for a photo that cannot be posed),
    ``located bool [Q])``. Each photo is posed on its own (``pose_distinct_first``: its distinct
    keypoints' correspondences first), so the order of the photos does not matter."""
    Q = len(photos)
    k = point_map.enlargement                     # as the solve saw the scene's photos
    size = (image_size[0] * k, image_size[1] * k)
    max_error = PNP_ERROR * pixel_scale(size)
    out = np.full((Q, 4, 4), np.nan)
    ok = np.zeros(Q, bool)
    for q, photo in enumerate(photos):
        feats = extract_features(enlarge(np.asarray(photo), k),
                                 contrast_threshold=contrast_threshold(image_size))
        kp, pt = correspondences(point_map, feats)
        pose = pose_distinct_first(point_map.points[pt], feats.uv[kp],
                                   distinct_keypoints(feats)[kp], focal * k, size,
                                   max_error=max_error)
        if pose is None:
            continue
        R, t, _ = pose
        out[q] = np.eye(4)
        out[q, :3, :3], out[q, :3, 3] = R.T, -R.T @ t
        ok[q] = True
    return out, ok


def point_map_from_cameras(photos, world_from_cam: np.ndarray, focal: float) -> PointMap:
    """The 3D points of ``photos`` (V uint8 photos of one size) whose cameras are known
    (``world_from_cam [V, 4, 4]``, ``focal`` pixels, principal point centred): their matches
    kept where the known epipolar geometry explains them, tracked across views and
    triangulated. The photos are matched in ``canonical_order``, so their order does not
    matter."""
    photos = [np.asarray(p) for p in photos]
    V = len(photos)
    T = np.asarray(world_from_cam, dtype=np.float64)
    if T.shape != (V, 4, 4) or not np.isfinite(T).all():
        raise InputError(f"world_from_cam: expected finite [{V}, 4, 4], got {T.shape}")
    perm = canonical_order(photos)
    feats, k = scene_features([photos[v] for v in perm])      # as the solve sees such photos
    focal = focal * k
    size = feats[0].image_size
    cam_from_world = np.linalg.inv(T[perm])
    R, t = cam_from_world[:, :3, :3], cam_from_world[:, :3, 3]
    K = intrinsics(focal, size)
    max_error = MAX_ERROR * pixel_scale(size)
    matches = {}
    for a in range(V):
        for b in range(a + 1, V):
            m = match_features(feats[a], feats[b])
            F = fundamental_matrix(cam_from_world[b] @ T[perm[a]], K)     # cam_b from cam_a
            keep = sampson_distances(feats[a].uv[m[:, 0]], feats[b].uv[m[:, 1]], F) <= max_error
            matches[a, b] = m[keep]
    tracks = build_tracks(feats, matches)
    X, ok = triangulate(R, t, focal, K[:2, 2], tracks.uv, tracks.observed,
                        max_error=PNP_ERROR * pixel_scale(size),
                        min_angle=MIN_TRIANGULATION_ANGLE)
    rows = np.flatnonzero(ok)
    t_idx, v_idx = np.nonzero(tracks.observed[rows])
    desc = (np.stack([feats[v].descriptors[tracks.keypoint[rows[i], v]]
                      for i, v in zip(t_idx, v_idx)]) if len(t_idx)
            else np.zeros((0, 128), np.uint8))
    return PointMap(X[rows], perm[v_idx], t_idx.astype(np.int64), desc, k)


def locate_views(reference_photos, reference_world_from_cam, focal: float, query_photos
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Poses of ``query_photos`` against reference photos whose cameras are known
    (``reference_world_from_cam [V, 4, 4]``, ``focal`` fx/W, square pixels, principal point
    centred; all photos of one size), those cameras held fixed: ``point_map_from_cameras`` of
    the references, then ``locate_photos``. Returns ``(world_from_cam [Q, 4, 4]`` (NaN where a
    query cannot be posed), ``located bool [Q])``, in the references' frame and unit."""
    refs = [np.asarray(p) for p in reference_photos]
    queries = [np.asarray(p) for p in query_photos]
    size = refs[0].shape[:2]
    if any(p.shape[:2] != size for p in refs + queries):
        raise InputError(f"query_photos: expected photos of the references' size {size}")
    f = float(focal) * size[1]
    pm = point_map_from_cameras(refs, reference_world_from_cam, f)
    return locate_photos(pm, f, size, queries)
