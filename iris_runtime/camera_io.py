"""Read and write camera files: nerfstudio ``transforms.json`` and COLMAP's text model.

numpy only (the runtime never imports torch). Inside IRIS every camera is OpenCV
(x right, y down, z forward) ``world_from_cam [4, 4]`` plus ``K [3, 3]`` in pixels with pixel
(row i, col j) centred at (j + 0.5, i + 0.5). Both formats below use that same pixel convention,
so only the axes and the direction of the pose change:

- **transforms.json** (nerfstudio / instant-ngp): ``transform_matrix`` is camera-to-world with
  OpenGL camera axes (x right, y up, z backward). ``world_from_cam = transform_matrix @
  diag(1, -1, -1, 1)`` (flip the camera's y and z axes) and back with the same product.
  Intrinsics ``fl_x, fl_y, cx, cy, w, h`` at the top level apply to every frame unless a frame
  gives its own; instant-ngp's ``camera_angle_x`` (horizontal field of view, radians) stands in
  for a missing ``fl_x``.
- **COLMAP text** (``cameras.txt``, ``images.txt``, ``points3D.txt``): ``images.txt`` holds
  ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` where (qvec, tvec) map world to camera:
  ``x_cam = R(q) x_world + t``; the camera axes are already OpenCV's.

Distortion coefficients are ignored (with a warning) because IRIS models pinhole cameras only.
Poses and intrinsics are checked by ``iris_runtime.validation`` (one tolerance each): the writers
take what ``check_world_from_cam`` / ``check_intrinsics`` accept and write it unchanged; the
``transforms.json`` reader snaps a matrix that is rigid only to a few printed decimals to the
nearest rigid transform (``snap_world_from_cam``); COLMAP quaternions are rotations by construction.
All writers write atomically (temporary file in the same directory, then ``os.replace``).
Malformed files raise ``InputError`` naming the file and what was expected.
"""
from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .errors import InputError
from .validation import check_intrinsics, check_world_from_cam, snap_world_from_cam
from .fileio import atomic_write_text, read_json, read_text

__all__ = ["CameraSet", "GL_FROM_CV", "flip_opengl_opencv", "quaternion_from_rotation",
           "rotation_from_quaternion", "read_transforms_json", "write_transforms_json",
           "read_colmap_text", "write_colmap_text", "atomic_write_text", "check_cameras"]

#: diag(1, -1, -1, 1): right-multiplying a camera-to-world pose by it swaps OpenCV <-> OpenGL axes.
GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])

#: COLMAP camera models: number of parameters and where fx, fy, cx, cy sit ("f" models share one
#: focal). Everything after the principal point is distortion, which IRIS ignores.
_COLMAP_MODELS = {
    "SIMPLE_PINHOLE": (3, "f"), "PINHOLE": (4, "fxfy"), "SIMPLE_RADIAL": (4, "f"),
    "RADIAL": (5, "f"), "OPENCV": (8, "fxfy"), "OPENCV_FISHEYE": (8, "fxfy"),
    "FULL_OPENCV": (12, "fxfy"), "FOV": (5, "fxfy"), "SIMPLE_RADIAL_FISHEYE": (4, "f"),
    "RADIAL_FISHEYE": (5, "f"), "THIN_PRISM_FISHEYE": (12, "fxfy"),
}
_FISHEYE = ("FISHEYE", "FOV")


@dataclass(frozen=True)
class CameraSet:
    """Cameras read from a file, in IRIS's convention, in the order the file lists them.

    names:          image names as written in the file (e.g. ``"images/0001.png"``)
    world_from_cam: float64 [V, 4, 4] OpenCV camera-to-world
    K:              float64 [V, 3, 3] pixels of an image of size ``sizes[v]``
    sizes:          int64   [V, 2]    (height, width) the intrinsics refer to
    source:         the file the cameras came from
    """

    names: tuple[str, ...]
    world_from_cam: np.ndarray
    K: np.ndarray
    sizes: np.ndarray
    source: str = ""

    def __len__(self) -> int:
        return len(self.names)

    def index_of(self, name: str) -> int | None:
        """Index of the camera of image ``name``: exact path, then file name, then stem."""
        want = _norm_name(name)
        for key in (lambda s: s, lambda s: s.rsplit("/", 1)[-1],
                    lambda s: s.rsplit("/", 1)[-1].rsplit(".", 1)[0]):
            hits = [i for i, n in enumerate(self.names) if key(_norm_name(n)) == key(want)]
            if len(hits) == 1:
                return hits[0]
            if len(hits) > 1:
                return None                    # ambiguous: refuse rather than guess
        return None


def _norm_name(name: str) -> str:
    s = str(name).replace("\\", "/")
    while s.startswith("./"):
        s = s[2:]
    return s


# ----------------------------------------------------------------------------------------------
# Small maths
# ----------------------------------------------------------------------------------------------

def flip_opengl_opencv(world_from_cam: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world ``[..., 4, 4]`` <-> OpenGL camera-to-world (the map is its own inverse)."""
    return np.asarray(world_from_cam, dtype=np.float64) @ GL_FROM_CV


def rotation_from_quaternion(q: Sequence[float]) -> np.ndarray:
    """Unit quaternion (w, x, y, z) -> rotation ``[3, 3]`` (the quaternion is normalised first)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def quaternion_from_rotation(R: np.ndarray) -> np.ndarray:
    """Rotation ``[3, 3]`` -> unit quaternion (w, x, y, z) with w >= 0.

    Shepperd's method: take the square root of the largest of 4w², 4x², 4y², 4z² so that no
    division by a small number happens (accurate to ~1e-16 for any rotation).
    """
    R = np.asarray(R, dtype=np.float64)
    t = np.trace(R)
    cands = [1 + t, 1 + 2 * R[0, 0] - t, 1 + 2 * R[1, 1] - t, 1 + 2 * R[2, 2] - t]
    k = int(np.argmax(cands))
    s = 2.0 * math.sqrt(max(cands[k], 1e-300))
    if k == 0:
        q = [s / 4, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif k == 1:
        q = [(R[2, 1] - R[1, 2]) / s, s / 4, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif k == 2:
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, s / 4, (R[1, 2] + R[2, 1]) / s]
    else:
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, s / 4]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def check_cameras(world_from_cam, K, size, image_names, what: str = "cameras"
                  ) -> tuple[np.ndarray, np.ndarray, tuple[int, int], list[str]]:
    """Validate writer arguments; returns (world_from_cam [V,4,4], K [V,3,3], (h, w), names).

    ``K`` may be shared ``[3, 3]`` or per view ``[V, 3, 3]``; ``size`` is (height, width).
    Poses: ``validation.check_world_from_cam``; intrinsics: ``validation.check_intrinsics``.
    """
    T = check_world_from_cam(world_from_cam, "world_from_cam", batch=True)
    V = T.shape[0]
    try:
        h, w = (int(size[0]), int(size[1]))
    except (TypeError, ValueError, IndexError):
        raise InputError(f"size: expected (height, width), got {size!r}") from None
    if h <= 0 or w <= 0 or len(size) != 2:
        raise InputError(f"size: expected (height, width) positive ints, got {size!r}")
    Kin = check_intrinsics(K, "K", h, w, views=V)
    names = [str(n) for n in image_names]
    if len(names) != V:
        raise InputError(f"image_names: expected {V} names (one per camera), got {len(names)}")
    if len(set(names)) != V or any(not n or "\n" in n for n in names):
        raise InputError("image_names: expected distinct, non-empty, single-line names")
    return T, Kin, (h, w), names


def _num(x: float) -> str:
    """Shortest text that reads back to the same float64."""
    return repr(float(x))


# ----------------------------------------------------------------------------------------------
# transforms.json
# ----------------------------------------------------------------------------------------------

def write_transforms_json(path, world_from_cam, K, size, image_names) -> Path:
    """Write nerfstudio ``transforms.json`` (OpenGL camera-to-world, pinhole intrinsics).

    world_from_cam: [V, 4, 4] OpenCV camera-to-world; K: [3, 3] shared or [V, 3, 3] per view;
    size: (height, width) of the images K refers to; image_names: V names stored as
    ``file_path``. Shared intrinsics go to the top level, per-view ones into each frame.
    """
    T, Ks, (h, w), names = check_cameras(world_from_cam, K, size, image_names)
    shared = bool(np.all(Ks == Ks[0]))

    def intr(k):
        return {"fl_x": float(k[0, 0]), "fl_y": float(k[1, 1]), "cx": float(k[0, 2]),
                "cy": float(k[1, 2])}

    doc: dict = {"camera_model": "PINHOLE"}
    if shared:
        doc.update(intr(Ks[0]))
    doc.update({"w": w, "h": h})
    frames = []
    for v in range(T.shape[0]):
        fr = {"file_path": names[v], "transform_matrix": flip_opengl_opencv(T[v]).tolist()}
        if not shared:
            fr.update(intr(Ks[v]))
        frames.append(fr)
    doc["frames"] = frames
    path = Path(path)
    atomic_write_text(path, json.dumps(doc, indent=2) + "\n")
    return path


def read_transforms_json(path, image_size: Callable[[str], tuple[int, int]] | None = None
                         ) -> CameraSet:
    """Read nerfstudio / instant-ngp ``transforms.json`` into a ``CameraSet`` (OpenCV axes).

    ``image_size(file_path) -> (height, width)`` is asked only when the file gives no ``w``/``h``
    (instant-ngp's Blender scenes); without it such a file is refused. A missing ``cx``/``cy``
    means the image centre.
    """
    path = Path(path)
    doc = read_json(path)
    frames = doc.get("frames")
    if not isinstance(frames, list) or not frames:
        raise InputError(f"{path}: expected a non-empty 'frames' list")
    names, poses, Ks, sizes = [], [], [], []
    ignored: set[str] = set()
    model = str(doc.get("camera_model", "OPENCV")).upper()
    for i, fr in enumerate(frames):
        where = f"{path}: frames[{i}]"
        if not isinstance(fr, dict) or not isinstance(fr.get("file_path"), str):
            raise InputError(f"{where}: expected an object with a 'file_path' string")
        M = _matrix(fr.get("transform_matrix"), f"{where}.transform_matrix")
        get = lambda k: fr.get(k, doc.get(k))  # noqa: E731  per-frame value overrides top level
        w, h = get("w"), get("h")
        if w is None or h is None:
            if image_size is None:
                raise InputError(f"{where}: no image size ('w', 'h') in the file")
            h, w = image_size(fr["file_path"])
        w, h = _pos(w, f"{where}.w"), _pos(h, f"{where}.h")
        fx, fy = get("fl_x"), get("fl_y")
        if fx is None and get("camera_angle_x") is not None:
            fx = 0.5 * w / math.tan(0.5 * _float(get("camera_angle_x"), f"{where}.camera_angle_x"))
        if fy is None and get("camera_angle_y") is not None:
            fy = 0.5 * h / math.tan(0.5 * _float(get("camera_angle_y"), f"{where}.camera_angle_y"))
        if fx is None and fy is None:
            raise InputError(f"{where}: no focal length ('fl_x'/'fl_y' or 'camera_angle_x')")
        fx = _pos(fx if fx is not None else fy, f"{where}.fl_x", integer=False)
        fy = _pos(fy if fy is not None else fx, f"{where}.fl_y", integer=False)
        cx = _float(get("cx"), f"{where}.cx") if get("cx") is not None else w / 2.0
        cy = _float(get("cy"), f"{where}.cy") if get("cy") is not None else h / 2.0
        for k in ("k1", "k2", "k3", "k4", "p1", "p2"):
            if get(k) not in (None, 0, 0.0):
                ignored.add(k)
        names.append(fr["file_path"])
        poses.append(M @ GL_FROM_CV)
        Ks.append([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        sizes.append((h, w))
    if ignored or any(s in model for s in _FISHEYE) or model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
        warnings.warn(f"{path}: camera model {model!r}, distortion {sorted(ignored)} ignored: IRIS "
                      "treats every camera as a pinhole", stacklevel=2)
    return CameraSet(tuple(names), np.asarray(poses), np.asarray(Ks, dtype=np.float64),
                     np.asarray(sizes, dtype=np.int64), str(path))






def _matrix(m, where: str) -> np.ndarray:
    """A camera-to-world 4x4 (or 3x4) from a text file, snapped to rigid within
    ``validation.SNAP_ATOL`` (``snap_world_from_cam``)."""
    try:
        M = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{where}: expected a 4x4 (or 3x4) matrix of numbers") from None
    if M.shape == (3, 4):
        M = np.vstack([M, [0.0, 0.0, 0.0, 1.0]])
    if M.shape != (4, 4) or not np.all(np.isfinite(M)):
        raise InputError(f"{where}: expected a finite 4x4 (or 3x4) matrix, got shape {M.shape}")
    return snap_world_from_cam(M, where)


def _float(x, where: str) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise InputError(f"{where}: expected a number, got {x!r}") from None
    if not math.isfinite(v):
        raise InputError(f"{where}: expected a finite number, got {x!r}")
    return v


def _pos(x, where: str, integer: bool = True):
    v = _float(x, where)
    if v <= 0 or (integer and v != int(v)):
        raise InputError(f"{where}: expected a positive {'integer' if integer else 'number'}, got {x!r}")
    return int(v) if integer else v


# ----------------------------------------------------------------------------------------------
# COLMAP text model
# ----------------------------------------------------------------------------------------------

def write_colmap_text(directory, world_from_cam, K, size, image_names) -> Path:
    """Write ``cameras.txt``, ``images.txt`` and an empty ``points3D.txt`` into ``directory``.

    Shared ``K [3, 3]`` -> one PINHOLE camera; per-view ``K [V, 3, 3]`` -> one camera per image.
    Poses are stored as COLMAP wants them: world-to-camera rotation (qw, qx, qy, qz) and
    translation, with image ids 1..V in the given order.
    """
    T, Ks, (h, w), names = check_cameras(world_from_cam, K, size, image_names)
    if any(any(c.isspace() for c in n) for n in names):
        raise InputError("image_names: COLMAP text names cannot contain white space")
    shared = bool(np.all(Ks == Ks[0]))
    V = T.shape[0]
    cam_ids = [1] * V if shared else list(range(1, V + 1))
    cams = ["# Camera list with one line of data per camera:",
            "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
            f"# Number of cameras: {1 if shared else V}"]
    for v in (range(1) if shared else range(V)):
        k = Ks[v]
        cams.append(f"{cam_ids[v]} PINHOLE {w} {h} {_num(k[0, 0])} {_num(k[1, 1])} "
                    f"{_num(k[0, 2])} {_num(k[1, 2])}")
    imgs = ["# Image list with two lines of data per image:",
            "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
            "#   POINTS2D[] as (X, Y, POINT3D_ID)",
            f"# Number of images: {V}, mean observations per image: 0"]
    for v in range(V):
        R_cam_from_world = T[v, :3, :3].T
        t_cam_from_world = -R_cam_from_world @ T[v, :3, 3]
        q = quaternion_from_rotation(R_cam_from_world)
        imgs.append(f"{v + 1} " + " ".join(_num(x) for x in (*q, *t_cam_from_world)) + f" {cam_ids[v]} {names[v]}")
        imgs.append("")                       # no 2D points
    pts = ["# 3D point list with one line of data per point:",
           "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
           "# Number of points: 0, mean track length: 0"]
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    atomic_write_text(d / "cameras.txt", "\n".join(cams) + "\n")
    atomic_write_text(d / "images.txt", "\n".join(imgs) + "\n")
    atomic_write_text(d / "points3D.txt", "\n".join(pts) + "\n")
    return d


def read_colmap_text(directory) -> CameraSet:
    """Read ``cameras.txt`` + ``images.txt`` from ``directory`` into a ``CameraSet`` (file order)."""
    d = Path(directory)
    cam_path, img_path = d / "cameras.txt", d / "images.txt"
    cameras = {}
    ignored = set()
    for lineno, line in _data_lines(cam_path):
        tok = line.split()
        where = f"{cam_path}:{lineno}"
        if len(tok) < 4:
            raise InputError(f"{where}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...'")
        model = tok[1].upper()
        if model not in _COLMAP_MODELS:
            raise InputError(f"{where}: unknown camera model {tok[1]!r} "
                             f"(expected one of {', '.join(_COLMAP_MODELS)})")
        n, kind = _COLMAP_MODELS[model]
        params = [_float(p, where) for p in tok[4:]]
        if len(params) != n:
            raise InputError(f"{where}: model {model} needs {n} parameters, got {len(params)}")
        w, h = _pos(tok[2], f"{where} WIDTH"), _pos(tok[3], f"{where} HEIGHT")
        if kind == "f":
            fx = fy = params[0]
            cx, cy = params[1], params[2]
            dist = params[3:]
        else:
            fx, fy, cx, cy = params[:4]
            dist = params[4:]
        if fx <= 0 or fy <= 0:
            raise InputError(f"{where}: focal length must be positive")
        if any(x != 0 for x in dist) or any(s in model for s in _FISHEYE):
            ignored.add(model)
        cameras[_int(tok[0], where)] = (np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], float), (h, w))
    if ignored:
        warnings.warn(f"{cam_path}: distortion of camera model(s) {sorted(ignored)} ignored: IRIS "
                      "treats every camera as a pinhole", stacklevel=2)
    names, poses, Ks, sizes = [], [], [], []
    for lineno, line in _data_lines(img_path, keep_empty=True):
        tok = line.split()
        if not _is_image_header(tok):
            continue                           # a POINTS2D line (or empty)
        where = f"{img_path}:{lineno}"
        q = np.array([float(x) for x in tok[1:5]])
        t = np.array([float(x) for x in tok[5:8]])
        if not np.all(np.isfinite(q)) or not np.all(np.isfinite(t)) or np.linalg.norm(q) < 1e-12:
            raise InputError(f"{where}: expected a finite non-zero quaternion and translation")
        cam_id = int(tok[8])
        if cam_id not in cameras:
            raise InputError(f"{where}: CAMERA_ID {cam_id} is not in {cam_path}")
        R_cam_from_world = rotation_from_quaternion(q)
        T = np.eye(4)
        T[:3, :3] = R_cam_from_world.T
        T[:3, 3] = -R_cam_from_world.T @ t
        names.append(" ".join(tok[9:]))
        poses.append(T)
        Ks.append(cameras[cam_id][0])
        sizes.append(cameras[cam_id][1])
    if not names:
        raise InputError(f"{img_path}: no image lines "
                         "('IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME')")
    return CameraSet(tuple(names), np.asarray(poses), np.asarray(Ks), np.asarray(sizes, np.int64),
                     str(d))


def _data_lines(path: Path, keep_empty: bool = False):
    text = read_text(path)
    for i, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if s.startswith("#") or (not s and not keep_empty):
            continue
        yield i, s


def _int(x: str, where: str) -> int:
    try:
        return int(x)
    except ValueError:
        raise InputError(f"{where}: expected an integer id, got {x!r}") from None


def _is_image_header(tok: list[str]) -> bool:
    """``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME``; a POINTS2D line is all numbers."""
    if len(tok) < 10:
        return False
    try:
        int(tok[0])
        [float(x) for x in tok[1:8]]
        int(tok[8])
    except ValueError:
        return False
    try:
        [float(x) for x in tok[9:]]
        return False                           # all numeric: a POINTS2D line
    except ValueError:
        return True
