"""Users' folders of photos as scenes at model resolution (``load_scene_folder``,
``load_dataset_folder``): photos of any size (sorted by file name = Seq order) brought to model
resolution with ``iris_runtime.images.fit_to_model``, with optional cameras from nerfstudio
``transforms.json`` or COLMAP text files, intrinsics adjusted for the crop. ``iris_train.data``
re-exports these names.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from iris_runtime.camera_io import CameraSet, read_colmap_text, read_transforms_json
from iris_runtime.errors import ImageError, InputError
from iris_runtime.images import CropResize, fit_to_model, load_image

__all__ = ["IMAGE_SUFFIXES", "FolderScene", "load_scene_folder", "load_dataset_folder"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class FolderScene:
    """Photos of one scene brought to model resolution (SceneData-like).

    images:         uint8   [V, H, W, 3]   in file-name order (= Seq order)
    world_from_cam: float64 [V, 4, 4] | None  OpenCV camera-to-world, None without camera files
    K:              float64 [V, 3, 3] | None  per view, in pixels of the *output* images
                                              (adjusted for the crop/resize of each photo)
    depth:          None (photos have no depth)
    names:          file names relative to the scene folder
    crops:          the CropResize of each photo (source size, crop box, scales)
    meta:           {"path": ..., "camera_source": path of the camera file or None}
    photos:         the photos as loaded, uint8 [h, w, 3] each at their own size (what a user
                    hands the runtime; the camera solve works on them)
    photo_K:        float64 [V, 3, 3] | None  K in pixels of ``photos``
    """

    images: np.ndarray
    world_from_cam: np.ndarray | None
    K: np.ndarray | None
    names: tuple[str, ...]
    crops: tuple[CropResize, ...]
    meta: dict = field(default_factory=dict)
    depth: None = None
    photos: tuple[np.ndarray, ...] = ()
    photo_K: np.ndarray | None = None

    @property
    def n_views(self) -> int:
        return int(self.images.shape[0])


def _image_files(folder: Path) -> list[Path]:
    return sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
                   and not p.name.startswith(".")), key=lambda p: p.name)


def _find_images(folder: Path) -> list[Path]:
    """Images directly in ``folder``, else in ``folder/images`` (nerfstudio / COLMAP layout)."""
    files = _image_files(folder)
    if not files and (folder / "images").is_dir():
        files = _image_files(folder / "images")
    return files


def _find_cameras(folder: Path, image_size) -> CameraSet | None:
    if (folder / "transforms.json").is_file():
        return read_transforms_json(folder / "transforms.json", image_size=image_size)
    for d in (folder, folder / "sparse" / "0", folder / "sparse", folder / "colmap"):
        if (d / "cameras.txt").is_file() and (d / "images.txt").is_file():
            return read_colmap_text(d)
    return None


def load_scene_folder(path, size: tuple[int, int] = (64, 64)) -> FolderScene:
    """Load a folder of photos (.png/.jpg/.jpeg, any size) as one scene at model resolution.

    Images are taken from ``path`` or, if it holds none, from ``path/images``, sorted by file
    name. Cameras are read from ``path/transforms.json`` or COLMAP text files (``path``,
    ``path/sparse/0``, ``path/sparse`` or ``path/colmap``) when present; every image must then
    have a camera. Raises ``InputError`` (folder, cameras) or ``ImageError`` (a photo), naming the
    file.
    """
    folder = Path(path)
    if not folder.is_dir():
        raise InputError(f"path: {folder} is not a folder")
    height, width = int(size[0]), int(size[1])
    files = _find_images(folder)
    if not files:
        raise InputError(f"{folder}: no images ({', '.join(IMAGE_SUFFIXES)}) in the folder or in "
                         "its images/ subfolder")
    names = tuple(p.relative_to(folder).as_posix() for p in files)
    cams = _find_cameras(folder, _image_size_of(folder, names))
    images, crops, Ks, poses, photos, photo_Ks = [], [], [], [], [], []
    for p, name in zip(files, names):
        img = load_image(p, name=str(p))
        out, plan = fit_to_model(img, height, width)
        images.append(out)
        photos.append(img)
        crops.append(plan)
        if cams is None:
            continue
        K, pose = _photo_camera(cams, p, name, img.shape[:2])
        Ks.append(plan.adjust_intrinsics(K))
        photo_Ks.append(K)
        poses.append(pose)
    return FolderScene(
        images=np.stack(images), world_from_cam=np.stack(poses) if cams is not None else None,
        K=np.stack(Ks) if cams is not None else None, names=names, crops=tuple(crops),
        meta={"path": str(folder), "camera_source": cams.source if cams is not None else None},
        photos=tuple(photos), photo_K=np.stack(photo_Ks) if cams is not None else None)


def _image_size_of(folder: Path, names: tuple[str, ...]):
    """``image_size(file_path) -> (h, w)`` of an image a camera file of ``folder`` names without
    giving its size (instant-ngp): the file itself, or the image of ``names`` of that stem."""
    def image_size(file_path: str) -> tuple[int, int]:
        from PIL import Image

        cands = [folder / file_path, folder / (file_path + ".png")]
        for c in cands:
            if c.is_file():
                try:
                    with Image.open(c) as im:
                        return im.height, im.width
                except OSError as e:
                    raise ImageError(f"{c}: not a readable image ({e})") from None
        i = next((k for k, n in enumerate(names) if Path(n).stem == Path(file_path).stem), None)
        if i is None:
            raise InputError(f"{folder}: camera file names {file_path!r}, which is not in the folder")
        return image_size(names[i])

    return image_size


def _photo_camera(cams: CameraSet, p: Path, name: str, photo_size: tuple[int, int]):
    """The camera of photo ``name`` (at ``p``, ``photo_size`` (h, w)) in ``cams`` -> (``K [3, 3]``
    in pixels of the photo, ``world_from_cam [4, 4]``), or ``InputError``."""
    idx = cams.index_of(name)
    if idx is None:
        raise InputError(f"{p}: no camera for this image in {cams.source} "
                         "(or several cameras match its name)")
    K = cams.K[idx].copy()
    ch, cw = (int(x) for x in cams.sizes[idx])
    ih, iw = photo_size
    if (ch, cw) != (ih, iw):
        # Cameras computed on a resized copy of the photo: rescale when the aspect agrees.
        if abs(cw / ch - iw / ih) > 0.01 * (iw / ih):
            raise InputError(f"{p}: image is {iw}x{ih} but {cams.source} describes it as "
                             f"{cw}x{ch} (different aspect ratio)")
        K = np.diag([iw / cw, ih / ch, 1.0]) @ K
    return K, cams.world_from_cam[idx]


def load_dataset_folder(path, size: tuple[int, int] = (64, 64)) -> list[FolderScene]:
    """Every scene folder (a sub-folder holding images) of ``path``, sorted by name."""
    root = Path(path)
    if not root.is_dir():
        raise InputError(f"path: {root} is not a folder")
    scenes = [load_scene_folder(d, size) for d in sorted(p for p in root.iterdir() if p.is_dir())
              if _find_images(d)]
    if not scenes:
        raise InputError(f"{root}: no scene folders (sub-folders with images) inside")
    return scenes
