"""The camera solve's one entry point: ``solve_cameras(photos, depth_range) -> CameraSolve``.

The photos are taken in ``canonical_order`` (fixed by their content), so the same photos in any
order give the same cameras, re-based on the caller's view 0. The solve has no unit of its own;
the cameras get the renderer's: the median depth of the scene's points is put ``DEPTH_TARGET``
of the way into the renderer's depth range [near, far], the range its training data was built in
(docs/CAMERAS.md, "Scale").
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from .features import (DISTINCT_DISTANCE, canonical_order, distinct_keypoints, match_features,
                       scene_features, twin_distance)
from .locate import PointMap, locate_photos, pose_from_points
from .mapper import MapperOptions, Reconstruction, incremental_mapping
from .tracks import Tracks, build_tracks
from .two_view import (MAX_ERROR, estimate_from_distinct, estimate_two_view, fundamental_matrix,
                       intrinsics, pixel_scale, sampson_distances)

__all__ = ["CameraSolve", "solve_cameras", "check_photos", "check_depth_range", "check_focal",
           "finish_solve",
           "STATUSES", "DEPTH_TARGET", "unit_range", "FOCAL_PRIORS", "LOCATE_MIN_INLIERS"]

#: Per-view outcome: registered in the joint solve, posed against its points afterwards with the
#: points held fixed, or not posed at all.
STATUSES = ("solved", "located", "unposed")
#: Where the scene's median point depth goes in the renderer's [near, far] (0: near, 1: far).
DEPTH_TARGET = 0.5


def unit_range(near: float, far: float, median_depth: float = 0.0) -> tuple[float, float]:
    """The ``depth_range`` to give the solve for a renderer that samples [near, far] and wants a
    scene's median point depth at ``median_depth`` (0: ``DEPTH_TARGET`` of the way into [near,
    far], the rule every model had before ``median_depth``): ``(near, far')`` whose
    ``DEPTH_TARGET`` point is ``median_depth``. Rounded to 12 decimals, so the default
    ``median_depth`` of (0.1, 1.0) gives (0.1, 1.0) exactly, as keys of stored solves have it."""
    if not median_depth:
        return float(near), float(far)
    return float(near), round(near + (median_depth - near) / DEPTH_TARGET, 12)
#: Starting focals, in units of the photo's longer side (the first is COLMAP's default prior);
#: the bundle adjustment refines each, the mapper keeps the reconstruction that explains the
#: observations best.
FOCAL_PRIORS = (1.2, 0.8)
#: A view the mapper could not register is still posed against the finished points when this
#: many correspondences agree (status "located").
LOCATE_MIN_INLIERS = 10


@dataclass(frozen=True)
class CameraSolve:
    """The cameras of V photos of one static scene, from the photos alone.

    world_from_cam: float64 [V, 4, 4]  OpenCV axes, in the frame of view ``root`` (the caller's
                                       view 0 when it is posed) and the renderer's unit; NaN
                                       rows for unposed views
    focal:          pixels of ``image_size`` (square pixels, principal point at the centre)
    image_size:     (H, W) of the photos the cameras were solved at
    status:         per view, one of ``STATUSES``
    root:           the view whose camera is the identity (-1: no view posed)
    scale:          the factor that took the solve's centres to the renderer's unit
    point_map:      the scene's 3D points (same frame and unit) and the descriptors that see
                    them, what ``locate.locate_photos`` poses new photos against
    """
    world_from_cam: np.ndarray
    focal: float
    image_size: tuple[int, int]
    status: tuple[str, ...]
    root: int
    scale: float
    point_map: PointMap

    @property
    def K(self) -> np.ndarray:
        """``K [3, 3]`` in pixels of ``image_size``."""
        return intrinsics(self.focal, self.image_size)

    @property
    def posed(self) -> np.ndarray:
        """bool [V]: the views with a camera ("solved" or "located")."""
        return np.array([s != "unposed" for s in self.status])

    def locate(self, photos) -> tuple[np.ndarray, np.ndarray]:
        """Poses of new ``photos`` (uint8, any size: brought to ``image_size`` by
        ``images.fit_to_model``, a centre crop where the aspect differs, as from the same
        camera) against this scene's points, its cameras fixed: ``locate.locate_photos``.
        Returns ``(world_from_cam [Q, 4, 4]`` (NaN where not posed), ``located bool [Q])``."""
        from ..images import fit_to_model
        copies = [fit_to_model(np.asarray(p), *self.image_size)[0] for p in photos]
        return locate_photos(self.point_map, self.focal, self.image_size, copies)


def check_photos(photos, name: str = "photos") -> list[np.ndarray]:
    """``photos`` as a list of V >= 1 uint8 arrays of one size, [H, W, 3] RGB or [H, W] grey, or
    ``InputError`` naming ``name``."""
    try:
        items = [np.asarray(p) for p in photos]
    except TypeError:
        raise InputError(f"{name}: expected a sequence of uint8 photos, got "
                         f"{type(photos).__name__}") from None
    if not items:
        raise InputError(f"{name}: expected at least one photo, got none")
    for k, p in enumerate(items):
        if p.dtype != np.uint8 or not (p.ndim == 2 or (p.ndim == 3 and p.shape[2] == 3)) \
                or min(p.shape[:2]) < 16:
            raise InputError(f"{name}[{k}]: expected uint8 [H, W, 3] or [H, W] with H, W >= 16, "
                             f"got {p.dtype} {p.shape}")
        if p.shape[:2] != items[0].shape[:2]:
            raise InputError(f"{name}[{k}]: size {p.shape[:2]} differs from {name}[0]'s "
                             f"{items[0].shape[:2]} (one camera: bring the photos to one size)")
    return items


def check_depth_range(depth_range) -> tuple[float, float]:
    """``depth_range`` as floats ``(near, far)`` with 0 <= near < far, or ``InputError``."""
    near, far = (float(x) for x in np.asarray(depth_range, np.float64).reshape(-1)[:2]) \
        if np.size(depth_range) == 2 else (np.nan, np.nan)
    if not (np.isfinite(near) and np.isfinite(far) and 0 <= near < far):
        raise InputError(f"depth_range: expected (near, far) with 0 <= near < far, got "
                         f"{depth_range!r}")
    return near, far


def check_focal(focal) -> float:
    """``focal`` (pixels) as a positive finite float, or ``InputError``: the one check of a
    given focal, for the solve and the refinement."""
    if (isinstance(focal, (bool, np.bool_)) or not isinstance(focal, (int, float, np.number))
            or not np.isfinite(focal) or focal <= 0):
        raise InputError(f"focal: expected a positive number of pixels, got {focal!r}")
    return float(focal)


def _point_map(rec: Reconstruction, tracks: Tracks, features, perm, k: int) -> PointMap:
    """The reconstruction's valid points and their active observations (views in the caller's
    numbering), their descriptors found in the photos enlarged ``k`` times."""
    active = rec.active(tracks)
    rows = np.flatnonzero(rec.point_ok)
    new_index = -np.ones(len(tracks), np.int64)
    new_index[rows] = np.arange(len(rows))
    t_idx, v_idx = np.nonzero(active)
    desc = np.stack([features[v].descriptors[tracks.keypoint[t, v]]
                     for t, v in zip(t_idx, v_idx)]) if len(t_idx) else np.zeros((0, 128), np.uint8)
    return PointMap(rec.points[rows], perm[v_idx], new_index[t_idx], desc, k)


def _median_depth(rec: Reconstruction, tracks: Tracks) -> float:
    active = rec.active(tracks)
    z = np.einsum("vij,pj->pvi", rec.R, rec.points)[..., 2] + rec.t[None, :, 2]
    z = z[active]
    return float(np.median(z)) if len(z) else float("nan")


def _distinct_support(rec: Reconstruction, features, matches, distinct, max_error: float) -> int:
    """How many distinct matches (``matches[a, b][distinct[a, b]]``: keypoints with neither a
    twin nor a mirrored twin) of the pairs of registered views the reconstruction's epipolar
    geometry explains within ``max_error`` pixels: what tells a reconstruction on the right
    matches from one on a repeated texture's shifted ones, which explains more matches overall
    and fewer distinct ones."""
    n = 0
    K = intrinsics(rec.focal, features[0].image_size)
    for (a, b), m in matches.items():
        if not (rec.registered[a] and rec.registered[b]) or not distinct[a, b].any():
            continue
        cam_a, cam_b = np.eye(4), np.eye(4)
        cam_a[:3, :3], cam_a[:3, 3] = rec.R[a], rec.t[a]
        cam_b[:3, :3], cam_b[:3, 3] = rec.R[b], rec.t[b]
        md = m[distinct[a, b]]
        F = fundamental_matrix(cam_b @ np.linalg.inv(cam_a), K)
        n += int((sampson_distances(features[a].uv[md[:, 0]], features[b].uv[md[:, 1]], F)
                  < max_error).sum())
    return n


def solve_cameras(photos, depth_range: tuple[float, float], *, focal: float | None = None,
                  options: MapperOptions | None = None) -> CameraSolve:
    """The cameras of ``photos`` (V uint8 photos of one size, RGB [H, W, 3] or grey [H, W]).

    depth_range: the renderer's (near, far): the cameras' unit puts the scene's median point
                 depth ``DEPTH_TARGET`` of the way into it
    focal:       a known focal in pixels of the photos to start from (default: each of
                 ``FOCAL_PRIORS`` x the longer side); the bundle adjustment refines it either way
    options:     the mapper's thresholds (pixels at ``two_view.REFERENCE_SIZE``) (default
                 ``MapperOptions()``)

    Photos under ``features.MIN_SIZE`` pixels, and low-texture photos under
    ``features.LOW_TEXTURE_SIZE``, are solved enlarged (``features.scene_features``); the cameras
    are reported for the photos as given. Steps: SIFT features of each photo and
    their matches across every pair (``features``); per pair F, H and the relative pose
    (``two_view``); tracks (``tracks``); the incremental mapper with bundle adjustment
    (``mapper``, ``triangulation``, ``bundle``), run twice, on every match and trusting the
    distinct keypoints first, keeping the reconstruction that registers more views and explains
    more distinct matches, mirrored twins excluded too (``_distinct_support``); views it could
    not register posed against its points (``locate``). Deterministic and order-free.
    """
    photos = check_photos(photos)
    near, far = check_depth_range(depth_range)
    if focal is not None:
        focal = check_focal(focal)
    V = len(photos)
    size = photos[0].shape[:2]
    perm = canonical_order(photos)
    features, k = scene_features([photos[v] for v in perm])   # in the photos enlarged k times
    H, W = size[0] * k, size[1] * k
    px = pixel_scale((H, W))
    opts = (options or MapperOptions()).in_pixels(px)
    focals = ((k * float(focal),) if focal is not None
              else tuple(prior * max(H, W) for prior in FOCAL_PRIORS))
    best = _best_reconstruction(features, focals, (H, W), opts, px)
    if best is None:
        return _unposed(V, focals[0] / k, size, k)
    rec, tracks = best
    cam_from_world, located = _canonical_cameras(rec, tracks, (H, W), opts.pnp_error)
    status = np.array(["unposed"] * V, dtype=object)
    status[perm[rec.registered]] = "solved"
    status[perm[located]] = "located"
    return finish_solve(rec, tracks, features, cam_from_world, status, perm, k, size,
                        (near, far))


def _distinct_matches(features, matches) -> tuple[list, dict, dict]:
    """Which keypoints and matches a repeated texture cannot have confused: ``(keypoint_distinct,
    distinct, unique)``, per view ``bool [N_v]`` the keypoints with no near twin in their photo
    (``distinct_keypoints``), per pair ``(a, b)`` of ``matches`` ``bool [M_ab]`` the matches of
    two such keypoints, and of two keypoints with no mirrored twin either."""
    keypoint_distinct = [distinct_keypoints(f) for f in features]
    distinct = {(a, b): keypoint_distinct[a][m[:, 0]] & keypoint_distinct[b][m[:, 1]]
                for (a, b), m in matches.items()}
    # The choice counts only matches whose keypoints have no mirrored twin either: a wall tiled
    # with a mirrored picture otherwise lends the wrong reconstruction distinct support. Only
    # there: the stricter set leaves too few keypoints for the pairs and registrations
    # (docs/CAMERAS.md, "Mirrored twins").
    keypoint_unique = [d & (twin_distance(f, mirrored=True) > DISTINCT_DISTANCE)
                       for d, f in zip(keypoint_distinct, features)]
    unique = {(a, b): keypoint_unique[a][m[:, 0]] & keypoint_unique[b][m[:, 1]]
              for (a, b), m in matches.items()}
    return keypoint_distinct, distinct, unique


def _best_reconstruction(features, focals: tuple[float, ...], size: tuple[int, int],
                         opts: MapperOptions, px: float) -> tuple[Reconstruction, Tracks] | None:
    """The reconstruction of the V views of ``features`` (photos of ``size`` (H, W), ``px``
    their ``pixel_scale``) and its tracks, or None (one view, or no pair can start one): the
    incremental mapper (starting focals ``focals``, pixels) run on every match and again
    trusting the distinct keypoints first, keeping the run that registers more views and, among
    those, explains more distinct matches, mirrored twins excluded too (``_distinct_support``)."""
    V = len(features)
    f0 = focals[0]
    matches = {(a, b): match_features(features[a], features[b])
               for a in range(V) for b in range(a + 1, V)}
    # Two reconstructions: one on every match, one whose pairs and registrations trust the
    # distinct keypoints first (no near twin in their photo); the one that registers more views
    # and, among those, explains more distinct matches is kept (docs/CAMERAS.md, "Repeated
    # patterns").
    keypoint_distinct, distinct, unique = _distinct_matches(features, matches)
    plain = {(a, b): estimate_two_view(features[a].uv, features[b].uv, m, f0, size,
                                       MAX_ERROR * px) for (a, b), m in matches.items()}
    best, best_key = None, None
    for trust_distinct in (False, True) if DISTINCT_DISTANCE > 0 else (False,):
        geometries = {(a, b): estimate_from_distinct(features[a].uv, features[b].uv, m,
                                                     distinct[a, b], f0, size, MAX_ERROR * px)
                      or plain[a, b] for (a, b), m in matches.items()} if trust_distinct \
            else plain
        inliers = {ab: g.inliers for ab, g in geometries.items() if g.config != "degenerate"}
        candidate_tracks = build_tracks(features, inliers)
        candidate = incremental_mapping(features, candidate_tracks, geometries, focals, size,
                                        opts, keypoint_distinct if trust_distinct else None) \
            if V > 1 else None
        if candidate is None:
            continue
        key = (int(candidate.registered.sum()),
               _distinct_support(candidate, features, matches, unique, MAX_ERROR * px))
        if best_key is None or key > best_key:
            best, best_key = (candidate, candidate_tracks), key
    return best


def _canonical_cameras(rec: Reconstruction, tracks: Tracks, size: tuple[int, int],
                       pnp_error: float) -> tuple[np.ndarray, np.ndarray]:
    """``(cam_from_world [V, 4, 4], located bool [V])`` in the canonical numbering: the views
    ``rec`` registered take its cameras; each other view is posed against the points it sees,
    the points held fixed (``pose_from_points`` in photos of ``size`` (H, W), at least
    ``LOCATE_MIN_INLIERS`` within ``pnp_error`` pixels), ``located`` where that succeeds and
    NaN rows where it does not."""
    V = len(rec.registered)
    cam_from_world = np.full((V, 4, 4), np.nan)
    located = np.zeros(V, dtype=bool)
    for v in np.flatnonzero(rec.registered):
        cam_from_world[v] = np.eye(4)
        cam_from_world[v, :3, :3], cam_from_world[v, :3, 3] = rec.R[v], rec.t[v]
    for v in np.flatnonzero(~rec.registered):
        sees = rec.point_ok & tracks.observed[:, v]
        pose = pose_from_points(rec.points[sees], tracks.uv[sees, v], rec.focal, size,
                                max_error=pnp_error, min_inliers=LOCATE_MIN_INLIERS)
        if pose is not None:
            cam_from_world[v] = np.eye(4)
            cam_from_world[v, :3, :3], cam_from_world[v, :3, 3] = pose[0], pose[1]
            located[v] = True
    return cam_from_world, located


def _unposed(V: int, focal: float, size: tuple[int, int], k: int) -> CameraSolve:
    """The solve of photos none of which could be posed."""
    empty = PointMap(np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64),
                     np.zeros((0, 128), np.uint8), k)
    return CameraSolve(np.full((V, 4, 4), np.nan), focal, size, ("unposed",) * V, -1, 1.0, empty)


def finish_solve(rec: Reconstruction, tracks: Tracks, features, cam_from_world: np.ndarray,
                 status: np.ndarray, perm: np.ndarray, k: int, size: tuple[int, int],
                 depth_range: tuple[float, float]) -> CameraSolve:
    """The ``CameraSolve`` of a finished reconstruction: ``cam_from_world [V, 4, 4]`` (NaN where
    unposed) and ``status`` per view, in the numbering of ``features``, which are the caller's
    views ``perm``, found in photos of ``size`` enlarged ``k`` times. The first posed view of the
    caller's becomes the root (the identity), and the unit puts the median depth of the points
    ``DEPTH_TARGET`` of the way into ``depth_range``."""
    near, far = depth_range
    V = len(status)
    world_from_cam = np.full((V, 4, 4), np.nan)
    posed = np.isfinite(cam_from_world).all(axis=(1, 2))
    world_from_cam[perm[posed]] = np.linalg.inv(cam_from_world[posed])
    root = int(np.flatnonzero(status != "unposed")[0])
    old_from_root = world_from_cam[root].copy()
    depth = _median_depth(rec, tracks)
    scale = (near + DEPTH_TARGET * (far - near)) / depth if np.isfinite(depth) and depth > 0 \
        else 1.0
    root_from_old = np.linalg.inv(old_from_root)
    world_from_cam = root_from_old @ world_from_cam
    world_from_cam[:, :3, 3] *= scale
    world_from_cam[root] = np.eye(4)
    world_from_cam[status == "unposed"] = np.nan
    point_map = _point_map(rec, tracks, features, perm, k)
    point_map = point_map.transformed(root_from_old).transformed(np.eye(4), scale)
    return CameraSolve(world_from_cam, rec.focal / k, size, tuple(status.tolist()), root, scale,
                       point_map)
