"""Two-view and global epipolar geometry of one scene's photos (numpy + OpenCV, no torch, no labels).

The cameras a scene's photos were taken from, from the photos alone:

1. ``flow_matches``: dense correspondences between two photos (OpenCV DIS optical flow on 4x
   upsampled grey images), kept where the forward and backward flows agree and both photos have
   texture;
2. ``search_focal``: one shared focal by a grid search (the focal whose essential matrices explain
   the most flow vectors, over every pair);
3. ``pairwise_poses``: per pair the essential matrix (OpenCV ``USAC_ACCURATE``, 5-point, 0.25 px)
   and the relative pose it implies (``cv2.recoverPose``: a rotation and a unit translation, sign
   fixed by cheirality) -> ``PairwisePoses``;
4. ``solve_cameras``: one camera per view from the trusted pairs (chordal rotation averaging, then
   linear translation averaging; see ``solve_global``) -> ``world_from_cam [V, 4, 4]``, view 0 = I,
   centres without a unit (|c| = 1 over the views);
5. ``refine_cameras``: a model's predicted cameras replaced by that solve, in the model's units
   (the scale of the centres fitted to the model's centres), what ``IrisRuntime.encode(images,
   cameras="epipolar")`` and ``iris-eval --cameras epipolar`` use;
6. ``locate_views``: the poses of query photos with the references' cameras held fixed.

This is the training teacher of ``iris_train.pseudo_poses`` (which imports it from here and caches
it), moved here so that a server without torch gets the same cameras. Conventions: DESIGN.md
(OpenCV axes, ``world_from_cam`` camera-to-world, view 0 = I, pixel centres at +0.5);
``cam_from_cam[i, j]`` maps camera i's coordinates to camera j's (x_j = R x_i + t, |t| = 1), so
with world_from_cam poses (R_k, c_k): R_ij = R_j^T R_i and t_ij ∝ R_j^T (c_i - c_j).

Cost: V (V - 1) / 2 pairs of DIS flow plus one essential matrix each, and the focal search (11
focals x every pair): ``IrisRuntime.encode(cameras="epipolar")`` of the 8-view sample scene at
64x64 takes 8.5 s on one core against 0.03 s with the encoder's cameras, 4.9 s with the focal
searched over pairs 2-3 apart, 10.0 s with the texture test of ``flow_matches`` off (fewer
vectors to score with it; ``benchmarks/epipolar_cost.py``, benchmarks/results/epipolar_cost.json,
medians of 3 in one process).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["PairwisePoses", "GlobalSolve", "CameraRefinement", "dis_flow", "flow_matches", "all_flow_matches",
           "canonical_order", "intrinsics", "search_focal", "relative_poses", "pairwise_poses", "reachable_views",
           "solve_global", "solve_cameras", "TRANSLATION_SOLVERS", "fit_scale", "refine_cameras", "locate_views",
           "FLOW_UPSAMPLE", "FB_TOLERANCE", "TEXTURE_MIN", "FOCAL_GRID", "MIN_INLIERS", "MIN_INLIER_RATIO",
           "ESTIMATOR", "RANSAC_THRESHOLD", "FOCAL_SEARCH_POINTS", "FOCAL_PAIRS", "DEFAULT_BASELINE",
           "COLLAPSED_SPREAD", "CAMERA_SOURCES", "DEPTH_TARGET", "MIN_PARALLAX", "SCALE_MODES",
           "match_depths",
           "solve_views", "reference_depths", "LOCATE_METHODS", "PNP_THRESHOLD", "PNP_MIN_INLIERS"]

#: Upsampling before flow (DIS works on 4x4+ patches; at 64x64 the flow is too coarse without it).
FLOW_UPSAMPLE = 4
#: Forward-backward disagreement (pixels of the model image) above which a flow vector is dropped.
FB_TOLERANCE = 0.5
#: Flow vectors are kept only where both photos have texture: the smallest eigenvalue of the
#: structure tensor (``cv2.cornerMinEigenVal`` of the grey photo at model resolution, 3x3 window,
#: 3x3 Sobel; OpenCV scales it to [0, 1] for uint8) above this at both ends. 0 keeps every vector.
TEXTURE_MIN = 3e-6
#: Focal candidates fx/W (vertical fields of view from about 35 to 80 degrees).
FOCAL_GRID = tuple(float(f) for f in np.geomspace(0.6, 1.6, 11))
#: A pair is trusted when the estimator keeps at least this many flow vectors and this fraction.
MIN_INLIERS = 100
MIN_INLIER_RATIO = 0.5
#: Robust estimator of the essential matrix and its inlier threshold (pixels of the model image).
#: USAC_ACCURATE (local optimisation + final polishing on all inliers) at 0.25 px against RANSAC at
#: 0.5 px, 16 held-out scenes with the true focal: teacher RPA@15 0.641 vs 0.480, median rotation
#: error 2.1 vs 3.9 degrees, translation direction 8.3 vs 15.0 (docs/TRAINING.md, "teacher").
ESTIMATOR = cv2.USAC_ACCURATE
RANSAC_THRESHOLD = 0.25
#: Flow vectors per pair scored by the focal search (a fixed random subset; a third of the time).
FOCAL_SEARCH_POINTS = 1500
#: Model centres whose RMS distance from view 0 is below this are "collapsed" (no scale to fit).
COLLAPSED_SPREAD = 1e-6
#: Mean distance between camera centres (model units) given to an epipolar solve when the model's
#: own centres carry no scale (collapsed): the mean pairwise baseline of the true cameras of the
#: 16 held-out synthetic scenes of 8 views, whose unit is the renderer's (depths in [0.1, 1.0]):
#: 0.143 (per scene 0.04-0.25).
DEFAULT_BASELINE = 0.14
#: ``refine_cameras(scale="depth")`` (the default): the unit-free centres are scaled so that the median depth of
#: the scene's triangulated flow matches lies this far into the renderer's depth range [near, far]
#: (0: at near, 1: at far). The synthetic data was built for the range [0.1, 1.0] with median
#: depths 0.51 (turntables) and 0.67 (rooms) (docs/DATA.md); the value is chosen on validation
#: scenes, not the held-out ones (docs/TRAINING.md, "Epipolar cameras at inference").
DEPTH_TARGET = 0.5
#: Matches whose two rays meet at less than this angle (radians, ~1 degree) carry no depth.
MIN_PARALLAX = 0.0175
#: How ``refine_cameras`` gives the unit-free centres a scale.
SCALE_MODES = ("depth", "model")
#: Values of ``CameraRefinement.source`` / ``Scene.camera_source``.
CAMERA_SOURCES = ("model", "epipolar", "mixed")


# -- two-view geometry ------------------------------------------------------------------------
@dataclass(frozen=True)
class PairwisePoses:
    """``cam_from_cam [V, V, 4, 4]``: entry [i, j] maps camera i's coordinates to camera j's
    (x_j = R x_i + t, |t| = 1; identity where no pose was found); ``trusted [V, V]`` bool
    (symmetric, False on the diagonal); ``inliers [V, V]`` int32; ``focal`` fx/W the relative poses
    were computed at (shared, square pixels)."""
    cam_from_cam: np.ndarray
    trusted: np.ndarray
    inliers: np.ndarray
    focal: float


def dis_flow(g0: np.ndarray, g1: np.ndarray) -> np.ndarray:
    """Dense flow [h, w, 2] float32 from grey uint8 image g0 to g1 (OpenCV DIS, medium preset):
    the flow of ``flow_matches``."""
    return cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(g0, g1, None)


def flow_matches(a: np.ndarray, b: np.ndarray, flow=dis_flow) -> tuple[np.ndarray, np.ndarray]:
    """Pixel correspondences ``p -> q`` ``[N, 2]`` float32 (pixels of the given images, centres at
    +0.5) from forward-backward-consistent DIS flow between uint8 RGB images a and b [H, W, 3],
    where both a at p and b at q have texture (``TEXTURE_MIN``).

    Why the texture test: DIS fills a flat region (a sky, a plain backdrop) with the flow of its
    surroundings or with zero, and forward and backward agree there, so those vectors pass the
    consistency check; zero flow over half the image fits R = I with any translation, and the
    essential matrix of a turntable scene came out as the identity rotation (errors equal to the
    true rotation, 10-67 degrees). ``scripts/epipolar_study.py rpa synthetic:validation --scenes
    24 --texture-min T``: RPA@15 / @30 0.385 / 0.607 without the test (T = 0), 0.512 / 0.685 at
    1e-6, 0.515 / 0.689 at 3e-6 (the default), 0.506 / 0.685 at 1e-5, 0.482 / 0.650 at 1e-4
    (docs/TRAINING.md, "Texture").

    ``flow``: the dense flow, ``(g0, g1) -> [h, w, 2]`` on the upsampled grey images
    (default ``dis_flow``; ``scripts/epipolar_study.py flow`` compares OpenCV's others)."""
    up = FLOW_UPSAMPLE
    H, W = a.shape[:2]
    grey = [cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) for x in (a, b)]
    big = [cv2.resize(g, (W * up, H * up), interpolation=cv2.INTER_CUBIC) for g in grey]
    fwd = flow(big[0], big[1])
    bwd = flow(big[1], big[0])
    step = up // 2
    ys, xs = np.mgrid[0:H * up:step, 0:W * up:step]
    p = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float32) + 0.5
    f = fwd[ys.ravel(), xs.ravel()]
    q = p + f
    back = cv2.remap(bwd, q[:, :1] - 0.5, q[:, 1:] - 0.5, cv2.INTER_LINEAR).reshape(-1, 2)
    ok = ((np.linalg.norm(f + back, axis=1) < FB_TOLERANCE * up)
          & (q[:, 0] > 0) & (q[:, 1] > 0) & (q[:, 0] < W * up) & (q[:, 1] < H * up))
    p, q = p[ok] / up, q[ok] / up
    if TEXTURE_MIN > 0:
        textured = [cv2.cornerMinEigenVal(g, 3, ksize=3).ravel() > TEXTURE_MIN for g in grey]
        keep = textured[0][_cells(p, H, W)] & textured[1][_cells(q, H, W)]
        p, q = p[keep], q[keep]
    return p, q


def all_flow_matches(images: np.ndarray) -> dict:
    """``{(i, j): (p, q)}`` for every pair i < j of uint8 ``images [V, H, W, 3]``."""
    V = images.shape[0]
    return {(i, j): flow_matches(images[i], images[j]) for i in range(V) for j in range(i + 1, V)}


def canonical_order(images: np.ndarray) -> np.ndarray:
    """``perm`` int64 [V]: the order the solve looks at uint8 ``images [V, H, W, 3]`` in, fixed by
    their content (ascending SHA-256 of each image's bytes; identical images keep their given
    order). Flow is computed i -> j for i < j, OpenCV's robust estimators draw in call order and
    the global solve roots its gauge at the first view, so a solve in the given order depends on
    the order of the photos: on 16 validation scenes the same photos in iris-eval's Seq and Rand
    orders gave renders up to 3.3 dB apart (mean 0.72 dB), and with the cameras swapped between
    the orders the renders followed the cameras (``scripts/epipolar_study.py order``,
    docs/logs/order_study_f1_before.log). Solved in this order, the cameras are a function of the set of photos."""
    import hashlib
    keys = [hashlib.sha256(np.ascontiguousarray(x).tobytes()).hexdigest() for x in images]
    return np.array(sorted(range(len(keys)), key=lambda k: (keys[k], k)), dtype=np.int64)


def intrinsics(focal: float, H: int, W: int) -> np.ndarray:
    """``K [3, 3]`` of a normalised focal fx/W with square pixels, principal point at the centre."""
    return np.array([[focal * W, 0.0, W / 2], [0.0, focal * W, H / 2], [0.0, 0.0, 1.0]])


def _check_images(images) -> np.ndarray:
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8 or images.shape[0] < 1:
        raise ValueError(f"images: expected uint8 [V, H, W, 3] with V >= 1, got {images.dtype} "
                         f"{images.shape}")
    return np.ascontiguousarray(images)


FOCAL_PAIRS = ("gap", "all")


def search_focal(matches: dict, H: int, W: int, pairs: str = "all") -> float:
    """The focal of ``FOCAL_GRID`` (fx/W) whose essential matrices keep the largest mean fraction
    of flow vectors as inliers (``matches`` from ``all_flow_matches``; on a fixed random subset of
    ``FOCAL_SEARCH_POINTS`` vectors per pair), over the pairs ``pairs`` says: "all" (default),
    every pair with enough matches, so that which pairs count does not depend on the order of the
    photos; "gap", the pairs two or three positions apart in the given order (the first rule).
    48 validation scenes, iris-eval's protocol (``scripts/epipolar_study.py rpa``), RPA@15 / @30
    Rand and Seq: "all" 0.507 / 0.705 and 0.510 / 0.702, "gap" 0.508 / 0.702 and 0.481 / 0.688.
    The score is flat near its top, so flow and RANSAC noise still move the pick by a grid step
    between orders (30 of 48 scenes, "gap" 39).
    Draws from OpenCV's RNG: seed it (``cv2.setRNGSeed``) for a reproducible result."""
    if pairs not in FOCAL_PAIRS:
        raise ValueError(f"pairs: expected one of {FOCAL_PAIRS}, got {pairs!r}")
    rng = np.random.default_rng(0)
    subsets = {k: rng.permutation(len(p))[:FOCAL_SEARCH_POINTS] for k, (p, _) in matches.items()}
    scores = []
    for f in FOCAL_GRID:
        K = intrinsics(f, H, W)
        ratios = []
        for (i, j), (p, q) in matches.items():
            if (pairs == "gap" and j - i not in (2, 3)) or len(p) < MIN_INLIERS:
                continue
            p, q = p[subsets[i, j]], q[subsets[i, j]]
            E, inl = cv2.findEssentialMat(p, q, K, ESTIMATOR, 0.999, RANSAC_THRESHOLD)
            if E is not None and E.shape == (3, 3):
                ratios.append(float(inl.mean()))
        scores.append(np.mean(ratios) if ratios else 0.0)
    return FOCAL_GRID[int(np.argmax(scores))]


def relative_poses(matches: dict, V: int, K: np.ndarray) -> PairwisePoses:
    """Per pair of ``matches`` (from ``all_flow_matches`` of V views) the essential matrix at
    intrinsics ``K [3, 3]`` and its relative pose -> ``PairwisePoses`` (``focal`` = K[0, 0] / W
    with W = 2 K[0, 2]). Draws from OpenCV's RNG: seed it first for a reproducible result."""
    K = np.asarray(K, dtype=np.float64)
    cam_from_cam = np.tile(np.eye(4), (V, V, 1, 1))
    trusted = np.zeros((V, V), dtype=bool)
    inliers = np.zeros((V, V), dtype=np.int32)
    for (i, j), (p, q) in matches.items():
        if len(p) < MIN_INLIERS:
            continue
        E, inl = cv2.findEssentialMat(p, q, K, ESTIMATOR, 0.999, RANSAC_THRESHOLD)
        if E is None or E.shape != (3, 3):
            continue
        n, R, t, _ = cv2.recoverPose(E, p, q, K, mask=inl.copy())
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, t.ravel() / max(np.linalg.norm(t), 1e-12)
        cam_from_cam[i, j] = T
        Ti = np.eye(4)
        Ti[:3, :3], Ti[:3, 3] = R.T, -R.T @ T[:3, 3]
        cam_from_cam[j, i] = Ti
        inliers[i, j] = inliers[j, i] = int(n)
        trusted[i, j] = trusted[j, i] = n >= MIN_INLIERS and n >= MIN_INLIER_RATIO * len(p)
    return PairwisePoses(cam_from_cam, trusted, inliers, float(K[0, 0] / (2.0 * K[0, 2])))


def pairwise_poses(images, focal: float | None = None, *, matches: dict | None = None
                   ) -> PairwisePoses:
    """``images`` uint8 ``[V, H, W, 3]`` of one static scene -> ``PairwisePoses`` of every pair.

    ``focal``: fx/W (square pixels, principal point at the centre) to compute the essential
    matrices at; None: the grid search ``search_focal``. Deterministic (OpenCV's RNG is seeded
    with 0 first). ``matches``: precomputed ``all_flow_matches(images)`` (the flow is the larger
    half of the time)."""
    images = _check_images(images)
    cv2.setRNGSeed(0)                      # robust estimator draws: same images, same poses
    V, H, W = images.shape[:3]
    if matches is None:
        matches = all_flow_matches(images)
    if focal is None:
        focal = search_focal(matches, H, W)
    elif not (np.isfinite(focal) and focal > 0):
        raise ValueError(f"focal: expected a positive fx/W, got {focal!r}")
    pp = relative_poses(matches, V, intrinsics(float(focal), H, W))
    return PairwisePoses(pp.cam_from_cam, pp.trusted, pp.inliers, float(focal))


# -- global solve ------------------------------------------------------------------------------
@dataclass(frozen=True)
class GlobalSolve:
    """``world_from_cam [V, 4, 4]`` (view 0 = I; NaN for views not ``solved``); ``solved [V]``
    bool: the views view 0 reaches through trusted pairs; ``translation_gap``: the two smallest
    singular values' ratio of the translation system (near 1: the centres are ill-posed, e.g. a
    chain of pairs whose baselines are independent; near 0: well posed; nan with < 2 views)."""
    world_from_cam: np.ndarray
    solved: np.ndarray
    translation_gap: float


def reachable_views(trusted: np.ndarray) -> np.ndarray:
    """bool [V]: the views connected to view 0 by a path of trusted pairs (view 0 included)."""
    trusted = np.asarray(trusted, dtype=bool)
    seen = np.zeros(trusted.shape[0], dtype=bool)
    seen[0] = True
    frontier = [0]
    while frontier:
        nxt = np.flatnonzero((trusted[frontier].any(axis=0)) & ~seen)
        seen[nxt] = True
        frontier = nxt.tolist()
    return seen


def _project_so3(M: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(M)
    D = np.ones(M.shape[:-2] + (3,))
    D[..., 2] = np.sign(np.linalg.det(U @ Vt))
    D[D == 0] = 1.0
    return (U * D[..., None, :]) @ Vt


def _chordal_rotations(pairs, rel, w, n) -> np.ndarray:
    """R_k (world_from_cam) of n views, R_0 = I, from R_i = R_j R_ij: weighted linear least
    squares on Y_k = R_k^T (Y_i - R_ij^T Y_j = 0, Y_0 = I moved to the right-hand side), each
    Y_k then projected on SO(3)."""
    A = np.zeros((3 * len(pairs), 3 * (n - 1)))
    b = np.zeros((3 * len(pairs), 3))
    for r, ((i, j), R, wk) in enumerate(zip(pairs, rel, w)):
        rows = slice(3 * r, 3 * r + 3)
        for k, block in ((i, np.eye(3)), (j, -R.T)):
            if k == 0:
                b[rows] -= wk * block            # block @ Y_0 = block
            else:
                A[rows, 3 * (k - 1):3 * k] += wk * block
    Y = np.linalg.lstsq(A, b, rcond=None)[0].reshape(n - 1, 3, 3)
    R = np.empty((n, 3, 3))
    R[0] = np.eye(3)
    R[1:] = np.swapaxes(_project_so3(Y), -1, -2)
    return R


#: Translation-averaging variants of ``solve_global``.
TRANSLATION_SOLVERS = ("baselines", "cross")


def solve_global(pairwise: PairwisePoses, *, robust: bool = True,
                 translation: str = "baselines", matches: dict | None = None,
                 image_size: tuple[int, int] | None = None) -> GlobalSolve:
    """One camera per view from the trusted pairs of ``pairwise``.

    Rotations: chordal averaging, min sum w_ij |R_i - R_j R_ij|_F^2 with R_0 = I, w_ij =
    sqrt(inliers_ij), solved linearly and projected on SO(3); ``robust``: then 3 reweighted
    solves with w_ij * 1 / (1 + (r_ij / 0.1)^2) (Cauchy weights on the chordal residual r_ij,
    0.1 ~ 4 degrees), so a few wrong pairs do not drag the others.

    Centres, with d_ij = R_j t_ij (the world direction of c_i - c_j, signed by cheirality) and
    c_0 = 0, both linear:

    - ``"baselines"`` (default): min sum w_ij^2 |c_i - c_j - l_ij d_ij|^2 over the centres and
      one baseline length l_ij per pair, subject to sum l_ij = number of pairs (an equality-
      constrained least squares, closed form); the signs of the d_ij enter the fit itself, so
      the solution cannot mirror. Directions alone leave the length of a pair free when one of
      its views has no other trusted pair (and nearly free on near-collinear chains): the least
      squares then puts the whole sum on that pair and collapses every other centre onto view 0.
      With ``matches`` (``all_flow_matches`` of the images, of size ``image_size`` (H, W)) the
      lengths are also tied to each other by the depths the pairs triangulate: two pairs that
      share a view see the same pixels there at depths proportional to their baselines, so
      l_e1 = rho l_e2 with rho the median ratio of their unit-baseline depths over the pixels
      both triangulate (``_baseline_ratios``), added as rows of weight
      sqrt(common pixels) to the same least squares.
    - ``"cross"``: min sum w_ij^2 |[d_ij]_x (c_i - c_j)|^2 with |c| = 1 (the smallest right
      singular vector), sign by the majority of (c_i - c_j) . d_ij > 0.

    Measured on the 16 held-out scenes (teacher pairs at the searched focal): RPA@15 / @30 of all
    8 views 0.665 / 0.850 ("baselines") vs 0.652 / 0.853 ("cross"); of iris-eval's 5 references
    0.531 / 0.662 vs 0.519 / 0.650, but the configuration of the centres came out mirrored
    (negative correlation with the true centres, which the sign-free RPA does not see and the
    renderer does) in 0 / 16 and 1 / 16 scenes vs 1 / 16 and 4 / 16. Either way |c| = 1 over
    the views. Only the views view 0 reaches through trusted pairs are solved
    (``reachable_views``); the others get NaN.
    """
    if translation not in TRANSLATION_SOLVERS:
        raise ValueError(f"translation: expected one of {TRANSLATION_SOLVERS}, got {translation!r}")
    trusted = np.asarray(pairwise.trusted, dtype=bool)
    V = trusted.shape[0]
    solved = reachable_views(trusted)
    idx = np.flatnonzero(solved)                   # idx[0] == 0
    n = len(idx)
    out = np.full((V, 4, 4), np.nan)
    out[0] = np.eye(4)
    gap = float("nan")
    if n >= 2:
        local = {g: k for k, g in enumerate(idx)}
        pairs, rel, t, w0 = [], [], [], []
        for a in range(n):
            for c in range(a + 1, n):
                i, j = int(idx[a]), int(idx[c])
                if trusted[i, j]:
                    T = np.asarray(pairwise.cam_from_cam[i, j], dtype=np.float64)
                    pairs.append((local[i], local[j]))
                    rel.append(T[:3, :3])
                    t.append(T[:3, 3])
                    w0.append(np.sqrt(max(float(pairwise.inliers[i, j]), 1.0)))
        w0 = np.asarray(w0)
        R = _chordal_rotations(pairs, rel, w0, n)
        if robust:
            for _ in range(3):
                res = np.array([np.linalg.norm(R[i] - R[j] @ Rij) for (i, j), Rij in zip(pairs, rel)])
                R = _chordal_rotations(pairs, rel, w0 / (1.0 + (res / 0.1) ** 2), n)
        dirs = [R[j] @ tij for (i, j), tij in zip(pairs, t)]
        if translation == "baselines":
            ratios = []
            if matches is not None:
                if image_size is None:
                    raise ValueError("image_size: (H, W) is needed with matches")
                glob = [(int(idx[a]), int(idx[b])) for a, b in pairs]
                ratios = _baseline_ratios(matches, pairwise, glob, *image_size)
            c, gap = _centres_baselines(pairs, dirs, w0, n, ratios)
        else:
            c, gap = _centres_cross(pairs, dirs, w0, n)
        T = np.tile(np.eye(4), (n, 1, 1))
        T[:, :3, :3], T[:, :3, 3] = R, c
        out[idx] = T
    return GlobalSolve(out, solved, gap)


def _centres_cross(pairs, dirs, w, n):
    """[d]_x (c_i - c_j) = 0, unknowns c_1 .. c_{n-1}: smallest right singular vector + sign vote."""
    A = np.zeros((3 * len(pairs), 3 * (n - 1)))
    for r, ((i, j), d, wk) in enumerate(zip(pairs, dirs, w)):
        X = wk * np.array([[0.0, -d[2], d[1]], [d[2], 0.0, -d[0]], [-d[1], d[0], 0.0]])
        for k, s in ((i, 1.0), (j, -1.0)):
            if k > 0:
                A[3 * r:3 * r + 3, 3 * (k - 1):3 * k] += s * X
    _, sv, Vt = np.linalg.svd(A)
    c = np.zeros((n, 3))
    c[1:] = Vt[-1].reshape(n - 1, 3)
    gap = float(sv[-1] / sv[-2]) if sv[-2] > 1e-8 * sv[0] else 1.0   # 3 (n - 1) >= 3 values
    votes = sum(np.sign((c[i] - c[j]) @ d) for (i, j), d in zip(pairs, dirs))
    return (-c if votes < 0 else c), gap


#: Pixels two pairs must both triangulate in their shared view to tie their baselines.
MIN_SHARED_DEPTHS = 20


def _unit_depths(p, q, T_ij, H, W, focal):
    """Depth maps (flat [H * W], NaN where nothing lands) in view i and view j of the matches
    p (view i) -> q (view j), triangulated with the relative pose ``T_ij`` (cam_from_cam[i, j],
    |t| = 1): the depths of a unit baseline."""
    T_i, T_j = np.eye(4), np.linalg.inv(T_ij)
    X, keep = _triangulate_pair(p, q, T_i, T_j, float(focal) * W, H, W)
    out = []
    for T, pix in ((T_i, p), (T_j, q)):
        z = (X[keep] - T[:3, 3]) @ T[:3, :3][:, 2]
        front = z > 0                                 # the midpoint, not only the ray, in front
        z, cell = z[front], _cells(pix[keep][front], H, W)
        sums = np.bincount(cell, np.log(z), minlength=H * W)
        counts = np.bincount(cell, minlength=H * W)
        out.append(np.where(counts > 0, sums / np.maximum(counts, 1), np.nan))   # mean log z
    return out


def _baseline_ratios(matches, pairwise, pairs, H, W):
    """[(e1, e2, rho, weight)]: for pairs e1, e2 (indices into ``pairs``, global view indices)
    that share a view, l_e1 / l_e2 = rho, the median over the pixels of the shared view that
    both triangulate of exp(log z_e2 - log z_e1) (unit-baseline depths, ``_unit_depths``)."""
    logz = {}
    for e, (i, j) in enumerate(pairs):
        key = (min(i, j), max(i, j))
        if key not in matches or len(matches[key][0]) == 0:
            continue
        p, q = (np.asarray(x, dtype=np.float64) for x in matches[key])
        a, b = key
        za, zb = _unit_depths(p, q, np.asarray(pairwise.cam_from_cam[a, b], np.float64), H, W,
                              pairwise.focal)
        logz[e, a], logz[e, b] = za, zb
    out = []
    for e1 in range(len(pairs)):
        for e2 in range(e1 + 1, len(pairs)):
            for v in set(pairs[e1]) & set(pairs[e2]):
                if (e1, v) not in logz or (e2, v) not in logz:
                    continue
                both = np.isfinite(logz[e1, v]) & np.isfinite(logz[e2, v])
                if both.sum() >= MIN_SHARED_DEPTHS:
                    rho = float(np.exp(np.median(logz[e2, v][both] - logz[e1, v][both])))
                    out.append((e1, e2, rho, float(np.sqrt(both.sum()))))
    return out


def _centres_baselines(pairs, dirs, w, n, ratios=()):
    """c_i - c_j = l_ij d_ij, unknowns c_1 .. c_{n-1} and l, with sum l = P, plus the rows
    l_e1 / sqrt(rho) - sqrt(rho) l_e2 = 0 of ``ratios``: the KKT system of the equality-
    constrained least squares; then |c| = 1."""
    P, m = len(pairs), 3 * (n - 1)
    A = np.zeros((3 * P + len(ratios), m + P))
    for r, ((i, j), d, wk) in enumerate(zip(pairs, dirs, w)):
        rows = slice(3 * r, 3 * r + 3)
        for k, s in ((i, 1.0), (j, -1.0)):
            if k > 0:
                A[rows, 3 * (k - 1):3 * k] += s * wk * np.eye(3)
        A[rows, m + r] = -wk * d
    for r, (e1, e2, rho, wk) in enumerate(ratios):
        A[3 * P + r, m + e1] = wk / np.sqrt(rho)
        A[3 * P + r, m + e2] = -wk * np.sqrt(rho)
    N = A.T @ A
    ev = np.linalg.eigvalsh(N)                        # >= 2 values: m >= 3 and P >= 1
    gap = float(np.sqrt(max(ev[0], 0.0) / ev[1])) if ev[1] > 1e-12 * ev[-1] else 1.0
    C = np.zeros(m + P)
    C[m:] = 1.0
    KKT = np.block([[N, C[:, None]], [C[None], np.zeros((1, 1))]])
    rhs = np.zeros(m + P + 1)
    rhs[-1] = P
    x = np.linalg.lstsq(KKT, rhs, rcond=None)[0]
    c = np.zeros((n, 3))
    c[1:] = x[:m].reshape(n - 1, 3)
    norm = np.linalg.norm(c)
    return (c / norm if norm > 0 else c), gap


def solve_cameras(pairwise: PairwisePoses, *, robust: bool = True,
                  translation: str = "baselines", matches: dict | None = None,
                  image_size: tuple[int, int] | None = None) -> np.ndarray:
    """``world_from_cam [V, 4, 4]`` of the global solve (``solve_global``, with the depth ties of
    ``matches`` when given): view 0 = I, unit-free centres (|c| = 1 over the views), NaN rows for
    the views view 0 does not reach through trusted pairs (``reachable_views``)."""
    return solve_global(pairwise, robust=robust, translation=translation, matches=matches,
                        image_size=image_size).world_from_cam


# -- refinement of a model's cameras ----------------------------------------------------------
def fit_scale(model_centres: np.ndarray, epipolar_centres: np.ndarray,
              all_model_centres: np.ndarray | None = None) -> tuple[float, str]:
    """Scale s putting unit-free epipolar centres [n, 3] into the model's units -> (s, how).

    "fit": s = <c_model, c_epi> / <c_epi, c_epi> summed over the n views (least squares), when
    that is > 0 and the model's centres are not collapsed (RMS distance from view 0 >=
    ``COLLAPSED_SPREAD``). Otherwise "baseline": the model's mean pairwise baseline (over
    ``all_model_centres``, default ``model_centres``) over the epipolar one, when the former is
    >= ``COLLAPSED_SPREAD``; else "constant": the epipolar mean baseline becomes
    ``DEFAULT_BASELINE``."""
    cm = np.asarray(model_centres, dtype=np.float64).reshape(-1, 3)
    ce = np.asarray(epipolar_centres, dtype=np.float64).reshape(-1, 3)
    allm = cm if all_model_centres is None else np.asarray(all_model_centres, np.float64).reshape(-1, 3)

    def mean_baseline(c):
        if len(c) < 2:
            return 0.0
        i, j = np.triu_indices(len(c), 1)
        return float(np.linalg.norm(c[i] - c[j], axis=1).mean())

    ee = float(np.sum(ce * ce))
    spread = float(np.sqrt(np.mean(np.sum(cm * cm, axis=1)))) if len(cm) else 0.0
    if ee > 0 and spread >= COLLAPSED_SPREAD:
        s = float(np.sum(cm * ce)) / ee
        if s > 0 and np.isfinite(s):
            return s, "fit"
    be = mean_baseline(ce)
    if be <= 0:
        return 1.0, "constant"                     # nothing to scale: all centres coincide
    bm = mean_baseline(allm)
    if bm >= COLLAPSED_SPREAD:
        return bm / be, "baseline"
    return DEFAULT_BASELINE / be, "constant"


def match_depths(matches: dict, world_from_cam: np.ndarray, focal: float, H: int, W: int,
                 pairs=None) -> np.ndarray:
    """Depths [N] (z in the first camera of each pair) of the flow matches of ``pairs`` (default:
    every key of ``matches`` whose two views are solved, i.e. have finite ``world_from_cam
    [V, 4, 4]``), triangulated at focal fx/W by the closed-form midpoint of the two rays. Matches
    whose rays meet at under ``MIN_PARALLAX``, or whose midpoint lies behind either camera, are
    left out. The unit is the cameras' (unit-free for a ``solve_global`` result)."""
    T = np.asarray(world_from_cam, dtype=np.float64)
    ok_view = np.isfinite(T).all(axis=(1, 2))
    F = float(focal) * W
    out = []
    for (i, j) in (matches if pairs is None else pairs):
        if not (ok_view[i] and ok_view[j]) or len(matches[i, j][0]) == 0:
            continue
        p, q = (np.asarray(x, dtype=np.float64) for x in matches[i, j])
        X, keep = _triangulate_pair(p, q, T[i], T[j], F, H, W)
        z = (X[keep] - T[i, :3, 3]) @ T[i, :3, :3][:, 2]
        out.append(z[z > 0])
    return np.concatenate(out) if out else np.zeros(0)


def solve_views(images: np.ndarray, pairwise: PairwisePoses, matches: dict, *,
                robust: bool = True, root: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One camera per view of ``images`` uint8 [V, H, W, 3], in view ``root``'s frame, unit-free.

    The largest set of views connected by trusted pairs (``pairwise.trusted``; ties: the one
    with ``root``, else the lowest view) is solved by ``solve_global`` (with the depth ties of
    ``matches``), rooted at its lowest view; every other view, ``root`` included when it is not
    in that set, is then located against it (``locate_views``, PnP on the set's triangulated
    pixels), and all poses are re-based so that view ``root`` = I. Without that, a root with no
    trusted pair left the whole scene to the model's cameras, and views outside the root's set
    kept cameras from another frame. (``refine_cameras`` solves in ``canonical_order`` and roots
    the result at the caller's view 0.)

    Returns ``(world_from_cam [V, 4, 4]`` (NaN rows: not solved), ``solved`` bool [V], ``core``
    bool [V]: the views of the trusted set); nothing is solved when the root can be neither
    solved nor located, or when no pair is trusted.
    """
    V, H, W = images.shape[:3]
    trusted = np.asarray(pairwise.trusted, dtype=bool)
    out = np.full((V, 4, 4), np.nan)
    none = (out, np.zeros(V, dtype=bool), np.zeros(V, dtype=bool))
    comps, seen = [], np.zeros(V, dtype=bool)
    for v in range(V):
        if not seen[v]:
            order = np.r_[v, np.delete(np.arange(V), v)]
            comp = order[reachable_views(trusted[np.ix_(order, order)])]
            seen[comp] = True
            comps.append(np.sort(comp))
    core_idx = max(comps, key=lambda c: (len(c), root in c, -c[0]))
    if len(core_idx) < 2:
        return none
    sub_matches = {(a, b): matches[core_idx[a], core_idx[b]]
                   for a in range(len(core_idx)) for b in range(a + 1, len(core_idx))
                   if (core_idx[a], core_idx[b]) in matches}
    sub = PairwisePoses(pairwise.cam_from_cam[np.ix_(core_idx, core_idx)],
                        trusted[np.ix_(core_idx, core_idx)],
                        pairwise.inliers[np.ix_(core_idx, core_idx)], pairwise.focal)
    sol = solve_global(sub, robust=robust, matches=sub_matches, image_size=(H, W))
    out[core_idx] = sol.world_from_cam                  # all of the set is reachable
    solved = np.zeros(V, dtype=bool)
    solved[core_idx] = True
    core = solved.copy()
    rest = np.flatnonzero(~core)
    if len(rest):
        T_rest, ok = locate_views(images[core_idx], out[core_idx], pairwise.focal, images[rest],
                                  reference_matches=sub_matches)
        out[rest[ok]] = T_rest[ok]
        solved[rest[ok]] = True
    if not solved[root]:
        return none
    out = np.linalg.inv(out[root]) @ np.where(solved[:, None, None], out, np.eye(4))
    out[~solved] = np.nan
    out[root] = np.eye(4)
    return out, solved, core


@dataclass(frozen=True)
class CameraRefinement:
    """What ``refine_cameras`` did.

    world_from_cam: [V, 4, 4] the cameras to use (view 0 = I, the renderer's units)
    focal:          [2] the normalised focal (fx/W, fy/H) they hold at
    source:         "epipolar" (every view solved), "mixed" (the views ``solve_views`` could
                    not pose keep the model's camera), "model" (none solved, or one view)
    solved:         bool [V], the views whose camera comes from the epipolar solve
    scale:          the factor applied to the unit-free epipolar centres
    scale_source:   "depth" (``refine_cameras(scale="depth")``), or "fit", "baseline" or
                    "constant" (``fit_scale``)
    pairwise:       the ``PairwisePoses`` solved from
    """
    world_from_cam: np.ndarray
    focal: np.ndarray
    source: str
    solved: np.ndarray
    scale: float
    scale_source: str
    pairwise: PairwisePoses


def refine_cameras(images, world_from_cam, focal, *, focal_mode: str = "search",
                   robust: bool = True, scale: str = "depth",
                   depth_range: tuple[float, float] | None = None) -> CameraRefinement:
    """A model's predicted cameras replaced by the global epipolar solve of its images.

    images:         uint8 [V, H, W, 3], the model-resolution photos the model saw
    world_from_cam: [V, 4, 4] the model's poses (view 0 = I); focal: [2] its (fx/W, fy/H)
    focal_mode:     "search" (default): the essential matrices at the grid-searched focal
                    (``search_focal``), returned in ``focal`` (fy/H = fx/W * W/H), so the caller
                    must render with it; "model": at the model's focal (fx/W, square pixels),
                    returned unchanged. Measured on the 16 held-out scenes with the first shipped
                    model (models/iris-tiny.pt, whose focal is 0.34, ~3x too short), RPA@15 / @30
                    of the refined cameras of all 8 views: "search" 0.652 / 0.853 (median
                    rotation error 2.7 deg), "model" 0.167 / 0.344 (10.8 deg); the model's own
                    0.004 / 0.009. With models/iris-tiny-rgb.pt (focal ~1.2x the truth) the
                    model's focal gives slightly better cameras (5 references: 0.556 / 0.719 vs
                    0.538 / 0.694) but lower held-out PSNR (19.8 vs 20.4 dB). A model focal is
                    only as good as the camera head; the search needs none (median 1.06x the
                    true focal)

    scale:          how the unit-free centres get a unit. "depth" (default): the median of
                    ``match_depths`` over the trusted pairs is put ``DEPTH_TARGET`` of the way
                    into ``depth_range`` (near, far), the renderer's sampling range, which is the
                    unit the training data was built in (``scale_source`` "depth"; the "model"
                    rule when fewer than ``MIN_INLIERS`` matches triangulate). "model":
                    ``fit_scale`` against the model's centres of the solved views (the renderer
                    keeps the model's units, whatever they are). 8 validation scenes (seeds
                    50000-50007), iris-eval with models/iris-tiny-rgb.pt, Rand: PSNR 22.19
                    ("depth") vs 21.69 ("model"), nearest reference 20.67

    The cameras are ``solve_views``' (the largest trusted set solved, the other views located
    against it by PnP) of the photos taken in ``canonical_order`` and rooted at view 0, so the
    same photos in any order give the same cameras (up to the choice of view 0 and float
    rounding); their unit-free centres scaled as ``scale`` says. Views it cannot pose
    keep the model's pose (``source`` "mixed", with the searched focal for all views; "model"
    when no view but view 0 is solved: then the model's poses and focal, unchanged).
    """
    images = _check_images(images)
    T_model = np.asarray(world_from_cam, dtype=np.float64)
    f_model = np.asarray(focal, dtype=np.float64).reshape(2)
    V, H, W = images.shape[:3]
    if T_model.shape != (V, 4, 4):
        raise ValueError(f"world_from_cam: expected [{V}, 4, 4], got {T_model.shape}")
    if focal_mode not in ("model", "search"):
        raise ValueError(f"focal_mode: expected 'model' or 'search', got {focal_mode!r}")
    if scale not in SCALE_MODES:
        raise ValueError(f"scale: expected one of {SCALE_MODES}, got {scale!r}")
    if scale == "depth":
        near, far = (float(x) for x in np.asarray(depth_range, dtype=np.float64).reshape(2)) \
            if depth_range is not None else (np.nan, np.nan)
        if not (np.isfinite(near) and np.isfinite(far) and 0 <= near < far):
            raise ValueError(f"depth_range: expected (near, far) with 0 <= near < far for "
                             f"scale='depth', got {depth_range!r}")
    if V == 1:
        pp = PairwisePoses(np.tile(np.eye(4), (1, 1, 1, 1)), np.zeros((1, 1), bool),
                           np.zeros((1, 1), np.int32), float(f_model[0]))
        return CameraRefinement(T_model.copy(), f_model.copy(), "model", np.zeros(1, bool), 1.0,
                                "constant", pp)
    perm = canonical_order(images)          # solve index a <-> view perm[a]; view k <-> inv[k]
    inv = np.argsort(perm)
    canon = images[perm]
    matches = all_flow_matches(canon)
    pp = pairwise_poses(canon, None if focal_mode == "search" else float(f_model[0]),
                        matches=matches)
    f_used = f_model.copy() if focal_mode == "model" else np.array([pp.focal, pp.focal * W / H])
    T_can, solved_can, core_can = solve_views(canon, pp, matches, robust=robust, root=int(inv[0]))
    T_epi, solved = T_can[inv], solved_can[inv]
    out = T_model.copy()
    s, how = 1.0, "constant"
    idx = np.flatnonzero(solved)
    if len(idx) >= 2:
        depths = np.zeros(0)
        if scale == "depth":
            trusted = [(a, b) for (a, b) in matches
                       if pp.trusted[a, b] and core_can[a] and core_can[b]]
            depths = match_depths(matches, T_can, pp.focal, H, W, trusted)
        if len(depths) >= MIN_INLIERS:
            s, how = (near + DEPTH_TARGET * (far - near)) / float(np.median(depths)), "depth"
        else:
            s, how = fit_scale(T_model[idx, :3, 3], T_epi[idx, :3, 3], T_model[:, :3, 3])
        out[idx] = T_epi[idx]
        out[idx, :3, 3] *= s
    out[0] = np.eye(4)
    n_solved = int(solved[1:].sum())
    source = "epipolar" if n_solved == V - 1 else "model" if n_solved == 0 else "mixed"
    if source == "model":                  # nothing solved: the model's cameras and focal
        f_used = f_model.copy()
        solved = np.zeros(V, dtype=bool)
    pp = PairwisePoses(pp.cam_from_cam[np.ix_(inv, inv)], pp.trusted[np.ix_(inv, inv)],
                       pp.inliers[np.ix_(inv, inv)], pp.focal)      # in the caller's order
    return CameraRefinement(out, f_used, source, solved, float(s), how, pp)


# -- queries located with the references fixed -------------------------------------------------
def reference_depths(matches: dict, world_from_cam: np.ndarray, focal: float, H: int, W: int
                     ) -> np.ndarray:
    """Sparse depth maps [V, H, W] (z, the cameras' unit; NaN where no match lands) of V views
    with known cameras: every flow match of ``matches`` (``all_flow_matches``) triangulated by the
    ray midpoint (``MIN_PARALLAX``, in front of both cameras), its depth in each of the two views
    written to the pixel it falls in there, the median where several land."""
    T = np.asarray(world_from_cam, dtype=np.float64)
    V = T.shape[0]
    F = float(focal) * W
    cells, values = [], []
    for (i, j), (p, q) in matches.items():
        if not (np.isfinite(T[i]).all() and np.isfinite(T[j]).all()) or len(p) == 0:
            continue
        p, q = np.asarray(p, np.float64), np.asarray(q, np.float64)
        X, keep = _triangulate_pair(p, q, T[i], T[j], F, H, W)
        for view, pix in ((i, p[keep]), (j, q[keep])):
            z = (X[keep] - T[view, :3, 3]) @ T[view, :3, :3][:, 2]
            front = z > 0                             # the midpoint, not only the ray, in front
            cells.append(view * H * W + _cells(pix[front], H, W))
            values.append(z[front])
    out = np.full(V * H * W, np.nan)
    cells = np.concatenate(cells) if cells else np.zeros(0, np.int64)
    values = np.concatenate(values) if values else np.zeros(0)
    if len(cells):
        order = np.lexsort((values, cells))
        cells, values = cells[order], values[order]
        starts = np.flatnonzero(np.r_[True, cells[1:] != cells[:-1]])
        ends = np.r_[starts[1:], len(cells)]
        out[cells[starts]] = 0.5 * (values[(starts + ends - 1) // 2] + values[(starts + ends) // 2])
    return out.reshape(V, H, W)


def _rays(pix, F, H, W):
    """K^-1 [u, v, 1] [N, 3] (z = 1) of pixels [N, 2] at focal F pixels, principal point centred."""
    return np.stack([(pix[:, 0] - W / 2) / F, (pix[:, 1] - H / 2) / F, np.ones(len(pix))], 1)


def _cells(pix, H, W):
    """Flat index v * W + u [N] of the pixel each point [N, 2] (centres at +0.5) falls in."""
    u = np.clip(np.floor(pix[:, 0]).astype(np.int64), 0, W - 1)
    v = np.clip(np.floor(pix[:, 1]).astype(np.int64), 0, H - 1)
    return v * W + u


def _triangulate_pair(p, q, Ti, Tj, F, H, W):
    """World points [N, 3] of matches p (view i) -> q (view j) by the ray midpoint, and the bool
    [N] of those with parallax >= ``MIN_PARALLAX`` in front of both cameras."""
    a, e = _rays(p, F, H, W) @ Ti[:3, :3].T, _rays(q, F, H, W) @ Tj[:3, :3].T
    w = Ti[:3, 3] - Tj[:3, 3]
    aa, ae, ee = (a * a).sum(1), (a * e).sum(1), (e * e).sum(1)
    aw, ew = a @ w, e @ w
    det = aa * ee - ae * ae
    good = det / (aa * ee) > np.sin(MIN_PARALLAX) ** 2
    d = np.where(good, det, 1.0)
    za, ze = (-aw * ee + ae * ew) / d, (aa * ew - ae * aw) / d
    X = 0.5 * (Ti[:3, 3] + za[:, None] * a + Tj[:3, 3] + ze[:, None] * e)
    return X, good & (za > 0) & (ze > 0)


#: ``locate_views(method="pnp")``: reprojection threshold (pixels of the model image) of OpenCV's
#: PnP RANSAC, and the fewest 2D-3D inliers a located query needs.
PNP_THRESHOLD = 1.0
PNP_MIN_INLIERS = 30
#: Query-location methods of ``locate_views``.
LOCATE_METHODS = ("lines", "pnp")


def _locate_pnp(refs, T_ref, focal, query, depths, H, W):
    """One query's world_from_cam by PnP on its flow to every reference, whose pixels are lifted
    to 3D by ``depths`` [V, H, W] -> ([4, 4], inliers) or (None, 0)."""
    F = float(focal) * W
    obj, img = [], []
    for j in range(refs.shape[0]):
        pq, pr = flow_matches(query, refs[j])
        if len(pq) == 0:
            continue
        z = depths[j].ravel()[_cells(pr, H, W)]
        ok = np.isfinite(z)
        if not ok.any():
            continue
        ray = _rays(pr[ok].astype(np.float64), F, H, W)
        obj.append(T_ref[j, :3, 3] + (z[ok][:, None] * ray) @ T_ref[j, :3, :3].T)
        img.append(pq[ok].astype(np.float64))
    if not obj:
        return None, 0
    obj, img = np.concatenate(obj), np.concatenate(img)
    if len(obj) < PNP_MIN_INLIERS:
        return None, 0
    K = intrinsics(float(focal), H, W)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K, None, iterationsCount=500,
                                             reprojectionError=PNP_THRESHOLD, confidence=0.999,
                                             flags=cv2.SOLVEPNP_EPNP)
    if not ok or inl is None or len(inl) < PNP_MIN_INLIERS:
        return None, 0
    inl = inl.ravel()
    rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], K, None, rvec, tvec)
    R_cw = cv2.Rodrigues(rvec)[0]
    out = np.eye(4)
    out[:3, :3] = R_cw.T
    out[:3, 3] = -R_cw.T @ tvec.ravel()
    return out, len(inl)


def locate_views(reference_images, reference_world_from_cam, focal: float, query_images, *,
                 robust: bool = True, min_links: int = 2, method: str = "pnp",
                 reference_matches: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Poses of query photos with the references' cameras held fixed.

    reference_images: uint8 [V, H, W, 3]; reference_world_from_cam [V, 4, 4] (their cameras,
    in the units the query centres should come out in); focal fx/W the essential matrices are
    computed at; query_images uint8 [Q, H, W, 3].

    Per query q and reference j: flow, essential matrix and relative pose ``cam_from_cam[q, j]``
    as in ``relative_poses``. With the trusted links: rotation R_q = chordal mean of R_j R_qj
    (Cauchy-reweighted like ``solve_global`` when ``robust``), centre c_q = the point nearest to
    the lines c_j + s R_j t_qj (min sum w_j |[R_j t_qj]_x (c_q - c_j)|^2, w_j = sqrt(inliers)).
    A query with fewer than ``min_links`` trusted links, or whose lines are nearly parallel
    (smallest eigenvalue of the 3x3 normal matrix < 1e-3 of its trace), is not solved.
    ``method="pnp"`` (default) instead lifts the references' pixels to 3D (``reference_depths`` of their
    pairwise flow, triangulated with their cameras) and solves each query's pose from its flow
    to every reference by OpenCV's PnP RANSAC (EPnP, ``PNP_THRESHOLD`` px, then Levenberg-
    Marquardt on the inliers): the centre's distance comes from the references' scale rather than
    from intersecting direction lines. A query with fewer than ``PNP_MIN_INLIERS`` inliers falls
    back to the "lines" solve. ``reference_matches``: ``all_flow_matches(reference_images)`` when
    the caller has it (the PnP depths are built from it). Chosen on 48 validation scenes (seeds 50000-50047, iris-eval's
    protocol: 5 references solved, 3 targets located; docs/TRAINING.md, "Epipolar cameras"):
    RPA@15 / @30 0.517 / 0.709 against 0.504 / 0.701 with "lines".
    The references are taken in ``canonical_order`` (``reference_matches`` is used only when
    they already are, as ``solve_views`` passes them) and the queries solved in the first one's
    frame; each query is located on its own. So neither the order of the references, nor the
    reference their frame is rooted at, nor the order of the queries changes a pose (up to float
    rounding).
    Returns ``(world_from_cam [Q, 4, 4] with NaN for unsolved queries, solved bool [Q])``.
    Deterministic (OpenCV's RNG is seeded with 0 per query).
    """
    if method not in LOCATE_METHODS:
        raise ValueError(f"method: expected one of {LOCATE_METHODS}, got {method!r}")
    refs = _check_images(reference_images)
    queries = _check_images(query_images)
    T_ref = np.asarray(reference_world_from_cam, dtype=np.float64)
    V, H, W = refs.shape[:3]
    if queries.shape[1:] != refs.shape[1:]:
        raise ValueError(f"query_images: expected [Q, {H}, {W}, 3] like the references, got "
                         f"{queries.shape}")
    if T_ref.shape != (V, 4, 4):
        raise ValueError(f"reference_world_from_cam: expected [{V}, 4, 4], got {T_ref.shape}")
    perm = canonical_order(refs)
    if (perm != np.arange(V)).any():
        refs, T_ref, reference_matches = refs[perm], T_ref[perm], None
    # Solved in the first canonical reference's frame: EPnP and its RANSAC draws see the same
    # coordinates whichever reference the caller's frame is rooted at.
    anchor = T_ref[0].copy()
    T_ref = np.linalg.inv(anchor) @ T_ref
    K = intrinsics(float(focal), H, W)
    Q = queries.shape[0]
    out = np.full((Q, 4, 4), np.nan)
    ok = np.zeros(Q, dtype=bool)
    depths = None
    if method == "pnp":
        if reference_matches is None:
            reference_matches = all_flow_matches(refs)
        depths = reference_depths(reference_matches, T_ref, focal, H, W)
    for q in range(Q):
        cv2.setRNGSeed(0)
        if depths is not None:
            T_q, n = _locate_pnp(refs, T_ref, focal, queries[q], depths, H, W)
            if T_q is not None:
                out[q], ok[q] = T_q, True
                continue
        matches = {(0, j + 1): flow_matches(queries[q], refs[j]) for j in range(V)}
        pp = relative_poses(matches, V + 1, K)
        links = [j for j in range(V) if pp.trusted[0, j + 1]]
        if len(links) < min_links:
            continue
        w0 = np.sqrt(np.maximum(pp.inliers[0, [j + 1 for j in links]].astype(np.float64), 1.0))
        cand = np.stack([T_ref[j, :3, :3] @ pp.cam_from_cam[0, j + 1][:3, :3] for j in links])
        w = w0.copy()
        R = _project_so3(np.einsum("k,kab->ab", w, cand))
        if robust:
            for _ in range(3):
                res = np.linalg.norm(cand - R, axis=(1, 2))
                w = w0 / (1.0 + (res / 0.1) ** 2)
                R = _project_so3(np.einsum("k,kab->ab", w, cand))
        M, rhs = np.zeros((3, 3)), np.zeros(3)
        for j, wk in zip(links, w0):
            d = T_ref[j, :3, :3] @ pp.cam_from_cam[0, j + 1][:3, 3]
            P = np.eye(3) - np.outer(d, d) / max(float(d @ d), 1e-24)
            M += wk * P
            rhs += wk * P @ T_ref[j, :3, 3]
        ev = np.linalg.eigvalsh(M)
        if ev[0] < 1e-3 * ev.sum():
            continue
        out[q] = np.eye(4)
        out[q, :3, :3] = R
        out[q, :3, 3] = np.linalg.solve(M, rhs)
        ok[q] = True
    out[ok] = anchor @ out[ok]
    return out, ok

