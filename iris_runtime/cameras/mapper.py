"""Step 7 of the camera solve: the incremental mapper, which grows one reconstruction view by view.

As COLMAP's incremental mapper does: start from the pair with the most F-consistent matches
seen under a wide enough angle (its essential matrix gives the two poses), triangulate the tracks
it sees (when every pair sees a plane, from the planar pair that moves most), then repeatedly
register the view that sees the most of the triangulated points (PnP),
extend and add tracks, and bundle-adjust everything (the focal too, once three views fix it),
dropping observations that reproject badly. A view that never gathers enough inliers stays
unregistered: it is reported, not guessed. Every choice is a function of the data (ties broken
by view index), so given views in a fixed order the result is fixed.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from .bundle import bundle_adjust, reprojection_errors
from .locate import PNP_ERROR, PNP_ITERATIONS, PNP_MIN_INLIERS, pose_distinct_first
from .tracks import Tracks
from .triangulation import camera_centres, max_ray_angles, triangulate
from .two_view import MAX_ERROR, MIN_INLIERS, TwoViewGeometry, relative_pose

__all__ = ["MapperOptions", "Reconstruction", "incremental_mapping", "reprojection_score"]


@dataclass(frozen=True)
class MapperOptions:
    """Thresholds of the mapper, in degrees and in pixels of photos of ``REFERENCE_SIZE``.

    init_min_inliers:   fewest F-consistent matches of the starting pair (COLMAP's relaxed value)
    planar_min_angle:   where no pair is "general" (every pair sees a plane, as a camera moved
                        over a poster or a facade does), planar pairs seen under at least this
                        triangulation angle may start, as COLMAP starts from a homography
    planar_point_angle: ... and points then need only this angle (``min_angle`` otherwise)
    init_trials:        starting pairs tried when one does not register every view
    min_trials:         starting pairs tried even when the first registers every view (the
                        reconstruction kept is then the one that explains the observations
                        best): 2 is more accurate than 1 in iris-eval's protocol, 1 solves
                        in 2/3 to 3/4 of the time (docs/CAMERAS.md "Starting pairs")
    init_angle:         triangulation angle (median, degrees) at which a starting pair counts in
                        full; narrower pairs are scored down in proportion
    two_view_error:     inlier threshold of the starting pair's essential matrix
    pnp_error:          reprojection threshold of a view's registration
    pnp_min_inliers:    fewest 2D-3D inliers of a registration
    max_error:          observations reprojecting further after a bundle adjustment are dropped
    min_angle:          points seen under a narrower angle carry no depth and are not kept
    loss_scale:         Cauchy scale of the bundle adjustment
    min_focal_views:    the focal is refined once this many views are registered
    ba_iterations:      Levenberg-Marquardt iterations after each registration / at the end
    ba_points:          points adjusted after each registration (the most observed; the end
                        adjusts all)
    pnp_method:         OpenCV's PnP in a registration's RANSAC (``locate.pose_from_points``)
    pnp_confident_stop: ... and whether it gives up once a pose would have been found with its
                        confidence (``locate.confident_iterations``; the refinement's witness)
    pnp_iterations:     ... and its iterations at most (``locate.PNP_ITERATIONS``; the witness
                        runs fewer, ``refine.CappedPnP.max_iterations``)
    finish_min_views:   a starting pair's reconstruction that registers fewer views is kept as
                        it stands, without the final adjustments (the refinement's witness: a
                        mapping of so few views can confirm nothing, ``refine.witness``)
    """
    init_min_inliers: int = 30
    planar_min_angle: float = 0.5
    planar_point_angle: float = 0.25
    init_trials: int = 4
    min_trials: int = 2
    init_angle: float = 16.0
    two_view_error: float = MAX_ERROR
    pnp_error: float = PNP_ERROR
    pnp_min_inliers: int = PNP_MIN_INLIERS
    max_error: float = 3.0
    min_angle: float = 1.5
    loss_scale: float = 1.0
    min_focal_views: int = 3
    ba_iterations: int = 10
    ba_points: int = 400
    final_ba_points: int = 1500
    final_ba_iterations: int = 50
    pnp_method: int = cv2.SOLVEPNP_SQPNP
    pnp_confident_stop: bool = False
    pnp_iterations: int = PNP_ITERATIONS
    finish_min_views: int = 0

    def in_pixels(self, px: float) -> MapperOptions:
        """These options with their pixel thresholds for photos ``px`` times ``REFERENCE_SIZE``
        (``two_view.pixel_scale``)."""
        return replace(self, two_view_error=self.two_view_error * px,
                       pnp_error=self.pnp_error * px, max_error=self.max_error * px,
                       loss_scale=self.loss_scale * px)


@dataclass
class Reconstruction:
    """The mapper's state: cam_from_world ``R [V, 3, 3]``, ``t [V, 3]``, ``focal`` (pixels),
    ``registered [V]``, one point per track ``points [T, 3]`` (valid where ``point_ok [T]``),
    ``rejected [T, V]``: observations dropped as outliers, ``first`` the pair it started from."""
    R: np.ndarray
    t: np.ndarray
    focal: float
    registered: np.ndarray
    points: np.ndarray
    point_ok: np.ndarray
    rejected: np.ndarray
    first: tuple[int, int]
    history: list = field(default_factory=list)

    def active(self, tracks: Tracks) -> np.ndarray:
        """bool [T, V]: observations of valid points in registered views, not rejected."""
        return (tracks.observed & ~self.rejected & self.registered[None]
                & self.point_ok[:, None])


def _init_pairs(geometries: dict[tuple[int, int], TwoViewGeometry], opts: MapperOptions,
                planar: bool = False):
    """Candidate starting pairs, best first: general pairs with a pose and enough inliers, scored
    by the inliers the homography does not explain (those that fix the essential matrix) x
    min(1, angle / init_angle); ties by the pair's indices. ``planar``: the planar-or-panoramic
    pairs instead, seen under at least ``planar_min_angle`` (a plane, not a rotation), scored by
    their inliers x min(1, angle / init_angle)."""
    scored = []
    for (i, j), g in geometries.items():
        if g.cam2_from_cam1 is None or len(g.inliers) < opts.init_min_inliers:
            continue
        if not planar and g.config == "general":
            off_plane = len(g.inliers) - g.num_h_inliers
            scored.append((-off_plane * min(1.0, g.triangulation_angle / opts.init_angle), i, j))
        elif (planar and g.config == "planar_or_panoramic"
              and g.triangulation_angle >= opts.planar_min_angle):
            scored.append((-len(g.inliers) * min(1.0, g.triangulation_angle / opts.init_angle),
                           i, j))
    return [(i, j) for _, i, j in sorted(scored)]


def _triangulate_missing(rec: Reconstruction, tracks: Tracks, centre, opts: MapperOptions):
    """Points for the tracks without one that two registered views see (their observations
    not rejected), where they pass the triangulation checks."""
    use = tracks.observed & rec.registered[None] & ~rec.rejected
    todo = ~rec.point_ok & (use.sum(1) >= 2)
    if not todo.any():
        return
    X, ok = triangulate(rec.R, rec.t, rec.focal, centre, tracks.uv[todo], use[todo],
                        max_error=opts.max_error, min_angle=opts.min_angle)
    idx = np.flatnonzero(todo)[ok]
    rec.points[idx] = X[ok]
    rec.point_ok[idx] = True


def _adjust(rec: Reconstruction, tracks: Tracks, centre, opts: MapperOptions, iterations: int,
            refine_focal: bool | None = None, max_points: int | None = None):
    """Bundle-adjust the registered views and valid points, then drop observations that
    reproject beyond ``max_error`` (or behind the camera) and points left with fewer than two
    observations or too narrow an angle. With ``max_points``, the adjustment sees only the
    points with the most observations (the cameras need no more), and the others are
    triangulated again on the adjusted cameras."""
    active = rec.active(tracks)
    keep = active.sum(1) >= 2
    rec.point_ok &= keep
    active &= keep[:, None]
    adjusted = keep.copy()
    if max_points is not None and keep.sum() > max_points:
        order = np.lexsort((np.arange(len(keep)), -active.sum(1)))     # most observed first
        adjusted = np.zeros_like(keep)
        adjusted[order[:max_points]] = True
        adjusted &= keep
    i, j = rec.first
    refine = int(rec.registered.sum()) >= opts.min_focal_views if refine_focal is None \
        else refine_focal
    res = bundle_adjust(rec.R, rec.t, rec.focal, centre, rec.points[adjusted],
                        tracks.uv[adjusted], active[adjusted], fixed_view=i, scale_view=j,
                        refine_focal=refine, loss_scale=opts.loss_scale,
                        max_iterations=iterations)
    rec.R, rec.t, rec.focal = res.R, res.t, res.focal
    rec.points[adjusted] = res.points
    rest = keep & ~adjusted
    if rest.any():
        X, ok = triangulate(rec.R, rec.t, rec.focal, centre, tracks.uv[rest], active[rest],
                            max_error=np.inf, min_angle=0.0)
        rec.points[rest] = X
        rec.point_ok[np.flatnonzero(rest)[~ok]] = False
    rec.history.append((int(rec.registered.sum()), res.iterations, res.cost, res.focal))
    err, z = reprojection_errors(rec.R, rec.t, rec.focal, centre, rec.points, tracks.uv)
    rec.rejected |= active & ((err > opts.max_error) | (z <= 0))
    active = rec.active(tracks)
    angle = max_ray_angles(rec.points, camera_centres(rec.R, rec.t), active)
    rec.point_ok &= (active.sum(1) >= 2) & (angle >= opts.min_angle)


def _start(pair, geometries, features, tracks: Tracks, focal, centre, image_size, opts
           ) -> Reconstruction | None:
    """A reconstruction of the pair's two views (their essential matrix at ``focal``) and the
    tracks both see, adjusted; None when the pair gives no pose at this focal."""
    i, j = pair
    V, T = tracks.keypoint.shape[1], len(tracks)
    m = geometries[pair].inliers
    pose, _ = relative_pose(features[i].uv[m[:, 0]], features[j].uv[m[:, 1]], focal, image_size,
                            opts.two_view_error)
    if pose is None:
        return None
    R, t = np.tile(np.eye(3), (V, 1, 1)), np.zeros((V, 3))
    R[j], t[j] = pose[:3, :3], pose[:3, 3]
    registered = np.zeros(V, bool)
    registered[[i, j]] = True
    rec = Reconstruction(R, t, float(focal), registered, np.zeros((T, 3)), np.zeros(T, bool),
                         np.zeros((T, V), bool), (i, j))
    _triangulate_missing(rec, tracks, centre, opts)
    if rec.point_ok.sum() < opts.pnp_min_inliers:        # too few points to register a view on
        return None
    _adjust(rec, tracks, centre, opts, opts.ba_iterations)
    return rec


def _register(rec: Reconstruction, tracks: Tracks, v: int, image_size, opts, distinct) -> bool:
    """Pose view v by PnP on its keypoints that see valid points (those of ``distinct[v]``
    first, when given); on success its observations that disagree with the pose are rejected."""
    sees = rec.point_ok & tracks.observed[:, v]
    first = (np.zeros(int(sees.sum()), bool) if distinct is None       # none: plain PnP
             else distinct[v][tracks.keypoint[sees, v]])
    pose = pose_distinct_first(rec.points[sees], tracks.uv[sees, v], first, rec.focal,
                               image_size, max_error=opts.pnp_error,
                               min_inliers=opts.pnp_min_inliers, method=opts.pnp_method,
                               confident_stop=opts.pnp_confident_stop,
                               max_iterations=opts.pnp_iterations)
    if pose is None:
        return False
    R, t, inliers = pose
    rec.R[v], rec.t[v] = R, t
    rec.registered[v] = True
    rec.rejected[np.flatnonzero(sees)[~inliers], v] = True
    return True


def _grow(rec: Reconstruction, tracks: Tracks, centre, image_size, opts: MapperOptions,
          distinct=None):
    """Register views into ``rec`` while one sees enough of its points, then finish it."""
    V = len(rec.registered)
    failed_at = np.full(V, -1)        # points a view saw when its registration last failed
    while not rec.registered.all():
        seen = (rec.point_ok[:, None] & tracks.observed).sum(0)
        seen = np.where(rec.registered | (seen <= failed_at), -1, seen)
        v = int(np.argmax(seen))
        if seen[v] < opts.pnp_min_inliers:
            break
        if not _register(rec, tracks, v, image_size, opts, distinct):
            failed_at[v] = seen[v]
            continue
        _triangulate_missing(rec, tracks, centre, opts)
        _adjust(rec, tracks, centre, opts, opts.ba_iterations, max_points=opts.ba_points)
    if rec.registered.sum() < opts.finish_min_views:
        return rec
    for _ in range(2):
        _triangulate_missing(rec, tracks, centre, opts)
        _adjust(rec, tracks, centre, opts, opts.final_ba_iterations, refine_focal=True,
                max_points=opts.final_ba_points)
    return rec


def reprojection_score(rec: Reconstruction, tracks: Tracks, centre, opts: MapperOptions) -> float:
    """Mean truncated squared reprojection error (pixels^2, truncated at ``max_error``) over the
    observations, in the registered views, of every track seen there twice or more; a track
    without a point counts as unexplained (the truncation value) in each of them. Lower is
    better; reconstructions registering the same views are compared on the same observations."""
    seen = tracks.observed & rec.registered[None]
    counted = seen & (seen.sum(1) >= 2)[:, None]
    err, z = reprojection_errors(rec.R, rec.t, rec.focal, centre, rec.points, tracks.uv)
    e2 = np.where(rec.point_ok[:, None] & (z > 0), np.minimum(err, opts.max_error) ** 2,
                  opts.max_error ** 2)
    return float(e2[counted].mean()) if counted.any() else np.inf


def incremental_mapping(features, tracks: Tracks,
                        geometries: dict[tuple[int, int], TwoViewGeometry],
                        focals: tuple[float, ...], image_size: tuple[int, int],
                        opts: MapperOptions = MapperOptions(),
                        distinct: list[np.ndarray] | None = None) -> Reconstruction | None:
    """One reconstruction of the views of ``tracks`` (keypoints ``features``, pair geometries
    ``geometries``), or None when no pair can start one.

    Each starting focal of ``focals`` (pixels) is tried, and for each up to ``init_trials``
    starting pairs, best first (at least ``min_trials``), until one registers every view that
    could be (pairs with fewer than ``init_min_inliers`` inliers start only when no pair has as
    many). The reconstruction kept registers the most views and, among those, has the lowest
    ``reprojection_score``: a wrong focal can lead the bundle adjustment into a consistent but
    wrong reconstruction that explains fewer of the observations (docs/record/cameras.md,
    "Choices, each measured ...": the starting focals).
    Views it cannot register stay ``registered`` False. ``distinct``: per view, bool [N_v] over its
    keypoints, those without a near twin in their photo (``features.distinct_keypoints``);
    given, each view is registered on the points its distinct keypoints see first
    (``locate.pose_distinct_first``)."""
    H, W = image_size
    centre = np.array([W / 2.0, H / 2.0])
    starts = _init_pairs(geometries, opts) or _init_pairs(
        geometries, replace(opts, init_min_inliers=MIN_INLIERS))
    if not starts:
        # Every pair sees a plane (a poster, a facade, a table top) or barely moves: start from
        # the pair that moves most, and keep points seen under narrower angles, which many
        # matches on a plane still place.
        starts = _init_pairs(geometries, opts, planar=True)
        opts = replace(opts, min_angle=opts.planar_point_angle)
    # A view with fewer track observations than a registration needs can never be registered:
    # a reconstruction holding every other view is as complete as this data allows.
    possible = tracks.observed.sum(0) >= opts.pnp_min_inliers
    best, best_key = None, None
    for focal in focals:
        for trial, pair in enumerate(starts[:opts.init_trials]):
            rec = _start(pair, geometries, features, tracks, focal, centre, image_size, opts)
            if rec is None:
                continue
            rec = _grow(rec, tracks, centre, image_size, opts, distinct)
            key = (int(rec.registered.sum()), -reprojection_score(rec, tracks, centre, opts))
            if best_key is None or key > best_key:
                best, best_key = rec, key
            if rec.registered[possible].all() and trial + 1 >= opts.min_trials:
                break
    return best
