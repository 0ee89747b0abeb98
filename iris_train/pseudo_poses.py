"""Pseudo-poses: the cameras of a training scene from its photos alone (no labels), the teacher
of the camera head and the cameras ``iris-train --render-cameras solve`` renders with.

The photometric loss alone leaves the camera head in a long valley (a small rotation and a small
sideways translation move a 64x64 image alike; docs/TRAINING.md). Multi-view geometry has no
such valley, so each training scene is posed once, from its pixels only, by the runtime's own
camera solve (``iris_runtime.cameras.solve_cameras``: SIFT matches, two-view model selection,
incremental mapping, bundle adjustment; docs/CAMERAS.md), on the scene's photos at the highest
resolution the dataset keeps (``SyntheticScenes.cached`` when it renders larger than it trains),
and the focal carried to the training size. Two products, both cached beside the scene cache:

- ``SolvedCameras`` (``load_or_solve``): every view's ``world_from_cam`` in view 0's frame, in
  the renderer's unit (the scene's median point depth ``DEPTH_TARGET`` into [near, far], what
  ``IrisRuntime.encode(cameras="solve")`` gives the renderer at inference);
- ``PseudoPoses`` (``load_or_estimate``): the same cameras as relative poses of every pair
  (unit translation, "trusted" where both views are posed), for the teacher losses.

Solving takes CPU-hours for thousands of scenes, so the solved cameras are kept twice: one small
file per scene beside the scene cache (local), and, packed by ``--pack``, one file per
``STORE_BLOCK`` consecutive seeds under ``data/teacher/`` in the repository, where they survive
the machine (the photos are a function of the seed and are rendered again where needed).

Nothing here reads a camera label; ``python -m iris_train.pseudo_poses --heldout --score``
compares the teacher with the true poses of the held-out scenes.
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

from iris_runtime.cameras import DEPTH_TARGET, solve_cameras  # noqa: F401 (DEPTH_TARGET: docs)
from iris_runtime.images import plan_crop_resize

from .config import preset
from .data import HELDOUT_SEEDS, SyntheticScenes, kind_version
from .scene_sets import CAPTURE_RENDER_SIZE
from .synthetic import CAPTURE_KINDS

#: Version of both caches (part of the file; another version is recomputed): raised whenever the
#: solve's results change (docs/TRAINING.md lists which runs used which). SOLVE_VERSION 12 and
#: TEACHER_VERSION 14: the solve adjusts with the one ``bundle.bundle_adjust`` (Nielsen's
#: damping, until then the refinement's alone), so its cameras moved; the store of version 11
#: that trained the shipped head is in git history (data/teacher/README.md).
TEACHER_VERSION = 14
SOLVE_VERSION = 12
#: The teacher's depth range when none is given (the models' [near, far]).
DEFAULT_DEPTH_RANGE = (0.1, 1.0)
#: The packed store of solved cameras (``pack``): kept in the repository, one file per block of
#: consecutive seeds, in a folder naming what the cameras depend on (``store_folder``).
STORE_DIR = Path(__file__).resolve().parents[1] / "data" / "teacher"
STORE_BLOCK = 500


@dataclass(frozen=True)
class SolvedCameras:
    """One camera per view of a training scene: ``world_from_cam [V, 4, 4]`` in view 0's frame
    and the renderer's unit (NaN for views the solve could not pose); ``focal`` fx/W at the
    training size (square pixels); ``solved`` bool [V], the views with a camera."""
    world_from_cam: np.ndarray
    focal: float
    solved: np.ndarray

    def rebased(self, order: np.ndarray) -> np.ndarray:
        """The cameras of views ``order`` (all solved) in the frame of ``order[0]`` -> [n, 4, 4]."""
        T = self.world_from_cam[np.asarray(order)]
        return np.linalg.inv(T[0]) @ T


@dataclass(frozen=True)
class PseudoPoses:
    """The teacher of the camera head: ``cam_from_cam [V, V, 4, 4]``, entry [i, j] maps camera
    i's coordinates to camera j's (unit translation; identity where not trusted); ``trusted
    [V, V]`` bool (both views posed, i != j); ``inliers [V, V]`` int32, the scene points both
    views see; ``focal`` fx/W at the training size."""
    cam_from_cam: np.ndarray
    trusted: np.ndarray
    inliers: np.ndarray
    focal: float


def solve_scene(images: np.ndarray, depth_range: tuple[float, float] = DEFAULT_DEPTH_RANGE,
                train_size: tuple[int, int] | None = None) -> SolvedCameras:
    """``images`` uint8 ``[V, h, w, 3]`` (any size) -> ``SolvedCameras``, the focal carried to
    ``train_size`` (H, W; default the photos' own) through ``fit_to_model``'s centre crop and
    resize. Deterministic."""
    return _solve(images, depth_range, train_size)[0]


def _solve(images, depth_range, train_size):
    images = np.asarray(images)
    h, w = images.shape[1:3]
    H, W = (h, w) if train_size is None else (int(train_size[0]), int(train_size[1]))
    s = solve_cameras(list(images), depth_range)
    K = plan_crop_resize(h, w, H, W).matrix @ s.K
    posed = s.posed
    T = np.where(posed[:, None, None], s.world_from_cam, np.nan)
    if s.root != 0:                       # view 0 unposed: no frame for the others either
        T, posed = np.full_like(T, np.nan), np.zeros_like(posed)
    return SolvedCameras(T, float(K[0, 0] / W), posed.copy()), s


def _pairs(solved: SolvedCameras, shared: np.ndarray) -> PseudoPoses:
    """The relative poses of every pair of posed views of ``solved``; ``shared [V, V]`` the
    points both see."""
    T = solved.world_from_cam
    V = T.shape[0]
    trusted = solved.solved[:, None] & solved.solved[None, :] & ~np.eye(V, dtype=bool)
    cam_from_cam = np.tile(np.eye(4), (V, V, 1, 1))
    for i, j in zip(*np.nonzero(trusted)):
        rel = np.linalg.inv(T[j]) @ T[i]
        rel[:3, 3] /= max(np.linalg.norm(rel[:3, 3]), 1e-12)
        cam_from_cam[i, j] = rel
    return PseudoPoses(cam_from_cam, trusted, np.where(trusted, shared, 0).astype(np.int32),
                       solved.focal)


def estimate(images: np.ndarray, train_size: tuple[int, int] | None = None,
             depth_range: tuple[float, float] = DEFAULT_DEPTH_RANGE) -> PseudoPoses:
    """``images`` uint8 ``[V, h, w, 3]`` of one static scene -> ``PseudoPoses`` (the solved
    cameras as relative poses; focal at ``train_size``, default the photos' own size)."""
    solved, s = _solve(images, depth_range, train_size)
    V = len(s.status)
    pm = s.point_map
    sees = np.zeros((V, max(len(pm.points), 1)), bool)
    sees[pm.view, pm.point] = True
    shared = sees.astype(np.int64) @ sees.T.astype(np.int64)
    return _pairs(solved, shared)


# -- cache ------------------------------------------------------------------------------------
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


def _photos(scenes, index: int) -> np.ndarray:
    """The photos of ``scenes[index]`` at the highest resolution the dataset keeps: its cached
    render when it has one (``SyntheticScenes.cached``), else the scene as served."""
    cached = getattr(scenes, "cached", None)
    if callable(cached):
        return cached(int(scenes.seeds[index])).images
    return scenes[index].images


def _train_size(scenes, index: int) -> tuple[int, int]:
    size = getattr(scenes, "size", None)
    return tuple(int(x) for x in size) if size is not None else scenes[index].images.shape[1:3]


def cache_path(cache_dir: Path, seed: int, n_views: int, train_size: tuple[int, int]) -> Path:
    """One file per training size: a render cache serves models of several sizes."""
    return Path(cache_dir) / f"pseudo_{seed:07d}_v{n_views}_{train_size[0]}x{train_size[1]}.npz"


def solved_cache_path(cache_dir: Path, seed: int, n_views: int, train_size: tuple[int, int]
                      ) -> Path:
    return Path(cache_dir) / f"solved_{seed:07d}_v{n_views}_{train_size[0]}x{train_size[1]}.npz"


def load_or_estimate(scenes, index: int) -> PseudoPoses:
    """``PseudoPoses`` of ``scenes[index]`` (a ``SyntheticScenes``), from the cache or computed."""
    size = _train_size(scenes, index)
    path = cache_path(scenes.cache_dir, scenes.seeds[index], scenes.n_views, size)
    key = {"version": TEACHER_VERSION, "train_size": np.asarray(size)}
    z = _read_cache(path, **key)
    if z is not None:
        return PseudoPoses(z["cam_from_cam"], z["trusted"], z["inliers"], float(z["focal"]))
    pp = estimate(_photos(scenes, index), size)
    _write_cache(path, **key, cam_from_cam=pp.cam_from_cam, trusted=pp.trusted,
                 inliers=pp.inliers, focal=pp.focal)
    return pp


def _solved_key(depth_range, size) -> dict:
    return {"version": SOLVE_VERSION, "depth_range": np.asarray(depth_range, np.float64),
            "train_size": np.asarray(size)}


def load_or_solve(scenes, index: int, depth_range: tuple[float, float],
                  store_dir: Path | None = STORE_DIR) -> SolvedCameras:
    """``SolvedCameras`` of ``scenes[index]`` (a ``SyntheticScenes``): from the packed store
    under ``store_dir`` (None: not looked at), else from the scene's own cache file, else
    solved (and written to the scene's cache file)."""
    size = _train_size(scenes, index)
    seed = int(scenes.seeds[index])
    folder = store_folder(scenes, size, store_dir) if store_dir is not None else None
    if folder is not None:
        block = _read_block(folder / _block_name(seed), depth_range, size)
        if block is not None and seed in block:
            return block[seed]
    path = solved_cache_path(scenes.cache_dir, seed, scenes.n_views, size)
    key = _solved_key(depth_range, size)
    z = _read_cache(path, **key)
    if z is not None:
        return SolvedCameras(z["world_from_cam"], float(z["focal"]), z["solved"])
    sc = solve_scene(_photos(scenes, index), depth_range, size)
    _write_cache(path, **key, world_from_cam=sc.world_from_cam, focal=sc.focal, solved=sc.solved)
    return sc


# -- the packed store: the solved cameras of many scenes, kept in the repository ---------------
def store_folder(scenes, train_size: tuple[int, int], store_dir: Path = STORE_DIR) -> Path | None:
    """The store's folder for the scenes of ``scenes`` (a ``SyntheticScenes``) trained at
    ``train_size``: named by their kind and its version, the render size the solve ran on, the
    training size, the views per scene and ``SOLVE_VERSION``; None for datasets the store does
    not keep (mixes of kinds, datasets that are not synthetic scenes)."""
    render = getattr(scenes, "render_size", None)
    kind_of = getattr(scenes, "kind_of", None)
    kind = getattr(scenes, "kind", None)
    if render is None or kind_of is None or isinstance(kind, dict):
        return None
    # "capture" draws one of the capture kinds per seed: the folder carries the newest of their
    # versions, so that a change to any of them starts a new folder.
    kinds = CAPTURE_KINDS if kind == "capture" else (kind,)
    name = ("classic-1" if kind is None
            else f"{kind}-{max(kind_version(k) for k in kinds)}")
    return Path(store_dir) / (f"{name}_{render[0]}x{render[1]}_to_{train_size[0]}x{train_size[1]}"
                              f"_v{scenes.n_views}_solve{SOLVE_VERSION}")


def _block_name(seed: int, block: int | None = None) -> str:
    block = STORE_BLOCK if block is None else block
    first = seed - seed % block
    return f"seeds_{first:07d}-{first + block - 1:07d}.npz"


_BLOCKS: dict = {}


def _read_block(path: Path, depth_range, size) -> dict[int, SolvedCameras] | None:
    """{seed: SolvedCameras} of one store file (read once per process and file version); None
    when the file is missing or its key (solve version, depth range, training size) differs."""
    try:
        stamp = path.stat().st_mtime_ns
    except OSError:
        return None
    tag = (str(path), stamp, tuple(map(float, depth_range)), tuple(size))
    if tag not in _BLOCKS:
        z = _read_cache(path, **_solved_key(depth_range, size))
        _BLOCKS[tag] = None if z is None else {
            int(s): SolvedCameras(z["world_from_cam"][k], float(z["focal"][k]), z["solved"][k])
            for k, s in enumerate(z["seeds"])}
    return _BLOCKS[tag]


def pack(scenes, depth_range: tuple[float, float], store_dir: Path = STORE_DIR,
         block: int | None = None) -> list[Path]:
    """Gather the solved cameras of ``scenes`` (a ``SyntheticScenes`` over consecutive seeds)
    into the store: one file per whole block of ``block`` seeds (first seed a multiple of it)
    whose every scene has a current cache file or is in the store already. Files are written
    atomically and never partial; returns the paths written."""
    block = STORE_BLOCK if block is None else block
    size = tuple(int(x) for x in scenes.size)
    folder = store_folder(scenes, size, store_dir)
    if folder is None:
        raise ValueError("pack: the store keeps single-kind synthetic scenes only")
    index_of = {int(s): i for i, s in enumerate(scenes.seeds)}
    key = _solved_key(depth_range, size)
    written = []
    for first in sorted({s - s % block for s in index_of}):
        seeds = range(first, first + block)
        if not all(s in index_of for s in seeds):
            continue
        path = folder / _block_name(first, block)
        have = _read_block(path, depth_range, size) or {}
        if len(have) == block:
            continue
        found = []
        for s in seeds:
            z = have.get(s)
            if z is None:
                c = _read_cache(solved_cache_path(scenes.cache_dir, s, scenes.n_views, size), **key)
                z = None if c is None else SolvedCameras(c["world_from_cam"], float(c["focal"]),
                                                         c["solved"])
            if z is None:
                break
            found.append(z)
        if len(found) < block:
            continue
        folder.mkdir(parents=True, exist_ok=True)
        _write_cache(path, **key, seeds=np.asarray(seeds, np.int64),
                     world_from_cam=np.stack([z.world_from_cam for z in found]),
                     focal=np.asarray([z.focal for z in found]),
                     solved=np.stack([z.solved for z in found]))
        written.append(path)
    return written


def _work(args) -> int:
    spec, index, depth_range = args
    cv2.setNumThreads(1)
    scenes = _scenes(*spec)
    if depth_range is None:
        load_or_estimate(scenes, index)
    else:
        load_or_solve(scenes, index, depth_range)
    return index


def _scenes(seeds, kind=None, size=(64, 64), render_size=None):
    return SyntheticScenes(seeds, size=size, kind=kind, render_size=render_size)


def pregenerate(seeds, workers: int = 2, depth_range: tuple[float, float] | None = None,
                kind: str | None = None, size: tuple[int, int] = (64, 64),
                render_size: tuple[int, int] | None = None) -> None:
    """Fill the cache of ``SyntheticScenes(seeds, size=size, kind=kind, render_size=...)``: the
    pair teacher, or with ``depth_range`` the solved scene cameras (what ``iris-train`` builds
    lazily, one scene at a time, otherwise)."""
    import multiprocessing as mp
    from tqdm import tqdm
    spec = (tuple(seeds), kind, tuple(size), None if render_size is None else tuple(render_size))
    jobs = [(spec, i, depth_range) for i in range(len(spec[0]))]
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


def _report_pack(paths: list[Path]) -> None:
    for path in paths:
        print(f"packed {path}")
    if not paths:
        print("packed nothing: no whole block of seeds newly solved")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m iris_train.pseudo_poses",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--train", type=int, default=0, help="training seeds 0..N-1 to cache")
    parser.add_argument("--capture", type=int, default=0,
                        help="capture-like training seeds 0..N-1 (rendered at iris-train's "
                             "CAPTURE_RENDER_SIZE, as iris-train --capture-scenes draws them)")
    parser.add_argument("--classic-render-size", type=int, default=0,
                        help="with --train: the classic scenes rendered at this square size, as "
                             "iris-train --classic-render-size (default: the model's)")
    parser.add_argument("--heldout", action="store_true", help="the held-out scenes")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--solve", action="store_true",
                        help="with --train: cache the solved scene cameras (what iris-train "
                             "--render-cameras solve renders with) instead of the pair teacher")
    parser.add_argument("--pack", action="store_true",
                        help="with --solve: gather the solved cameras of every whole block of "
                             f"{STORE_BLOCK} seeds into data/teacher/ (kept in the repository)")
    parser.add_argument("--pack-only", action="store_true",
                        help="with --pack: solve nothing, pack the blocks the local caches hold")
    parser.add_argument("--score", action="store_true",
                        help="compare with the true poses (held-out scenes): RPA of the teacher "
                             "over all pairs (pairs with an unposed view count as failures)")
    args = parser.parse_args(argv)
    cfg = preset("tiny")
    size = (cfg.image_height, cfg.image_width)
    depth_range = (cfg.near, cfg.far) if args.solve else None
    if args.pack and not args.solve:
        parser.error("--pack: needs --solve (the store keeps solved cameras)")
    if args.pack_only and not args.pack:
        parser.error("--pack-only: needs --pack")
    if args.train:
        side = args.classic_render_size
        render_size = (side, side) if side else None
        if not args.pack_only:
            pregenerate(range(args.train), args.workers, depth_range, size=size,
                        render_size=render_size)
        if args.pack:
            _report_pack(pack(SyntheticScenes(range(args.train), size=size,
                                              render_size=render_size), depth_range))
    if args.capture:
        if not args.pack_only:
            pregenerate(range(args.capture), args.workers, depth_range, kind="capture",
                        size=size, render_size=CAPTURE_RENDER_SIZE)
        if args.pack:
            _report_pack(pack(SyntheticScenes(range(args.capture), size=size, kind="capture",
                                              render_size=CAPTURE_RENDER_SIZE), depth_range))
    if args.heldout:
        pregenerate(HELDOUT_SEEDS, args.workers, size=size)
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
            ok = e[:, 0] < 180
            print(json.dumps({"pairs": len(e), "trusted": float(np.mean(trusted)),
                              **{f"rpa@{t}": float(np.mean(e.max(1) < t)) for t in (5, 15, 30)},
                              "median_rotation_error_trusted": float(np.median(e[ok, 0])) if ok.any() else None,
                              "median_translation_error_trusted": float(np.median(e[ok, 1])) if ok.any() else None,
                              "focal_ratio_median": float(np.median(focal_ratio))}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
