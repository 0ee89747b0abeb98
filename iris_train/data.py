"""Data for training and evaluation: cached synthetic scenes and users' folders of photos.

- ``SyntheticScenes``: scenes of ``iris_train.synthetic`` by seed, rendered on first use and cached
  as one ``.npz`` per scene (written atomically) under ``default_cache_dir(size)``
  = ``$IRIS_CACHE_DIR/synthetic/<H>x<W>/`` (``IRIS_CACHE_DIR`` defaults to ``~/.cache/iris``).
  ``pregenerate`` fills the cache with several processes. Capture kinds (``kind="capture"``, a
  kind name or a mix) are cached clean at a render size and brought to the model's size and
  given their photometric camera effects on access.
- ``TRAIN_SEEDS`` / ``HELDOUT_SEEDS`` / ``VALIDATION_SEEDS`` and ``CAPTURE_HELDOUT_SEEDS`` /
  ``CAPTURE_VALIDATION_SEEDS``: the fixed, disjoint seed splits.
- ``load_scene_folder`` / ``load_dataset_folder``: users' folders of photos, with optional
  cameras (``iris_train.folders``, whose names are importable from here too).

``SceneData`` is a dataclass, which torch's default collate does not batch: use a ``collate_fn``
(or index one scene per step, as the training loop draws V views of *one* scene).
"""
from __future__ import annotations

import io
import json
import multiprocessing as mp
import os
import time
import warnings
import zipfile
from collections import OrderedDict
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from iris_runtime.fileio import atomic_write_bytes
from iris_runtime.errors import InputError

from .folders import IMAGE_SUFFIXES, FolderScene, load_dataset_folder, load_scene_folder
from .synthetic import (ALL_KINDS, CAPTURE_KINDS, KIND_VERSIONS, KINDS, SceneData,
                        downsample_scene, kind_version, photometric, render_scene, resolve_kind)

__all__ = ["TRAIN_SEEDS", "HELDOUT_SEEDS", "VALIDATION_SEEDS", "CAPTURE_HELDOUT_SEEDS",
           "CAPTURE_VALIDATION_SEEDS", "IMAGE_SUFFIXES", "default_cache_dir", "SyntheticScenes",
           "pregenerate", "main", "save_scene", "load_scene", "parse_mix", "kind_of_seed",
           "FolderScene", "load_scene_folder", "load_dataset_folder", "relative_to_first"]

# Fixed seed splits. Training draws only from TRAIN_SEEDS; HELDOUT_SEEDS lie far outside that
# range so that no training run, whatever its length, ever sees a held-out scene. The held-out
# scenes are the evaluation set for NVS (PSNR/SSIM) and pose (RPA) numbers.
TRAIN_SEEDS = range(0, 100_000)
HELDOUT_SEEDS = tuple(range(1_000_000, 1_000_016))
assert min(HELDOUT_SEEDS) > TRAIN_SEEDS[-1]
# Validation: where choices are made (methods, constants), so that the held-out scenes only ever
# report. Inside the training range but above any run's --train-scenes so far (training uses
# seeds 0 .. train_scenes - 1; iris_train.train refuses a count that would reach them).
VALIDATION_SEEDS = tuple(range(50_000, 50_048))
# The capture kinds (kind="capture": walk, orbit, handheld, indoor by seed % 4, so each set is
# balanced) use the same TRAIN_SEEDS (their random streams differ from the classic kinds') and
# their own held-out and validation seeds, disjoint from training and from each other.
CAPTURE_HELDOUT_SEEDS = tuple(range(2_000_000, 2_000_016))
CAPTURE_VALIDATION_SEEDS = tuple(range(60_000, 60_048))
assert min(CAPTURE_HELDOUT_SEEDS) > TRAIN_SEEDS[-1] and min(CAPTURE_VALIDATION_SEEDS) > max(VALIDATION_SEEDS)


# ----------------------------------------------------------------------------------------------
# Synthetic scenes, cached
# ----------------------------------------------------------------------------------------------

def default_cache_dir(size: tuple[int, int] = (64, 64)) -> Path:
    """``$IRIS_CACHE_DIR/synthetic/<H>x<W>`` with ``IRIS_CACHE_DIR`` defaulting to ``~/.cache/iris``."""
    root = Path(os.environ.get("IRIS_CACHE_DIR", Path.home() / ".cache" / "iris"))
    return root / "synthetic" / f"{int(size[0])}x{int(size[1])}"


def _cache_path(cache_dir: Path, seed: int, n_views: int, version: int = 1) -> Path:
    # Version 1 files keep their old names (the classic kinds' caches stay valid); later
    # versions carry theirs in the name, so two generator versions can share a folder.
    suffix = "" if version == 1 else f"_g{version}"
    return Path(cache_dir) / f"scene_{int(seed):07d}_v{int(n_views)}{suffix}.npz"


def save_scene(path: Path, scene: SceneData, depth_dtype=np.float32) -> None:
    """Write ``scene`` to ``path`` (.npz, compressed) atomically: temp file + ``os.replace``.

    ``meta`` is stored as JSON; numpy arrays inside ``meta`` (marker coverage) are not stored.
    The file records the generator version of the scene's kind. ``depth_dtype=np.float16``
    stores depth to ~5e-4 relative and 8x smaller (renders kept only to be downsampled).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {k: v for k, v in scene.meta.items() if not isinstance(v, np.ndarray)}
    buf = io.BytesIO()
    np.savez_compressed(buf, images=scene.images, world_from_cam=scene.world_from_cam, K=scene.K,
                        depth=scene.depth.astype(depth_dtype), meta=np.array(json.dumps(meta)),
                        generator_version=np.array(kind_version(meta.get("kind", "turntable"))))
    atomic_write_bytes(path, buf.getvalue())


def load_scene(path: Path) -> SceneData:
    """Read a scene written by ``save_scene``. Raises ``InputError`` if unreadable or stale
    (another generator version than its kind's current one)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            version = int(z["generator_version"])
            meta = json.loads(str(z["meta"]))
            kind = meta.get("kind")
            expected = kind_version(kind) if kind in KIND_VERSIONS else None
            if version != expected:
                raise InputError(f"{path}: generator version {version} for kind {kind!r}, expected "
                                 f"{expected}")
            return SceneData(images=z["images"], world_from_cam=z["world_from_cam"], K=z["K"],
                             depth=z["depth"].astype(np.float32, copy=False), meta=meta)
    except InputError:
        raise
    except (OSError, KeyError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise InputError(f"{path}: not a readable cached scene ({type(e).__name__}: {e})") from None


def parse_mix(text: str) -> dict[str, float]:
    """``"walk=2,orbit=1,handheld=1"`` -> ``{"walk": 2.0, ...}`` (kinds of ``ALL_KINDS`` except
    "capture", weights > 0). Raises ``InputError`` naming the bad item."""
    mix: dict[str, float] = {}
    for item in str(text).split(","):
        name, sep, weight = item.strip().partition("=")
        try:
            w = float(weight) if sep else 1.0
        except ValueError:
            w = float("nan")
        if name not in ALL_KINDS or name == "capture" or not w > 0 or not np.isfinite(w):
            raise InputError(f"mix: expected kind=weight items with kinds from "
                             f"{tuple(k for k in ALL_KINDS if k != 'capture')} and weights > 0, "
                             f"got {item!r}")
        mix[name] = mix.get(name, 0.0) + w
    return mix


def kind_of_seed(seed: int, kind) -> str:
    """The concrete kind of scene ``seed`` under ``kind``: None (classic, drawn from the seed),
    a kind name, "capture", or a mix ``{kind: weight}`` (drawn from the seed with the weights)."""
    if isinstance(kind, dict):
        names = sorted(kind)
        p = np.array([kind[k] for k in names], dtype=np.float64)
        rng = np.random.default_rng([int(seed), 0x313])
        return names[int(rng.choice(len(names), p=p / p.sum()))]
    return resolve_kind(seed, kind)


class SyntheticScenes:
    """Synthetic scenes by seed, generated on first access and cached on disk.

    ``SyntheticScenes(seeds, n_views=8, size=(64, 64), cache_dir=None, kind=None)[i]`` is the
    ``SceneData`` of ``seeds[i]`` (images uint8 [V, H, W, 3], world_from_cam [V, 4, 4], K [3, 3],
    depth [V, H, W]). A map-style dataset: works with ``torch.utils.data.DataLoader`` given a
    collate_fn.

    ``kind``: None (the classic kinds, drawn from the seed), a kind name, "capture" or a mix
    ``{kind: weight}`` / ``"walk=2,orbit=1"`` (``parse_mix``). Scenes are cached at
    ``render_size`` (default ``size``; a multiple of it, e.g. 256 for a 64 or 128 model) and
    brought to ``size`` on access by ``downsample_scene``; capture kinds are cached *clean* and
    then given their photometric camera effects unless ``clean``. So one 256 cache serves a
    teacher solve at 256 and models at 64 and 128.
    ``memory``: how many scenes to keep in memory once brought to ``size`` (least recently used
    out; a 64x64 8-view scene takes ~230 kB), which spares reading and downsampling them again.
    """

    def __init__(self, seeds: Sequence[int], n_views: int = 8, size: tuple[int, int] = (64, 64),
                 cache_dir: Path | None = None, kind=None, render_size: tuple[int, int] | None = None,
                 clean: bool = False, memory: int = 0):
        self.seeds = seeds
        self.n_views = int(n_views)
        self.size = (int(size[0]), int(size[1]))
        self.render_size = self.size if render_size is None else (int(render_size[0]), int(render_size[1]))
        f = self.render_size[0] // self.size[0]
        if f < 1 or self.render_size != (self.size[0] * f, self.size[1] * f):
            raise InputError(f"render_size: expected a whole multiple of size {self.size}, got "
                             f"{self.render_size}")
        self.factor = f
        self.kind = parse_mix(kind) if isinstance(kind, str) and ("=" in kind or "," in kind) else kind
        if self.kind is not None and not isinstance(self.kind, dict):
            resolve_kind(0, self.kind)                   # raises on an unknown kind
        self.clean = bool(clean)
        self.memory = int(memory)
        self._kept: OrderedDict[int, SceneData] = OrderedDict()
        self._root = Path(cache_dir) if cache_dir is not None else None
        # The folder of kind=None (and of the classic kinds' files); kept as an attribute because
        # callers put side caches (pseudo-poses, solved cameras) beside the scenes.
        self.cache_dir = self._root if self._root is not None else default_cache_dir(self.render_size)
        if isinstance(self.kind, str) and self._root is None:
            # The default cache holds mixed kinds; keep single-kind scenes apart.
            self.cache_dir = self.cache_dir / self.kind

    def __len__(self) -> int:
        return len(self.seeds)

    def kind_of(self, seed: int) -> str | None:
        """The concrete kind of ``seed`` (None: a classic kind drawn from the seed)."""
        return None if self.kind is None else kind_of_seed(seed, self.kind)

    def path(self, seed: int) -> Path:
        kind = self.kind_of(seed)
        version = 1 if kind is None else kind_version(kind)
        if not isinstance(self.kind, dict):
            return _cache_path(self.cache_dir, seed, self.n_views, version)
        # A mix: one sub-folder per kind, shared with the single-kind caches of the same root.
        base = self._root if self._root is not None else default_cache_dir(self.render_size)
        return _cache_path(base / kind, seed, self.n_views, version)

    def __getitem__(self, i: int) -> SceneData:
        if not -len(self) <= i < len(self):
            raise IndexError(f"index {i} out of range for {len(self)} scenes")
        return self.get_seed(int(self.seeds[i]))

    def render(self, seed: int) -> SceneData:
        """The scene as cached: rendered at ``render_size``, clean."""
        return render_scene(seed, self.n_views, self.render_size, kind=self.kind_of(seed), clean=True)

    def cached(self, seed: int) -> SceneData:
        """The cached scene of ``seed`` (rendered and written when missing or stale)."""
        p = self.path(seed)
        if p.exists():
            try:
                scene = load_scene(p)
                if scene.images.shape[:3] == (self.n_views, *self.render_size):
                    return scene
                warnings.warn(f"regenerating cached scene: {p} holds {scene.images.shape[:3]}",
                              stacklevel=3)
            except InputError as e:
                warnings.warn(f"regenerating cached scene: {e}", stacklevel=3)
        scene = self.render(seed)
        return self._save(p, scene)

    def _save(self, path: Path, scene: SceneData) -> SceneData:
        """Write ``scene`` and return it as it reads back. A render cache that is only ever
        downsampled keeps depth in float16: 8x smaller on disk (float32 depth compresses badly)."""
        dtype = np.float16 if self.factor > 1 else np.float32
        save_scene(path, scene, dtype)
        depth = scene.depth.astype(dtype).astype(np.float32)
        return SceneData(scene.images, scene.world_from_cam, scene.K, depth, scene.meta)

    def get_seed(self, seed: int) -> SceneData:
        if seed in self._kept:
            self._kept.move_to_end(seed)
            return self._kept[seed]
        scene = downsample_scene(self.cached(seed), self.factor)
        if scene.meta.get("kind") in CAPTURE_KINDS and not self.clean:
            scene = SceneData(photometric.apply(scene.images, seed), scene.world_from_cam,
                              scene.K, scene.depth, {**scene.meta, "photometric": True})
        if self.memory > 0:
            self._kept[seed] = scene
            while len(self._kept) > self.memory:
                self._kept.popitem(last=False)
        return scene

    def is_cached(self, seed: int) -> bool:
        return self.path(seed).exists()


def _pool_init() -> None:
    # Each worker renders on one core; llvmpipe would otherwise start one thread per core in
    # every worker and the workers would fight over the same cores.
    os.environ.setdefault("LP_NUM_THREADS", "1")


def _same_scene(a: SceneData, b: SceneData) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f))
               for f in ("images", "world_from_cam", "K", "depth"))


def _generate(args: tuple) -> bool:
    """Render one scene into the cache; with ``verify``, re-render a cached one and replace it
    if it differs. Returns True when a stale cached file was replaced."""
    seed, n_views, size, cache_dir, kind, verify, render_size = args
    ds = SyntheticScenes([seed], n_views, size, cache_dir, kind, render_size)
    if verify and ds.is_cached(seed):
        try:
            old = load_scene(ds.path(seed))
        except InputError:
            old = None
        new = ds.render(seed)
        if old is not None and _same_scene(old, new) or (
                old is not None and ds.factor > 1 and _same_scene(old, SceneData(
                    new.images, new.world_from_cam, new.K,
                    new.depth.astype(np.float16).astype(np.float32), new.meta))):
            return False
        ds._save(ds.path(seed), new)
        return True
    ds.cached(seed)
    return False


def pregenerate(seeds: Iterable[int], n_views: int = 8, size: tuple[int, int] = (64, 64),
                cache_dir: Path | None = None, workers: int = 2, kind=None,
                progress: bool = True, verify: bool = False,
                render_size: tuple[int, int] | None = None) -> dict:
    """Render and cache every scene of ``seeds`` not yet cached, with ``workers`` processes.

    ``kind`` and ``render_size`` as in ``SyntheticScenes``. ``verify=True`` also re-renders the
    cached scenes and replaces those that differ from what the current code renders (use it after
    changing the generator without bumping its version). Returns ``{"generated": n, "cached": n,
    "replaced": n, "seconds": t, "cache_dir": str, "bytes": total size of the seeds' files}``.
    Workers are started with the "spawn" method: a forked child would inherit the parent's
    OpenGL context.
    """
    ds = SyntheticScenes(list(seeds), n_views, size, cache_dir, kind, render_size)
    todo = [s for s in ds.seeds if not ds.is_cached(s)]
    work = list(ds.seeds) if verify else todo
    t0 = time.perf_counter()
    jobs = [(s, ds.n_views, ds.size, cache_dir, ds.kind, verify, ds.render_size) for s in work]
    replaced = 0
    bar = None
    if progress and work:
        from tqdm import tqdm
        bar = tqdm(total=len(work), desc=f"rendering scenes into {ds.cache_dir}", unit="scene")
    if workers <= 1 or len(work) <= 1:
        results = map(_generate, jobs)
        for r in results:
            replaced += int(r)
            if bar:
                bar.update(1)
    else:
        with mp.get_context("spawn").Pool(workers, initializer=_pool_init) as pool:
            for r in pool.imap_unordered(_generate, jobs, chunksize=4):
                replaced += int(r)
                if bar:
                    bar.update(1)
    if bar:
        bar.close()
    return {"generated": len(todo), "cached": len(ds.seeds) - len(todo), "replaced": replaced,
            "seconds": time.perf_counter() - t0, "cache_dir": str(ds.cache_dir),
            "bytes": sum(ds.path(s).stat().st_size for s in ds.seeds if ds.is_cached(s))}


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m iris_train.data --train 3000 --heldout [--verify]``: fill the default cache;
    ``--kind capture --render-size 256 256 --train 3000 --capture-heldout``: the capture kinds."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m iris_train.data",
                                 description="Pre-generate the synthetic scene cache.")
    ap.add_argument("--train", type=int, default=0, help="first N training seeds (0..N-1)")
    ap.add_argument("--heldout", action="store_true", help="the 16 classic held-out seeds")
    ap.add_argument("--validation", action="store_true", help="the validation seeds of --kind")
    ap.add_argument("--capture-heldout", action="store_true",
                    help="the 16 held-out seeds of the capture kinds (kind capture), rendered at "
                         "--size whatever --render-size")
    ap.add_argument("--kind", "--mix", default=None,
                    help=f"one of {ALL_KINDS}, or a mix such as walk=2,orbit=1,handheld=1,indoor=1 "
                         "(default: the classic kinds drawn from the seed)")
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--size", type=int, nargs=2, default=(64, 64), metavar=("H", "W"))
    ap.add_argument("--render-size", type=int, nargs=2, default=None, metavar=("H", "W"),
                    help="capture kinds: cache renders of this size (a multiple of --size)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--cache-dir", type=Path, default=None)
    ap.add_argument("--verify", action="store_true",
                    help="re-render cached scenes and replace those that differ")
    a = ap.parse_args(argv)
    try:
        kind = parse_mix(a.kind) if a.kind and "=" in a.kind else a.kind
        resolve_kind(0, None if isinstance(kind, dict) else kind)
    except InputError as e:
        ap.error(str(e))
    capture = kind is not None and (isinstance(kind, dict) or kind not in KINDS)
    splits = [("train", TRAIN_SEEDS[:a.train], kind),
              ("heldout", HELDOUT_SEEDS if a.heldout else (), None),
              ("validation", (CAPTURE_VALIDATION_SEEDS if capture else VALIDATION_SEEDS)
               if a.validation else (), kind),
              ("capture-heldout", CAPTURE_HELDOUT_SEEDS if a.capture_heldout else (), "capture")]
    for name, seeds, k in splits:
        if len(seeds):
            # Held-out scenes are rendered at the model's size: exact depth for the evaluation.
            render = tuple(a.render_size) if a.render_size and name != "capture-heldout" else None
            r = pregenerate(seeds, a.views, tuple(a.size), a.cache_dir, a.workers, k,
                            verify=a.verify, render_size=render)
            n = max(r["generated"], 1)
            print(json.dumps({"split": name, **r, "bytes_per_scene": r["bytes"] / len(seeds),
                              "seconds_per_scene": r["seconds"] / n}))


def relative_to_first(world_from_cam: np.ndarray) -> np.ndarray:
    """Poses ``[V, 4, 4]`` re-expressed in view 0's camera frame (so that result[0] == I)."""
    T = np.asarray(world_from_cam, dtype=np.float64)
    R0, c0 = T[0, :3, :3], T[0, :3, 3]
    cam0_from_world = np.eye(4)
    cam0_from_world[:3, :3] = R0.T
    cam0_from_world[:3, 3] = -R0.T @ c0
    out = cam0_from_world @ T
    out[0] = np.eye(4)
    return out


if __name__ == "__main__":
    main()
