"""What is evaluated: the MODEL and DATA arguments, and one scene brought to the protocol's frames
and the model's resolution."""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from iris_runtime.errors import InputError

from .protocol import DEFAULT_VIEWS

__all__ = ["SYNTHETIC_SETS", "SYNTHETIC_PHOTO_SIZE", "PreparedScene", "prepare_scene", "true_depth_and_K",
           "load_scenes", "load_evaluable", "scene_name", "to_output_size", "check_output_size"]

#: DATA values naming a synthetic set: the held-out scenes (the record), the validation scenes
#: (where choices are made; iris_train.data.VALIDATION_SEEDS), and the held-out capture-like
#: scenes (object walks, orbits, hand-held and indoor paths with photometric camera effects;
#: iris_train.data.CAPTURE_HELDOUT_SEEDS) and their validation twins (where capture-like choices
#: are made; CAPTURE_VALIDATION_SEEDS).
SYNTHETIC_SETS = ("synthetic:heldout", "synthetic:validation", "synthetic:capture-heldout",
                  "synthetic:capture-validation")
#: The seeds of the capture-like sets, by DATA name.
_CAPTURE_SETS = {"synthetic:capture-heldout": "CAPTURE_HELDOUT_SEEDS",
                 "synthetic:capture-validation": "CAPTURE_VALIDATION_SEEDS"}
#: The resolution (H, W) of the synthetic sets' photos, the camera solve's input: what a phone
#: photo shrunk for upload would be, not the model's thumbnail.
SYNTHETIC_PHOTO_SIZE = (256, 256)


@dataclass
class PreparedScene:
    """One scene's ``views`` frames at the model's resolution.

    images:     uint8 [N, H, W, 3]; gt_images: float64 [N, H, W, 3] in [0, 1] (the same)
    poses:      float64 [N, 4, 4] true world_from_cam, or None
    K:          float64 [N, 3, 3] true intrinsics in pixels of ``images``, or None
    true_depth: float64 [N, H, W] or None; stored_K: K as stored (for the camera picture)
    name:       the scene's folder name, synthetic seed or position
    photos:     the same frames at their own resolution, uint8 [h, w, 3] each: what a user hands
                the runtime, and what the camera solve works on (the model sees ``images``)
    photo_K:    float64 [N, 3, 3] true intrinsics in pixels of ``photos``, or None
    output_size: None (the protocol at the model's resolution), or (S, S) for ``iris-eval
                --size S``: then ``images`` are the photos fitted to the model
                (``iris_runtime.images.fit_to_model``, what the runtime does with them), the
                reference photos go to the encoder at their own resolution, and ``gt_images``
                and ``true_depth`` are at the output size (``to_output_size``), what the renders
                and the photo baselines are scored against
    """
    images: np.ndarray
    gt_images: np.ndarray
    poses: np.ndarray | None
    K: np.ndarray | None
    true_depth: np.ndarray | None
    stored_K: np.ndarray | None
    name: str
    photos: list[np.ndarray]
    photo_K: np.ndarray | None
    output_size: tuple[int, int] | None = None


def _frame_index(V: int, views: int) -> np.ndarray:
    """Frames kept of a V-frame scene: ``views`` evenly along the stored order."""
    return np.round(np.linspace(0, V - 1, views)).astype(int)


def scene_name(scene, index: int) -> str:
    meta = getattr(scene, "meta", None) or {}
    if meta.get("path"):
        return Path(meta["path"]).name
    if meta.get("seed") is not None:
        return f"seed {meta['seed']}"
    return f"scene {index}"


def _model_intrinsics(scene, idx: np.ndarray, image_size: tuple[int, int]) -> np.ndarray | None:
    """True K [N, 3, 3] in pixels of the model-resolution images (the stored K mapped through the
    same crop and resize as the images, ``iris_runtime.images.plan_crop_resize``), or None."""
    K = getattr(scene, "K", None)
    if K is None:
        return None
    K = np.asarray(K, dtype=np.float64)
    V, h, w = np.asarray(scene.images).shape[:3]
    K = np.broadcast_to(K, (V, 3, 3))[idx] if K.ndim == 2 else K[idx]
    if (h, w) == tuple(image_size):
        return np.array(K)
    from iris_runtime.images import plan_crop_resize
    plan = plan_crop_resize(h, w, *image_size)
    return np.stack([plan.adjust_intrinsics(k) for k in K])


def to_output_size(photo: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """A photo ``uint8 [h, w, 3]`` as the ground truth of an ``S x S`` render (``size`` (S, S)):
    centre-cropped to a square (``min(h, w)`` on a side, offsets ``(w - side) // 2`` and
    ``(h - side) // 2``: the crop ``fit_to_model`` gives the model too), then shrunk with
    ``cv2.INTER_AREA`` (a copy when the crop is S already). ``uint8 [S, S, 3]``. The photo must
    be at least S on its shorter side (``check_output_size``)."""
    from iris_runtime.images import fit_to_model
    return fit_to_model(np.asarray(photo), int(size[0]), int(size[1]))[0]


def check_output_size(photos, size: tuple[int, int], where: str) -> None:
    """``InputError`` unless every photo ``[h, w, 3]`` covers ``size`` (S, S) after the centre
    crop to a square, i.e. ``min(h, w) >= S``: renders are never scored against enlarged
    photos."""
    S = int(size[0])
    small = [np.asarray(p).shape[:2] for p in photos if min(np.asarray(p).shape[:2]) < S]
    if small:
        h, w = small[0]
        raise InputError(f"{where}: its photos are {w}x{h} (width x height), smaller than the "
                         f"output size {S}x{S} asked by --size {S}: ground truth would have to be "
                         f"enlarged; evaluate at --size {min(h, w)} or less")


def prepare_scene(scene, views: int, image_size: tuple[int, int], index: int = 0,
                  output_size: tuple[int, int] | None = None) -> PreparedScene | None:
    """``scene`` (``images`` uint8 [V, H, W, 3], ``world_from_cam`` [V, 4, 4] or None, optional
    ``K``, ``depth``, ``meta``, and ``photos`` / ``photo_K``: the frames at their own resolution
    where ``images`` were brought to the model's) -> its ``views`` frames at the model's size
    (images of another size through ``iris_runtime.images.fit_to_model``), or None when it has
    fewer frames.

    ``output_size`` (S, S) (``iris-eval --size S``): the model's images are the photos (or the
    images, without photos) fitted to the model, and the ground truth images and depth are the
    photos and depth brought to S (``to_output_size``; depth centre-cropped alike and resized
    nearest-neighbour); ``InputError`` when a photo is smaller than S (``check_output_size``)."""
    if output_size is not None:
        return _prepare_at_output_size(scene, views, image_size, index, output_size)
    images = np.asarray(scene.images)
    if images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise InputError(f"scene images: expected uint8 [V, H, W, 3], got {images.dtype} {images.shape}")
    poses = getattr(scene, "world_from_cam", None)
    V = images.shape[0]
    if V < views:
        return None
    idx = _frame_index(V, views)
    stored_photos = getattr(scene, "photos", None)
    if stored_photos is not None and len(stored_photos):
        if len(stored_photos) != V:
            raise InputError(f"scene photos: expected {V} (one per image), got {len(stored_photos)}")
        photos = [np.asarray(stored_photos[i]) for i in idx]
        photo_K = getattr(scene, "photo_K", None)
    else:
        photos, photo_K = list(images[idx]), getattr(scene, "K", None)
    if photo_K is not None and poses is not None:
        photo_K = np.asarray(photo_K, dtype=np.float64)
        photo_K = np.broadcast_to(photo_K, (V, 3, 3))[idx] if photo_K.ndim == 2 else photo_K[idx]
    else:
        photo_K = None
    images = images[idx]
    if poses is not None:
        poses = np.asarray(poses, dtype=np.float64)[idx]
    K = _model_intrinsics(scene, idx, image_size) if poses is not None else None
    if images.shape[1:3] != tuple(image_size):
        from iris_runtime.images import fit_to_model
        images = np.stack([fit_to_model(im, *image_size)[0] for im in images])
    true_depth, stored_K = true_depth_and_K(scene, views, image_size)
    return PreparedScene(images, images.astype(np.float64) / 255.0, poses, K, true_depth, stored_K,
                         scene_name(scene, index), photos, photo_K)


def _prepare_at_output_size(scene, views: int, image_size: tuple[int, int], index: int,
                            output_size: tuple[int, int]) -> PreparedScene | None:
    from iris_runtime.images import fit_to_model
    prepared = prepare_scene(scene, views, image_size, index)
    if prepared is None:
        return None
    photos = []
    for k, p in enumerate(prepared.photos):
        p = np.asarray(p)
        if p.ndim != 3 or p.shape[-1] != 3 or p.dtype != np.uint8:
            raise InputError(f"scene photos[{k}]: expected uint8 [h, w, 3], got {p.dtype} {p.shape}")
        photos.append(p)
    check_output_size(photos, output_size, f"scene {index} ({prepared.name})")
    images = np.stack([fit_to_model(p, *image_size)[0] for p in photos])
    gt = np.stack([to_output_size(p, output_size) for p in photos]).astype(np.float64) / 255.0
    depth = getattr(scene, "depth", None)
    true_depth = None
    if depth is not None:
        depth = np.asarray(depth, dtype=np.float64)
        V = np.asarray(scene.images).shape[0]
        if depth.ndim == 3 and depth.shape[0] == V:
            true_depth = _fit_depth(depth[_frame_index(V, views)], output_size)
    return dataclasses.replace(prepared, images=images, gt_images=gt, true_depth=true_depth,
                               photos=photos, output_size=(int(output_size[0]), int(output_size[1])))


def _fit_depth(depth: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Depth maps ``[N, h, w]`` -> ``[N, H, W]``: the images' centre crop, nearest-neighbour resize
    (no depths mixed across edges)."""
    if depth.shape[1:] == tuple(size):
        return depth
    import cv2

    from iris_runtime.images import plan_crop_resize
    H, W = size
    plan = plan_crop_resize(depth.shape[1], depth.shape[2], H, W)
    return np.stack([cv2.resize(np.ascontiguousarray(d[plan.y0:plan.y0 + plan.crop_h,
                                                       plan.x0:plan.x0 + plan.crop_w]),
                                (W, H), interpolation=cv2.INTER_NEAREST) for d in depth])


def true_depth_and_K(scene, views: int, image_size: tuple[int, int]):
    """-> ``(true depth float64 [N, H, W] at the model's size or None, K [3, 3] / [N, 3, 3] or None)``
    of the frames ``prepare_scene`` keeps. A depth of another size gets the same centre crop as
    the images and a nearest-neighbour resize (no depths mixed across edges); K is left as stored
    (only its cx/fx, cy/fy are used, for the camera picture)."""
    depth = getattr(scene, "depth", None)
    K = getattr(scene, "K", None)
    V = np.asarray(scene.images).shape[0]
    idx = _frame_index(V, views)
    if K is not None:
        K = np.asarray(K, dtype=np.float64)
        K = K[idx] if K.ndim == 3 else K
    if depth is None:
        return None, K
    depth = np.asarray(depth, dtype=np.float64)
    if depth.ndim != 3 or depth.shape[0] != V:
        return None, K
    return _fit_depth(depth[idx], image_size), K


def _with_photos(scene, photos):
    """A synthetic scene with its frames rendered at the photo size too (same seed: the same
    scene and cameras, K scaled)."""
    return _PhotoScene(scene.images, scene.world_from_cam, scene.K, scene.depth, scene.meta,
                       tuple(photos.images), photos.K)


@dataclass
class _PhotoScene:
    images: np.ndarray
    world_from_cam: np.ndarray
    K: np.ndarray
    depth: np.ndarray
    meta: dict
    photos: tuple
    photo_K: np.ndarray


def load_evaluable(path: str | os.PathLike, threads: int | None = None):
    """A checkpoint file -> ``IrisModel``; a directory with ``iris.json`` -> ``IrisRuntime``
    (``threads``: its ONNX Runtime intra-op threads)."""
    path = Path(path)
    if path.is_dir():
        if not (path / "iris.json").is_file():
            from iris_runtime.errors import ManifestError
            raise ManifestError(f"MODEL {str(path)!r} is a directory without iris.json "
                                "(expected an exported model directory or a .pt checkpoint)")
        from iris_runtime import IrisRuntime      # lazily: the runtime is optional here
        return IrisRuntime(path, threads=threads)
    from ..model import load_model, read_checkpoint, trained_cameras
    model = load_model(path)
    model.trained_cameras = trained_cameras(read_checkpoint(path))
    return model


def load_scenes(data: str, image_size: tuple[int, int], views: int = DEFAULT_VIEWS,
                limit: int | None = None, output_size: tuple[int, int] | None = None
                ) -> tuple[Iterable, int]:
    """DATA argument -> (scenes, count). ``synthetic:heldout`` / ``synthetic:validation`` render
    the held-out / validation synthetic scenes lazily; anything else is a folder of scene folders
    (``iris_train.data.load_dataset_folder``).

    ``output_size`` (S, S) (``iris-eval --size S``): the synthetic sets are their photos at
    ``SYNTHETIC_PHOTO_SIZE`` alone (the same seeds and cache as the photos of the default run;
    ``prepare_scene`` fits them to the model), and an S above that size is an ``InputError``
    before anything is rendered; a folder's scenes are checked likewise once loaded."""
    if output_size is not None and data in SYNTHETIC_SETS:
        check_output_size([np.zeros((*SYNTHETIC_PHOTO_SIZE, 3), np.uint8)], output_size,
                          f"DATA {data!r}")
        from .. import data as D
        if data in _CAPTURE_SETS:
            seeds, kind = list(getattr(D, _CAPTURE_SETS[data]))[:limit], "capture"
        else:
            seeds = list(D.HELDOUT_SEEDS if data == "synthetic:heldout" else D.VALIDATION_SEEDS)[:limit]
            kind = None
        # Cached at SYNTHETIC_PHOTO_SIZE (default_cache_dir: .../synthetic/256x256[/capture]),
        # the files `python -m iris_train.data --heldout --render-size 256 256` writes.
        photos = D.SyntheticScenes(seeds, n_views=views, size=SYNTHETIC_PHOTO_SIZE, kind=kind)
        return (photos[i] for i in range(len(photos))), len(photos)
    if data in _CAPTURE_SETS:
        from .. import data as D
        # The photos are the 256x256 renders with their camera effects, brought to the model's
        # size by prepare_scene like any user's photos.
        scenes = D.SyntheticScenes(list(getattr(D, _CAPTURE_SETS[data]))[:limit], n_views=views,
                                   size=SYNTHETIC_PHOTO_SIZE, kind="capture")
        return (scenes[i] for i in range(len(scenes))), len(scenes)
    if data in SYNTHETIC_SETS:
        from .. import data as D
        seeds = list(D.HELDOUT_SEEDS if data == "synthetic:heldout" else D.VALIDATION_SEEDS)[:limit]
        # Rendered on first use and cached on disk (iris_train.data.default_cache_dir): at the
        # model's size (what it sees and is scored against, as it always was) and at
        # SYNTHETIC_PHOTO_SIZE, the photos' own resolution that the camera solve works on.
        scenes = D.SyntheticScenes(seeds, n_views=views, size=tuple(image_size))
        photos = D.SyntheticScenes(seeds, n_views=views, size=SYNTHETIC_PHOTO_SIZE)
        return (_with_photos(scenes[i], photos[i]) for i in range(len(scenes))), len(scenes)
    if data.startswith("synthetic:"):
        raise InputError(f"DATA {data!r}: the synthetic sets are {list(SYNTHETIC_SETS)}")
    path = Path(data)
    if not path.is_dir():
        raise InputError(f"DATA {data!r}: not one of {list(SYNTHETIC_SETS)} and not a folder")
    from ..data import load_dataset_folder
    scenes = load_dataset_folder(path, size=tuple(image_size))[:limit]
    if output_size is not None:         # refused before any scene is evaluated
        for i, scene in enumerate(scenes):
            check_output_size(scene.photos or scene.images, output_size,
                              f"scene {i} ({scene_name(scene, i)})")
    return scenes, len(scenes)
