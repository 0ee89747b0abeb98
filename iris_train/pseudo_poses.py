"""Epipolar pseudo-poses: relative cameras of a training scene from its images alone (no labels).

The photometric loss alone leaves the camera head in a long valley: at 64x64 with a narrow depth
range, a small rotation and a small sideways translation move the image alike, and the learned
renderer co-adapts to collapsed cameras (issue 10's measurements, docs/TRAINING.md). Classical
two-view geometry has no such valley for the rotation: dense optical flow between two photos of a
static scene fixes the essential matrix, whose rotation is well conditioned even where the
translation direction is not. So each training scene gets, once, from its pixels only:

1. dense flow between every pair of views (OpenCV DIS on 4x upsampled grey images), kept where the
   forward and backward flows agree;
2. one shared focal by a grid search (the focal whose essential matrices explain the most flow
   vectors, over pairs two or three views apart);
3. per pair, the essential matrix (OpenCV's USAC_ACCURATE, 5-point) and the relative pose it implies
   (``cv2.recoverPose``: rotation and a unit translation, sign fixed by cheirality).

These are a teacher for the camera head (``iris_train.train``: rotation geodesic and translation
direction losses on the pairs the teacher trusts), next to the photometric losses that fix the
scale. Nothing here reads a camera label; evaluation compares them with the true poses only to
report how good a teacher they are (``python -m iris_train.pseudo_poses --heldout --score``).

The result is cached beside the scene cache as ``pseudo_<seed:07d>_v<n>.npz`` (``TEACHER_VERSION``
is part of the file; a different version is recomputed).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

TEACHER_VERSION = 3
#: Upsampling before flow (DIS works on 4x4+ patches; at 64x64 the flow is too coarse without it).
FLOW_UPSAMPLE = 4
#: Forward-backward disagreement (pixels of the model image) above which a flow vector is dropped.
FB_TOLERANCE = 0.5
#: Focal candidates fx/W (vertical fields of view from about 35 to 80 degrees).
FOCAL_GRID = tuple(float(f) for f in np.geomspace(0.6, 1.6, 11))
#: A pair is trusted when RANSAC keeps at least this many flow vectors and this fraction of them.
MIN_INLIERS = 100
MIN_INLIER_RATIO = 0.5
#: Robust estimator of the essential matrix and its inlier threshold (pixels of the model image).
#: USAC_ACCURATE (local optimisation + final polishing on all inliers) at 0.25 px against RANSAC at
#: 0.5 px, 16 held-out scenes with the true focal: teacher RPA@15 0.641 vs 0.480, median rotation
#: error 2.1 vs 3.9 degrees, translation direction 8.3 vs 15.0 (docs/TRAINING.md, "teacher").
ESTIMATOR = cv2.USAC_ACCURATE
RANSAC_THRESHOLD = 0.25
FOCAL_SEARCH_POINTS = 1500


@dataclass(frozen=True)
class PseudoPoses:
    """``cam_from_cam [V, V, 4, 4]``: entry [i, j] maps camera i's coordinates to camera j's
    (x_j = R x_i + t, |t| = 1); ``trusted [V, V]`` bool (symmetric, False on the diagonal);
    ``inliers [V, V]``; ``focal`` fx/W of the grid search (shared, square pixels)."""
    cam_from_cam: np.ndarray
    trusted: np.ndarray
    inliers: np.ndarray
    focal: float


def _flow_matches(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel correspondences ``p -> q`` ``[N, 2]`` (model-image pixels, centres at +0.5) from
    forward-backward-consistent DIS flow between uint8 RGB images a and b."""
    up = FLOW_UPSAMPLE
    H, W = a.shape[:2]
    grey = [cv2.resize(cv2.cvtColor(x, cv2.COLOR_RGB2GRAY), (W * up, H * up),
                       interpolation=cv2.INTER_CUBIC) for x in (a, b)]
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    fwd = dis.calc(grey[0], grey[1], None)
    bwd = dis.calc(grey[1], grey[0], None)
    step = up // 2
    ys, xs = np.mgrid[0:H * up:step, 0:W * up:step]
    p = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float32) + 0.5
    f = fwd[ys.ravel(), xs.ravel()]
    q = p + f
    back = cv2.remap(bwd, q[:, :1] - 0.5, q[:, 1:] - 0.5, cv2.INTER_LINEAR).reshape(-1, 2)
    ok = ((np.linalg.norm(f + back, axis=1) < FB_TOLERANCE * up)
          & (q[:, 0] > 0) & (q[:, 1] > 0) & (q[:, 0] < W * up) & (q[:, 1] < H * up))
    return p[ok] / up, q[ok] / up


def _intrinsics(focal: float, H: int, W: int) -> np.ndarray:
    return np.array([[focal * W, 0.0, W / 2], [0.0, focal * W, H / 2], [0.0, 0.0, 1.0]])


def estimate(images: np.ndarray) -> PseudoPoses:
    """``images`` uint8 ``[V, H, W, 3]`` of one static scene -> ``PseudoPoses``."""
    cv2.setRNGSeed(0)                      # RANSAC draws: same images, same teacher
    V, H, W = images.shape[:3]
    matches = {(i, j): _flow_matches(images[i], images[j]) for i in range(V) for j in range(i + 1, V)}
    # The focal search scores 11 focals on ~11 pairs: a fixed random subset of each pair's flow
    # vectors keeps it at a third of the scene's time (the final fit below uses all of them).
    rng = np.random.default_rng(0)
    subsets = {k: rng.permutation(len(p))[:FOCAL_SEARCH_POINTS] for k, (p, _) in matches.items()}
    scores = []
    for f in FOCAL_GRID:
        K = _intrinsics(f, H, W)
        ratios = []
        for (i, j), (p, q) in matches.items():
            if j - i not in (2, 3) or len(p) < MIN_INLIERS:
                continue
            p, q = p[subsets[i, j]], q[subsets[i, j]]
            E, inl = cv2.findEssentialMat(p, q, K, ESTIMATOR, 0.999, RANSAC_THRESHOLD)
            if E is not None and E.shape == (3, 3):
                ratios.append(float(inl.mean()))
        scores.append(np.mean(ratios) if ratios else 0.0)
    focal = FOCAL_GRID[int(np.argmax(scores))]
    K = _intrinsics(focal, H, W)
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
    return PseudoPoses(cam_from_cam, trusted, inliers, float(focal))


# -- cache ------------------------------------------------------------------------------------
def cache_path(cache_dir: Path, seed: int, n_views: int) -> Path:
    return Path(cache_dir) / f"pseudo_{seed:07d}_v{n_views}.npz"


def load_or_estimate(scenes, index: int) -> PseudoPoses:
    """Pseudo-poses of ``scenes[index]`` (a ``SyntheticScenes``), from the cache or computed."""
    from iris_runtime.camera_io import atomic_write_bytes
    import io
    seed = scenes.seeds[index]
    path = cache_path(scenes.cache_dir, seed, scenes.n_views)
    if path.is_file():
        try:
            with np.load(path) as z:
                if int(z["version"]) == TEACHER_VERSION:
                    return PseudoPoses(z["cam_from_cam"], z["trusted"], z["inliers"], float(z["focal"]))
        except (OSError, KeyError, ValueError):
            pass                                      # unreadable or old: recompute below
    pp = estimate(scenes[index].images)
    buf = io.BytesIO()
    np.savez(buf, version=TEACHER_VERSION, cam_from_cam=pp.cam_from_cam, trusted=pp.trusted,
             inliers=pp.inliers, focal=pp.focal)
    atomic_write_bytes(path, buf.getvalue())
    return pp


def _work(args) -> int:
    seeds, index = args
    cv2.setNumThreads(1)
    from .data import SyntheticScenes
    load_or_estimate(SyntheticScenes(seeds), index)
    return index


def pregenerate(seeds, workers: int = 2) -> None:
    import multiprocessing as mp
    from tqdm import tqdm
    seeds = tuple(seeds)
    jobs = [(seeds, i) for i in range(len(seeds))]
    with mp.get_context("spawn").Pool(workers) as pool:
        for _ in tqdm(pool.imap_unordered(_work, jobs, chunksize=4), total=len(jobs),
                      desc="pseudo-poses", dynamic_ncols=True):
            pass


# -- scoring against the truth (evaluation only) ----------------------------------------------
def pair_errors(pp: PseudoPoses, world_from_cam: np.ndarray) -> np.ndarray:
    """``[P, 2]`` rotation and (sign-free) translation-direction errors in degrees of every pair
    i < j against true poses; untrusted pairs count as 180."""
    V = world_from_cam.shape[0]
    out = []
    for i in range(V):
        for j in range(i + 1, V):
            if not pp.trusted[i, j]:
                out.append((180.0, 180.0))
                continue
            true = np.linalg.inv(world_from_cam[j]) @ world_from_cam[i]
            T = pp.cam_from_cam[i, j]
            c = np.clip((np.trace(T[:3, :3].T @ true[:3, :3]) - 1) / 2, -1, 1)
            a, b = T[:3, 3], true[:3, 3]
            ct = abs(a @ b) / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-12)
            out.append((math.degrees(math.acos(c)), math.degrees(math.acos(min(ct, 1.0)))))
    return np.array(out)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m iris_train.pseudo_poses",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--train", type=int, default=0, help="training seeds 0..N-1 to cache")
    parser.add_argument("--heldout", action="store_true", help="the held-out scenes")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--score", action="store_true",
                        help="compare with the true poses (held-out scenes): RPA of the teacher")
    args = parser.parse_args(argv)
    from .data import HELDOUT_SEEDS, SyntheticScenes
    if args.train:
        pregenerate(range(args.train), args.workers)
    if args.heldout:
        pregenerate(HELDOUT_SEEDS, args.workers)
        if args.score:
            scenes = SyntheticScenes(HELDOUT_SEEDS)
            errs, trusted, focal_ratio = [], [], []
            for i in range(len(scenes)):
                pp = load_or_estimate(scenes, i)
                d = scenes[i]
                errs.append(pair_errors(pp, d.world_from_cam))
                trusted.append(pp.trusted[np.triu_indices(d.images.shape[0], 1)].mean())
                focal_ratio.append(pp.focal / (d.K[0, 0] / d.images.shape[2]))
            e = np.concatenate(errs)
            ep = e.max(1)
            print(json.dumps({"pairs": len(e), "trusted": float(np.mean(trusted)),
                              **{f"rpa@{t}": float(np.mean(ep < t)) for t in (5, 15, 30)},
                              "median_rotation_error_trusted": float(np.median(e[e[:, 0] < 180, 0])),
                              "median_translation_error_trusted": float(np.median(e[e[:, 1] < 180, 1])),
                              "focal_ratio_median": float(np.median(focal_ratio))}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
