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

The geometry itself is ``iris_runtime.epipolar`` (numpy + OpenCV, torch-free: the runtime's
``IrisRuntime.encode(images, cameras="epipolar")`` uses the same code); this module adds the cache,
the pre-generation CLI and the score against the true poses, which also scores the global solve
(``iris_runtime.epipolar.solve_cameras``) over all pairs.

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

# The two-view geometry lives in the torch-free runtime (one implementation for the teacher, the
# runtime's cameras="epipolar" and iris-eval); its constants are re-exported here.
from iris_runtime.epipolar import (ESTIMATOR, FB_TOLERANCE, FLOW_UPSAMPLE,  # noqa: F401
                                   FOCAL_GRID, FOCAL_SEARCH_POINTS, MIN_INLIER_RATIO, MIN_INLIERS,
                                   RANSAC_THRESHOLD, PairwisePoses, flow_matches, intrinsics,
                                   pairwise_poses, solve_global)

#: 4: flow vectors without texture dropped (``epipolar.TEXTURE_MIN``); 3: as stored before.
TEACHER_VERSION = 4

#: The teacher's result: ``iris_runtime.epipolar.PairwisePoses`` (cam_from_cam [V, V, 4, 4],
#: trusted, inliers, focal), under the name the training code knows it by.
PseudoPoses = PairwisePoses
# Kept for callers of the old private names.
_flow_matches = flow_matches
_intrinsics = intrinsics


def estimate(images: np.ndarray) -> PseudoPoses:
    """``images`` uint8 ``[V, H, W, 3]`` of one static scene -> ``PseudoPoses`` at the
    grid-searched focal (``iris_runtime.epipolar.pairwise_poses(images)``)."""
    return pairwise_poses(images)


# -- cache ------------------------------------------------------------------------------------
def cache_path(cache_dir: Path, seed: int, n_views: int) -> Path:
    return Path(cache_dir) / f"pseudo_{seed:07d}_v{n_views}.npz"


def _read_cache(path: Path, **key) -> dict | None:
    """The arrays of the ``.npz`` cache file ``path`` if its ``key`` arrays (version, ...) equal
    ``key``; None when it is missing, unreadable or stale (the caller recomputes)."""
    if not path.is_file():
        return None
    try:
        with np.load(path) as z:
            if all(np.array_equal(z[k], v) for k, v in key.items()):
                return {k: z[k] for k in z.files}
    except (OSError, KeyError, ValueError):
        pass
    return None


def _write_cache(path: Path, **arrays) -> None:
    import io
    from iris_runtime.fileio import atomic_write_bytes
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    atomic_write_bytes(path, buf.getvalue())


def load_or_estimate(scenes, index: int) -> PseudoPoses:
    """Pseudo-poses of ``scenes[index]`` (a ``SyntheticScenes``), from the cache or computed."""
    path = cache_path(scenes.cache_dir, scenes.seeds[index], scenes.n_views)
    z = _read_cache(path, version=TEACHER_VERSION)
    if z is not None:
        return PseudoPoses(z["cam_from_cam"], z["trusted"], z["inliers"], float(z["focal"]))
    pp = estimate(scenes[index].images)
    _write_cache(path, version=TEACHER_VERSION, cam_from_cam=pp.cam_from_cam, trusted=pp.trusted,
                 inliers=pp.inliers, focal=pp.focal)
    return pp


# -- solved scene cameras: the whole scene posed by the runtime's epipolar solve ---------------
#: Version of the solved-camera cache (part of the file; another version is recomputed).
#: 2: the solve takes the photos in ``epipolar.canonical_order`` and drops flow vectors without
#: texture (``epipolar.TEXTURE_MIN``); 1, F1's teacher: in the stored order, every vector.
SOLVE_VERSION = 2


@dataclass(frozen=True)
class SolvedCameras:
    """One camera per view of a training scene from ``iris_runtime.epipolar.refine_cameras`` of
    its photos (no labels): ``world_from_cam [V, 4, 4]`` in view 0's frame, scaled so that the
    scene's median triangulated depth is ``DEPTH_TARGET`` into the renderer's [near, far] (the
    unit ``IrisRuntime.encode(cameras="epipolar")`` gives the renderer at inference); ``focal``
    the searched fx/W; ``solved`` bool [V] (views the solve could not pose hold NaN)."""
    world_from_cam: np.ndarray
    focal: float
    solved: np.ndarray

    def rebased(self, order: np.ndarray) -> np.ndarray:
        """The cameras of views ``order`` (all solved) in the frame of ``order[0]`` -> [n, 4, 4]."""
        T = self.world_from_cam[np.asarray(order)]
        return np.linalg.inv(T[0]) @ T


def solve_scene(images: np.ndarray, depth_range: tuple[float, float]) -> SolvedCameras:
    """``images`` uint8 ``[V, H, W, 3]`` -> ``SolvedCameras`` (the runtime's solve, seeded)."""
    from iris_runtime.epipolar import refine_cameras
    cv2.setRNGSeed(0)
    V = images.shape[0]
    ref = refine_cameras(images, np.tile(np.eye(4), (V, 1, 1)), np.ones(2), depth_range=depth_range)
    # ref.solved holds view 0 (= I) whenever any view is solved, none when the solve failed.
    T = np.where(ref.solved[:, None, None], ref.world_from_cam, np.nan)
    return SolvedCameras(T, float(ref.focal[0]), ref.solved.copy())


def solved_cache_path(cache_dir: Path, seed: int, n_views: int) -> Path:
    return Path(cache_dir) / f"solved_{seed:07d}_v{n_views}.npz"


def load_or_solve(scenes, index: int, depth_range: tuple[float, float]) -> SolvedCameras:
    """``SolvedCameras`` of ``scenes[index]`` (a ``SyntheticScenes``), from the cache or solved."""
    path = solved_cache_path(scenes.cache_dir, scenes.seeds[index], scenes.n_views)
    key = {"version": SOLVE_VERSION, "depth_range": np.asarray(depth_range, np.float64)}
    z = _read_cache(path, **key)
    if z is not None:
        return SolvedCameras(z["world_from_cam"], float(z["focal"]), z["solved"])
    sc = solve_scene(scenes[index].images, depth_range)
    _write_cache(path, **key, world_from_cam=sc.world_from_cam, focal=sc.focal, solved=sc.solved)
    return sc


def _work(args) -> int:
    seeds, index, depth_range = args
    cv2.setNumThreads(1)
    from .data import SyntheticScenes
    scenes = SyntheticScenes(seeds)
    if depth_range is None:
        load_or_estimate(scenes, index)
    else:
        load_or_solve(scenes, index, depth_range)
    return index


def pregenerate(seeds, workers: int = 2, depth_range: tuple[float, float] | None = None) -> None:
    """Fill the cache: the pair teacher, or with ``depth_range`` the solved scene cameras."""
    import multiprocessing as mp
    from tqdm import tqdm
    seeds = tuple(seeds)
    jobs = [(seeds, i, depth_range) for i in range(len(seeds))]
    with mp.get_context("spawn").Pool(workers) as pool:
        for _ in tqdm(pool.imap_unordered(_work, jobs, chunksize=4), total=len(jobs),
                      desc="pseudo-poses" if depth_range is None else "solved cameras",
                      dynamic_ncols=True):
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


def global_errors(pp: PseudoPoses, world_from_cam: np.ndarray, *, robust: bool = True
                  ) -> np.ndarray:
    """``[P, 2]`` rotation and (sign-free) translation-direction errors in degrees of every pair
    i < j of the globally solved cameras (``iris_runtime.epipolar.solve_global``) against true
    poses (``iris_train.metrics.relative_pose_errors``); pairs with a view the solve does not
    reach count as 180."""
    from .metrics import relative_pose_errors
    sol = solve_global(pp, robust=robust)
    T = np.where(sol.solved[:, None, None], sol.world_from_cam, np.eye(4))
    rot, trans = relative_pose_errors(T, world_from_cam)
    i, j = np.triu_indices(len(T), 1)
    bad = ~(sol.solved[i] & sol.solved[j])
    return np.stack([np.where(bad, 180.0, rot), np.where(bad, 180.0, trans)], 1)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m iris_train.pseudo_poses",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--train", type=int, default=0, help="training seeds 0..N-1 to cache")
    parser.add_argument("--heldout", action="store_true", help="the held-out scenes")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--solve", action="store_true",
                        help="with --train: cache the whole-scene epipolar solve (the cameras "
                             "iris-train --render-cameras epipolar renders with) instead of the "
                             "pair teacher")
    parser.add_argument("--score", action="store_true",
                        help="compare with the true poses (held-out scenes): RPA of the teacher "
                             "(trusted pairs; the others count as failures) and, under 'global', "
                             "of the globally solved cameras over all pairs")
    args = parser.parse_args(argv)
    from .data import HELDOUT_SEEDS, SyntheticScenes
    if args.train:
        from .config import preset
        cfg = preset("tiny")
        pregenerate(range(args.train), args.workers,
                    (cfg.near, cfg.far) if args.solve else None)
    if args.heldout:
        pregenerate(HELDOUT_SEEDS, args.workers)
        if args.score:
            scenes = SyntheticScenes(HELDOUT_SEEDS)
            errs, glob, trusted, focal_ratio = [], [], [], []
            for i in range(len(scenes)):
                pp = load_or_estimate(scenes, i)
                d = scenes[i]
                errs.append(pair_errors(pp, d.world_from_cam))
                glob.append(global_errors(pp, d.world_from_cam))
                trusted.append(pp.trusted[np.triu_indices(d.images.shape[0], 1)].mean())
                focal_ratio.append(pp.focal / (d.K[0, 0] / d.images.shape[2]))
            e = np.concatenate(errs)
            ep = e.max(1)
            g = np.concatenate(glob)
            print(json.dumps({"pairs": len(e), "trusted": float(np.mean(trusted)),
                              **{f"rpa@{t}": float(np.mean(ep < t)) for t in (5, 15, 30)},
                              "median_rotation_error_trusted": float(np.median(e[e[:, 0] < 180, 0])),
                              "median_translation_error_trusted": float(np.median(e[e[:, 1] < 180, 1])),
                              "focal_ratio_median": float(np.median(focal_ratio)),
                              "global": {
                                  **{f"rpa@{t}": float(np.mean(g.max(1) < t)) for t in (5, 15, 30)},
                                  "median_rotation_error": float(np.median(g[:, 0])),
                                  "median_translation_error": float(np.median(g[:, 1]))}},
                             indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
