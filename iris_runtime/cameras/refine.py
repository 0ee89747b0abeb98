"""Step 9 of the camera solve: cameras a model predicted, refined by the photos.

The incremental mapper (``mapper``) spends most of the solve finding a start: starting pairs,
focal priors and view-by-view registrations, tried until one reconstruction explains the photos.
A model's camera head already gives every view a pose and the focal, so here they start a bundle
adjustment instead: SIFT matches of every pair (``features``), kept where their essential matrix
at the model's focal explains them (``two_view.essential_pose``, which also gives the pair's
relative pose), tracks (``tracks``), then ``STARTS``: the model's cameras and two built from the
pairs' relative poses (``average_rotations``, ``average_centres``). Each gets a first round of
bundle adjustment (``bundle.fast_bundle_adjust``) with the focal held (a pose error of several
degrees moves the focal as much as a wrong focal does), after which the best is chosen, and a
second with the focal free. Like the solve it runs in ``canonical_order`` and its result is in
the solve's terms (``solve.CameraSolve``: its unit, root and point map), so it replaces a
model's cameras as the solve does (``replace.refine_model_cameras``). Its accuracy rests on its
starts: where the head and the pairs are both far off, the adjustment ends in a wrong minimum
(docs/CAMERAS.md, "Refining the model's cameras"). A wrong minimum is rarely reached from two
starts, so the chosen start is kept only where another start's cameras agree with it
(``agreement``; "Telling a wrong refinement"). Where none does, the views on which one does
(``agreeing_views``) are kept if they are half the views or more, and the others are posed
against their points as the mapper registers a view (``_salvaged``; "Salvaging the views two
starts agree on"). Where no start agrees on that many, a quick incremental mapping on the
refinement's own pairs (``_witness``) is the other witness: a start it confirms is kept, or the
views it agrees with the best start on are salvaged; otherwise the caller is told to run the
solve ("A mapping as the witness").
"""
from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import InputError
from .bundle import fast_bundle_adjust, reprojection_errors
from .features import canonical_order, match_features, scene_features
from .locate import PNP_MIN_INLIERS, pose_from_points
from .mapper import MapperOptions, Reconstruction, incremental_mapping, reprojection_score
from .solve import (LOCATE_MIN_INLIERS, CameraSolve, check_depth_range, check_photos,
                    finish_solve)
from .tracks import build_tracks
from .triangulation import triangulate
from .two_view import (MAX_ERROR, TwoViewGeometry, essential_pose, intrinsics,
                       median_triangulation_angle, pixel_scale)

__all__ = ["refine_cameras", "average_rotations", "average_centres", "agreement",
           "agreeing_pairs", "agreeing_views", "salvage_core", "STARTS", "REFINE_ROUNDS",
           "REFINE_TOLERANCE", "MIN_AGREEMENT", "AGREEMENT_DEGREES", "MIN_CORE_SHARE",
           "MIN_CORE_VIEWS", "WITNESS_TRIALS", "WITNESS_ITERATIONS", "RETRIANGULATION_ANGLE",
           "REFINED_MIN_OBSERVATIONS", "AVERAGING_ROUNDS", "AVERAGING_SCALE", "SALVAGE_PNP",
           "SALVAGE_PNP_ITERATIONS"]

#: The cameras the adjustment starts from: the model's ("model"), the model's centres turned by
#: the pairs' rotations (their essential matrices' rotations averaged, ``average_rotations``:
#: "rotations"), and the pairs' rotations with the centres their translation directions give
#: (``average_centres``: "pairs", which needs nothing of the model but its focal); the
#: adjustment that registers the most views and reprojects the observations best
#: (``mapper.reprojection_score``) is kept. A head a few degrees off starts well from its own
#: cameras; where it has not learned a scene's rotations, or its centres, the pairs' do better
#: (docs/CAMERAS.md, "Refining the model's cameras").
STARTS = ("model", "rotations", "pairs")
#: Reweighting rounds of the rotation averaging, and its Cauchy scale (degrees).
AVERAGING_ROUNDS = 4
AVERAGING_SCALE = 5.0

#: The bundle adjustment's rounds: (Levenberg-Marquardt iterations, whether the focal moves).
REFINE_ROUNDS = ((20, False), (50, True))
#: A round ends early at a step that lowers the cost by less than this share of it (the solve's
#: adjustments go on to ``bundle.RELATIVE_TOLERANCE``, a hundredth of this). The three starts'
#: six rounds are the refinement's largest cost, and on the held-out scenes the steps past this
#: are a third of their iterations for 0.003 of RPA@15 (docs/CAMERAS.md, "What the refinement
#: costs").
REFINE_TOLERANCE = 1e-4
#: Keypoints matched per photo (the strongest of the solve's ``features.MAX_FEATURES``; SIFT
#: describes no others): the matching's cost grows with their square and a start needs fewer
#: than a mapper; 0: the solve's.
MAX_KEYPOINTS = 1024
#: Photos under ``features.MIN_SIZE`` are enlarged to this longer side (the solve: to
#: ``features.LOW_TEXTURE_SIZE``): 64x64 photos 3 times instead of 5, a third of the pixels SIFT
#: reads. Chosen on the validation scenes at 64x64 among 2, 3 and 4 times (docs/CAMERAS.md,
#: "Salvaging the views two starts agree on").
SMALL_SIZE = 192
#: Rounds after which the best start is chosen; the others run the rest of their rounds only as
#: long as none has confirmed it (``agreement``).
CHOOSE_AFTER = 1
#: Points dropped after the first round are triangulated again where seen under this angle
#: (degrees) or more.
RETRIANGULATION_ANGLE = 0.5
#: A view counts as refined ("solved") with this many observations left after the last round;
#: others are reported "unposed" (the caller keeps the model's camera for them).
REFINED_MIN_OBSERVATIONS = LOCATE_MIN_INLIERS
#: The chosen start's refined cameras must agree with another start's on this share of the pairs
#: of views (``agreement``: relative rotation and baseline direction within
#: ``AGREEMENT_DEGREES``), or the refinement is taken to have ended in a wrong minimum and is
#: salvaged (``MIN_CORE_SHARE``) or returns None (the caller runs the solve). Off with fewer
#: than two ``STARTS``. Two thirds: on the held-out scenes the starts agree on 0.75 or more or on
#: 0.64 or less, and the wrong minimum of a real scene reaches 0.54 (docs/CAMERAS.md, "Telling a
#: wrong refinement").
MIN_AGREEMENT = 2.0 / 3.0
AGREEMENT_DEGREES = 5.0
#: Where no start confirms the chosen one, the largest set of views on which one agrees with it
#: pair by pair is kept if it holds this share of the views and ``MIN_CORE_VIEWS`` or more, and
#: the others are posed against its points (``_salvaged``); otherwise the caller runs the solve.
#: Half: the kept views are then the majority the scene's points come from. Four: the three-view
#: sets salvaged on the validation scenes and on `Castle-simu` ended worse than the solve, and a
#: share of 0 (three views) gave lower validation RPA@15 than half (docs/CAMERAS.md, "Salvaging
#: the views two starts agree on").
MIN_CORE_SHARE = 0.5
MIN_CORE_VIEWS = 4
#: Where no start agrees with the best on ``MIN_CORE_VIEWS``, the incremental mapper runs on the
#: refinement's pairs and tracks at the best start's focal, trying this many starting pairs
#: (``_witness``; 0: no witness, the caller runs the solve). Its reconstruction owes nothing to
#: the starts' cameras, though it shares the pairs' essential matrices with two of them: a start
#: it confirms (``MIN_AGREEMENT``) is kept, or the views it agrees with the best start on are
#: salvaged (``MIN_CORE_SHARE``, ``MIN_CORE_VIEWS``). Two: with one, held-out scene 8 as
#: iris-eval brings it to 64x64 still goes to the solve; four give the same cameras as two
#: (docs/CAMERAS.md, "A mapping as the witness").
WITNESS_TRIALS = 2
#: The witness mapping's Levenberg-Marquardt iterations after each registration and at the end
#: (the solve's: ``MapperOptions.ba_iterations`` 10 and ``final_ba_iterations`` 50). With
#: every scene sent to the witness, its cameras were as often within 5 degrees of the truth
#: (the resolution ``agreement`` judges them at) on the validation scenes, and on the held-out
#: ones, in three quarters of its time (docs/CAMERAS.md, "A cheaper witness").
WITNESS_ITERATIONS = (5, 20)
#: OpenCV's PnP in the RANSAC that poses the views a salvage did not keep, and in the witness's
#: registrations: AP3P on four-point samples, not the solve's SQPnP. Views with few inliers run
#: all of the RANSAC's iterations, and there SQPnP made the one salvaged held-out scene and the
#: witness's hardest scene slower, to the same cameras (docs/CAMERAS.md, "Salvaging the views
#: two starts agree on", "A mapping as the witness").
SALVAGE_PNP = cv2.SOLVEPNP_AP3P
#: ... and its RANSAC's iterations at most (the solve's: ``locate.PNP_ITERATIONS``, 1000): by
#: then a pose that 42% of a view's correspondences support would have been drawn with the
#: RANSAC's confidence (``locate.confident_iterations``). The views whose pose only more
#: iterations find are those few correspondences support. With every scene sent to the
#: witness, it registered the same views at the same RPA@5 and RPA@15 on all 80 benchmark
#: scenes as with 1000 iterations (docs/CAMERAS.md, "Fewer PnP iterations for the salvage and
#: the witness").
SALVAGE_PNP_ITERATIONS = 300
#: Rigid-pose tolerance of the model's cameras: |R^T R - I| and the last row.
_RIGID_TOLERANCE = 1e-3


def _check_start(world_from_cam, focal, V: int) -> tuple[np.ndarray, float]:
    poses = np.asarray(world_from_cam, dtype=np.float64)
    if poses.shape != (V, 4, 4) or not np.isfinite(poses).all():
        raise InputError(f"world_from_cam: expected finite float [{V}, 4, 4] (one pose per photo),"
                         f" got shape {poses.shape}")
    R = poses[:, :3, :3]
    if (np.abs(R.transpose(0, 2, 1) @ R - np.eye(3)).max() > _RIGID_TOLERANCE
            or np.abs(np.linalg.det(R) - 1).max() > _RIGID_TOLERANCE
            or np.abs(poses[:, 3] - [0, 0, 0, 1]).max() > _RIGID_TOLERANCE):
        raise InputError("world_from_cam: expected rigid poses (rotation and translation, last "
                         "row 0 0 0 1)")
    if (isinstance(focal, (bool, np.bool_)) or not isinstance(focal, (int, float, np.number))
            or not np.isfinite(focal) or focal <= 0):
        raise InputError(f"focal: expected a positive number of pixels, got {focal!r}")
    return poses, float(focal)


def average_rotations(relative: dict[tuple[int, int], tuple[np.ndarray, float]],
                      R_start: np.ndarray) -> np.ndarray:
    """Rotations ``R [V, 3, 3]`` (cam_from_world) that agree best with the pairs' relative
    rotations ``relative {(a, b): (R_ab [3, 3] cam_b_from_cam_a, weight)}``: chordal L2
    averaging (the top three eigenvectors of the block matrix of the pairs, each block projected
    onto SO(3)), reweighted ``AVERAGING_ROUNDS`` times by the pairs' residual angles (Cauchy,
    ``AVERAGING_SCALE`` degrees) so that a wrong pair does not drag the others. View 0 keeps
    ``R_start[0]``; views no pair links to view 0 keep ``R_start``'s."""
    V = len(R_start)
    linked, grew = {0}, True
    while grew:
        grew = False
        for a, b in relative:
            if (a in linked) != (b in linked):
                linked |= {a, b}
                grew = True
    views = sorted(linked)
    pos = {v: k for k, v in enumerate(views)}
    pairs = [(pos[a], pos[b], R_ab, w) for (a, b), (R_ab, w) in relative.items()
             if a in pos and b in pos]
    out = R_start.copy()
    if len(views) < 2:
        return out
    weights = np.array([w for *_, w in pairs], np.float64)
    for _ in range(AVERAGING_ROUNDS):
        G = np.zeros((3 * len(views), 3 * len(views)))
        for (i, j, R_ij, _), w in zip(pairs, weights):
            G[3 * j:3 * j + 3, 3 * i:3 * i + 3] += w * R_ij
            G[3 * i:3 * i + 3, 3 * j:3 * j + 3] += w * R_ij.T
        X = np.linalg.eigh(G)[1][:, -3:].reshape(len(views), 3, 3)
        Q = _nearest_rotations(X @ np.linalg.inv(X[0]))          # view k from view 0
        residual = np.array([np.degrees(_angle(Q[j] @ Q[i].T, R_ij)) for i, j, R_ij, _ in pairs])
        weights = np.array([w for *_, w in pairs]) / (1.0 + (residual / AVERAGING_SCALE) ** 2)
    out[views] = Q @ R_start[0]
    return out


def average_centres(relative: dict[tuple[int, int], tuple[np.ndarray, float]], R: np.ndarray,
                    start: np.ndarray) -> np.ndarray:
    """Camera centres ``[V, 3]`` whose baselines point along the pairs' translation directions
    (``relative {(a, b): (cam_b_from_cam_a [4, 4] (unit translation), weight)}``, rotations
    ``R [V, 3, 3]`` cam_from_world): the least-squares null vector of d_ab x (c_a - c_b) = 0
    with c_0 fixed at ``start [V, 3]``'s, scaled (and signed) to agree best with ``start``'s
    centres; ``start`` itself where the directions leave more than that scale free."""
    V = len(R)
    rows = []
    for (a, b), (T, w) in relative.items():
        d = R[b].T @ T[:3, 3]                         # c_a - c_b, in the world frame
        cross = np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
        A = np.zeros((3, 3 * V))
        A[:, 3 * a:3 * a + 3], A[:, 3 * b:3 * b + 3] = cross, -cross
        rows.append(np.sqrt(w) * A)
    if not rows:
        return start
    A = np.concatenate(rows)[:, 3:]                   # c_0 is fixed
    if A.shape[0] < A.shape[1]:
        return start
    _, sv, Vt = np.linalg.svd(A)
    if sv[-2] < 1e-9 * sv[0]:
        return start
    c = np.concatenate([np.zeros(3), Vt[-1]]).reshape(V, 3)
    rel = start - start[0]
    return start[0] + c * (np.sum(c * rel) / max(np.sum(c * c), 1e-300))


def agreeing_pairs(R_a: np.ndarray, t_a: np.ndarray, posed_a: np.ndarray, R_b: np.ndarray,
                   t_b: np.ndarray, posed_b: np.ndarray) -> np.ndarray:
    """bool [V, V], symmetric: the pairs of views posed in both cameras a and b (cam_from_world
    ``R [V, 3, 3]``, ``t [V, 3]``, ``posed bool [V]``) whose relative rotation and baseline
    direction (scale-free, as RPA measures them) agree within ``AGREEMENT_DEGREES``."""
    C_a = -np.einsum("vji,vj->vi", R_a, t_a)
    C_b = -np.einsum("vji,vj->vi", R_b, t_b)
    tolerance = np.radians(AGREEMENT_DEGREES)
    V = len(R_a)
    agree = np.zeros((V, V), bool)
    for i in range(V):
        for j in range(i + 1, V):
            if not (posed_a[i] and posed_a[j] and posed_b[i] and posed_b[j]):
                continue
            # Baselines in camera i's frame: the frames of a and b may differ by any similarity.
            d_a, d_b = R_a[i] @ (C_a[j] - C_a[i]), R_b[i] @ (C_b[j] - C_b[i])
            n = np.linalg.norm(d_a) * np.linalg.norm(d_b)
            agree[i, j] = agree[j, i] = bool(
                n > 0 and _angle(R_a[j] @ R_a[i].T, R_b[j] @ R_b[i].T) <= tolerance
                and np.arccos(np.clip(d_a @ d_b / n, -1.0, 1.0)) <= tolerance)
    return agree


def agreement(R_a: np.ndarray, t_a: np.ndarray, posed_a: np.ndarray, R_b: np.ndarray,
              t_b: np.ndarray, posed_b: np.ndarray) -> float:
    """The share of the pairs of views posed in cameras a on which cameras b agree
    (``agreeing_pairs``; a pair b leaves unposed disagrees). 0 when a poses fewer than two
    views."""
    i, j = np.triu_indices(len(R_a), 1)
    counted = posed_a[i] & posed_a[j]
    agree = agreeing_pairs(R_a, t_a, posed_a, R_b, t_b, posed_b)[i, j]
    return float(agree[counted].mean()) if counted.any() else 0.0


def agreeing_views(agree: np.ndarray) -> np.ndarray:
    """bool [V]: the largest set of views every pair of which agrees (``agree`` bool [V, V],
    symmetric, from ``agreeing_pairs``), the one with the lowest view indices among equals: a
    largest clique, by trying the sets largest first (at most 2^V of them; V is a handful)."""
    V = len(agree)
    best = np.zeros(V, bool)
    for n in range(V, 1, -1):
        for views in itertools.combinations(range(V), n):
            if agree[np.ix_(views, views)][np.triu_indices(n, 1)].all():
                best[list(views)] = True
                return best
    return best


def _nearest_rotations(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    D = np.ones(M.shape[:-1])
    D[..., -1] = np.sign(np.linalg.det(U @ Vt))
    return (U * D[..., None, :]) @ Vt


def _angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    return float(np.arccos(np.clip((np.trace(Ra.T @ Rb) - 1.0) / 2.0, -1.0, 1.0)))


@dataclass
class _Adjustment:
    """One start's state: cam_from_world ``R [V, 3, 3]``, ``t [V, 3]``, ``focal``, one point per
    track ``X [T, 3]`` and the observations it keeps, ``active [T, V]``."""
    R: np.ndarray
    t: np.ndarray
    focal: float
    X: np.ndarray
    active: np.ndarray


def _start(R, t, f, centre, tracks, views=None) -> _Adjustment:
    """The adjustment of cameras ``R, t, f`` with every track seen by ``views`` (bool [V];
    None: all) triangulated on them."""
    observed = tracks.observed if views is None else tracks.observed & views[None]
    X, ok = triangulate(R, t, f, centre, tracks.uv, observed, max_error=np.inf, min_angle=0.0)
    return _Adjustment(R, t, f, X, observed & ok[:, None])


def _round(a: _Adjustment, iterations: int, refine_focal: bool, last: bool, centre, tracks,
           scale_view: int, max_error: float, loss_scale: float) -> _Adjustment | None:
    """One round of the adjustment: bundle-adjust the points seen twice, drop observations
    beyond ``max_error`` or behind a camera, and (unless ``last``) triangulate the points left
    with fewer than two again; None when the focal left the positive numbers."""
    keep = a.active.sum(1) >= 2
    res = fast_bundle_adjust(a.R, a.t, a.focal, centre, a.X[keep], tracks.uv[keep],
                             a.active[keep], fixed_view=0, scale_view=scale_view,
                             refine_focal=refine_focal, loss_scale=loss_scale,
                             max_iterations=iterations, tolerance=REFINE_TOLERANCE)
    if not (np.isfinite(res.focal) and res.focal > 0):
        return None
    X = a.X.copy()
    X[keep] = res.points
    err, z = reprojection_errors(res.R, res.t, res.focal, centre, X, tracks.uv)
    active = a.active & (err <= max_error) & (z > 0)
    if not last:
        # Only the points left with fewer than two observations are replaced (each track is
        # triangulated on its own, so the others' need not be computed).
        todo = np.flatnonzero((active.sum(1) < 2) & (tracks.observed.sum(1) >= 2))
        X2, ok2 = triangulate(res.R, res.t, res.focal, centre, tracks.uv[todo],
                              tracks.observed[todo], max_error=max_error,
                              min_angle=RETRIANGULATION_ANGLE)
        again = todo[ok2]
        X[again], active[again] = X2[ok2], tracks.observed[again]
    else:
        active &= (active.sum(1) >= 2)[:, None]
    return _Adjustment(res.R, res.t, res.focal, X, active)


def _reconstruction(a: _Adjustment, tracks, scale_view: int) -> Reconstruction:
    """The adjustment as the mapper's ``Reconstruction`` (a view counts as registered with
    ``REFINED_MIN_OBSERVATIONS`` observations)."""
    return Reconstruction(a.R, a.t, a.focal, a.active.sum(0) >= REFINED_MIN_OBSERVATIONS, a.X,
                          a.active.sum(1) >= 2, tracks.observed & ~a.active, (0, scale_view))


def salvage_core(best: Reconstruction, witnesses: list[Reconstruction]) -> np.ndarray | None:
    """bool [V]: the largest set of views on which a witness (another start's end) agrees with
    ``best`` pair by pair (``agreeing_views``), or None when it holds fewer than
    ``MIN_CORE_SHARE`` of the views or ``MIN_CORE_VIEWS``."""
    V = len(best.registered)
    core = np.zeros(V, bool)
    for w in witnesses:
        views = agreeing_views(agreeing_pairs(best.R, best.t, best.registered, w.R, w.t,
                                              w.registered))
        if views.sum() > core.sum():
            core = views
    return core if core.sum() >= max(MIN_CORE_VIEWS, MIN_CORE_SHARE * V) else None


def _salvaged(best: Reconstruction, witnesses: list[Reconstruction], tracks, image_size, centre,
              max_error, loss_scale, pnp_error) -> Reconstruction | None:
    """Where no start confirms the ``best`` one: its views in ``salvage_core`` are kept, their
    points triangulated again from those views alone, the other views posed against them by PnP
    RANSAC as the mapper registers a view (their poses in ``best`` are what no witness
    confirmed), and the refinement's rounds run again. None when there is no such set, or view
    0 (the gauge) is not posed."""
    core = salvage_core(best, witnesses)
    if core is None:
        return None
    R, t, f = best.R.copy(), best.t.copy(), best.focal
    X, ok = triangulate(R, t, f, centre, tracks.uv, tracks.observed & core[None],
                        max_error=max_error, min_angle=RETRIANGULATION_ANGLE)
    posed = core.copy()
    for v in np.flatnonzero(~core):
        sees = ok & tracks.observed[:, v]
        pose = pose_from_points(X[sees], tracks.uv[sees, v], f, image_size,
                                max_error=pnp_error, min_inliers=PNP_MIN_INLIERS,
                                method=SALVAGE_PNP, confident_stop=True,
                                max_iterations=SALVAGE_PNP_ITERATIONS)
        if pose is not None:
            R[v], t[v] = pose[0], pose[1]
            posed[v] = True
    if not posed[0]:
        return None
    # The scale gauge on a posed view (the one farthest from view 0).
    C = -np.einsum("vji,vj->vi", R, t)
    scale_view = int(np.argmax(np.where(posed, np.linalg.norm(C - C[0], axis=1), -1.0)))
    a = _start(R, t, f, centre, tracks, posed)
    last = len(REFINE_ROUNDS) - 1
    for n, (iterations, refine_focal) in enumerate(REFINE_ROUNDS):
        a = _round(a, iterations, refine_focal, n == last, centre, tracks, scale_view,
                   max_error, loss_scale) if a else None
    return _reconstruction(a, tracks, scale_view) if a is not None else None


def _witness(features, tracks, inliers: dict, relative: dict, focal: float, image_size,
             opts: MapperOptions, useful_views: int) -> Reconstruction | None:
    """The incremental mapper's reconstruction of the refinement's tracks (``incremental_mapping``
    at ``focal``, ``WITNESS_TRIALS`` starting pairs, PnP by ``SALVAGE_PNP``, the refinement's
    ``fast_bundle_adjust``), started from its pairs' essential matrices (``inliers {(a, b):
    int64 [M, 2]}``, ``relative {(a, b): (cam_b_from_cam_a [4, 4], weight)}``): the solve's
    method on data already at hand, without its focal priors, homographies and second pass.
    A starting pair's mapping that registers fewer than ``useful_views`` views is not finished
    (``MapperOptions.finish_min_views``): the caller can use none such. None when no pair
    starts one. ``opts`` in pixels of ``image_size``."""
    K = intrinsics(focal, image_size)
    geometries = {}
    for (a, b), m in inliers.items():
        T = relative[a, b][0]
        angle = median_triangulation_angle(features[a].uv[m[:, 0]], features[b].uv[m[:, 1]], T,
                                           K)
        # No homography: every pair counts as "general", scored by its inliers and angle.
        geometries[a, b] = TwoViewGeometry("general", m, 0, T, angle)
    opts = dataclasses.replace(opts, init_trials=WITNESS_TRIALS, min_trials=1,
                               ba_iterations=WITNESS_ITERATIONS[0],
                               final_ba_iterations=WITNESS_ITERATIONS[1],
                               pnp_method=SALVAGE_PNP, pnp_confident_stop=True,
                               pnp_iterations=SALVAGE_PNP_ITERATIONS,
                               fast_adjustment=True, finish_min_views=useful_views)
    return incremental_mapping(features, tracks, geometries, (focal,), image_size, opts)


def _witnessed(best: Reconstruction, ends: list[Reconstruction], mapped: Reconstruction | None,
               salvage: tuple) -> Reconstruction | None:
    """The first of ``best`` and the other starts' ``ends`` that the witness mapping ``mapped``
    confirms (``agreement`` on ``MIN_AGREEMENT`` of the pairs either of them poses); else
    ``best`` salvaged on the views ``mapped`` agrees with it on (``_salvaged``, ``salvage`` its
    remaining arguments); None when there is no witness or neither holds."""
    if mapped is None:
        return None
    for rec in (best, *ends):
        # Both ways: a start that leaves a view unposed is not confirmed by a witness that
        # poses it, nor a start by a witness that poses fewer of its views.
        if min(agreement(rec.R, rec.t, rec.registered, mapped.R, mapped.t, mapped.registered),
               agreement(mapped.R, mapped.t, mapped.registered, rec.R, rec.t,
                         rec.registered)) >= MIN_AGREEMENT:
            return rec
    return _salvaged(best, [mapped], *salvage)


def refine_cameras(photos, world_from_cam, focal: float, depth_range: tuple[float, float], *,
                   options: MapperOptions | None = None) -> CameraSolve | None:
    """The cameras of ``photos`` (V uint8 photos of one size, RGB [H, W, 3] or grey [H, W]),
    refined from a model's: ``world_from_cam [V, 4, 4]`` (rigid, any frame and unit) and
    ``focal`` (pixels of the photos). Returns a ``CameraSolve`` in the renderer's
    ``depth_range`` as ``solve_cameras`` does (views left with fewer than
    ``REFINED_MIN_OBSERVATIONS`` observations "unposed"), or None when the photos do not
    constrain the cameras (fewer than two views refined, a start without a baseline, an
    adjustment that left the focal non-positive) or where no other start's cameras agree with
    the chosen ones on ``MIN_AGREEMENT`` of the pairs (a wrong minimum, or a scene the photos
    leave ambiguous) and neither another start nor the witness mapping (``_witness``) agrees with
    it on ``MIN_CORE_VIEWS`` views or more.
    ``options``: the mapper's thresholds (pixels at ``two_view.REFERENCE_SIZE``): the
    adjustment uses ``max_error`` and ``loss_scale``, the ranking of the starts ``max_error``,
    the salvage ``pnp_error``, the witness mapping all of them."""
    photos = check_photos(photos)
    near, far = check_depth_range(depth_range)
    V = len(photos)
    start, focal = _check_start(world_from_cam, focal, V)
    options = options or MapperOptions()
    # As the solve: the photos in canonical_order, so that their order only decides the root.
    perm = canonical_order(photos)
    # ... and the start in the frame of canonical view 0 (the adjustment's gauge), so that the
    # same cameras given in another frame start the same adjustment: a round that ends at its
    # tolerance ends where it would have in any frame.
    start = np.linalg.inv(start[perm[0]]) @ start[perm]
    # The scale gauge: one coordinate of the view farthest from view 0 stays where it starts.
    baseline = np.linalg.norm(start[:, :3, 3] - start[0, :3, 3], axis=1)
    scale_view = int(np.argmax(baseline))
    if V < 2 or not baseline[scale_view] > 1e-9 * max(1.0, np.abs(start[:, :3, 3]).max()):
        return None
    features, k = scene_features([photos[v] for v in perm], small_size=SMALL_SIZE,
                                 max_features=MAX_KEYPOINTS or None)
    H, W = features[0].image_size
    px = pixel_scale((H, W))
    opts = options.in_pixels(px)        # the thresholds in these photos' pixels, as the solve's
    f = focal * k
    centre = np.array([W / 2.0, H / 2.0])

    inliers, relative = {}, {}            # relative: {(a, b): (cam_b_from_cam_a, inliers)}
    for a in range(V):
        for b in range(a + 1, V):
            m = match_features(features[a], features[b])
            pair = essential_pose(features[a].uv[m[:, 0]], features[b].uv[m[:, 1]], f, (H, W),
                                  MAX_ERROR * px)
            if pair is not None:
                inliers[a, b] = m[pair[0]]
                relative[a, b] = (pair[1], float(pair[0].sum()))
    tracks = build_tracks(features, inliers)
    cam_from_world = np.linalg.inv(start)
    R0, centres = cam_from_world[:, :3, :3], start[:, :3, 3]
    rotations = {ab: (T[:3, :3], w) for ab, (T, w) in relative.items()}
    args = (centre, tracks, scale_view, opts.max_error, opts.loss_scale)
    last = len(REFINE_ROUNDS) - 1
    started = []            # per start: (its key after CHOOSE_AFTER rounds, its adjustment then)
    for kind in STARTS:
        R = R0 if kind == "model" else average_rotations(rotations, R0)
        c = average_centres(relative, R, centres) if kind == "pairs" else centres
        a = _start(R.copy(), -np.einsum("vij,vj->vi", R, c), f, centre, tracks)
        for n, (iterations, refine_focal) in enumerate(REFINE_ROUNDS[:CHOOSE_AFTER]):
            a = _round(a, iterations, refine_focal, n == last, *args) if a else None
        if a is not None:
            rec = _reconstruction(a, tracks, scale_view)
            started.append(((int(rec.registered.sum()),
                             -reprojection_score(rec, tracks, centre, opts)), a))
    ends: dict[int, Reconstruction | None] = {}

    def end(i: int) -> Reconstruction | None:
        """Start i adjusted to the end, its remaining rounds run when first asked for: where the
        second-ranked start confirms the best, the third's are never run."""
        if i not in ends:
            a = started[i][1]
            for n, (iterations, refine_focal) in enumerate(REFINE_ROUNDS):
                if n >= CHOOSE_AFTER:
                    a = _round(a, iterations, refine_focal, n == last, *args) if a else None
            ends[i] = _reconstruction(a, tracks, scale_view) if a is not None else None
        return ends[i]

    # The best-ranked start (as the mapper ranks reconstructions) is kept where another start
    # confirms it, agreeing on MIN_AGREEMENT of its pairs: a wrong minimum is rarely reached
    # twice. Where none does, the views one confirms are salvaged; where none confirms enough,
    # the witness mapping is asked; else the caller runs the solve.
    ranked = sorted(range(len(started)), key=lambda i: started[i][0], reverse=True)
    finished = (rec for rec in map(end, ranked) if rec is not None)       # lazily, best first
    best = next(finished, None)
    if best is None or best.registered.sum() < 2:
        return None
    if len(STARTS) > 1:
        witnesses = []
        for rec in finished:
            witnesses.append(rec)
            if agreement(best.R, best.t, best.registered, rec.R, rec.t,
                         rec.registered) >= MIN_AGREEMENT:
                break
        else:
            salvage = (tracks, (H, W), centre, opts.max_error, opts.loss_scale, opts.pnp_error)
            kept = _salvaged(best, witnesses, *salvage)
            if kept is None and WITNESS_TRIALS:
                # A mapping of fewer views than MIN_CORE_VIEWS salvages nothing, and confirms
                # (on MIN_AGREEMENT of the pairs) no start that poses more views than it does.
                useful = min(MIN_CORE_VIEWS, *(int(r.registered.sum()) for r in [best, *witnesses]))
                mapped = _witness(features, tracks, inliers, relative, best.focal, (H, W), opts,
                                  useful)
                kept = _witnessed(best, witnesses, mapped, salvage)
            if kept is None:
                return None
            best = kept
    refined = best.registered                                      # canonical numbering
    cams = np.full((V, 4, 4), np.nan)
    cams[refined] = np.eye(4)
    cams[refined, :3, :3], cams[refined, :3, 3] = best.R[refined], best.t[refined]
    status = np.array(["unposed"] * V, dtype=object)
    status[perm[refined]] = "solved"
    return finish_solve(best, tracks, features, cams, status, perm, k, photos[0].shape[:2],
                        (near, far))
