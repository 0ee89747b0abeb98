"""Build the real evaluation sets of docs/REAL.md from Debian packages, reproducibly.

    apt-get install -y visp-images-data
    python scripts/real_sets.py --out data/real              # every set, one folder each
    python scripts/real_sets.py --out data/real --sets castle --force
    python scripts/real_sets.py --check                      # the motion check of every candidate
    iris-eval MODEL data/real/castle --cameras true          # then evaluate a set

Each set is a folder of scene folders that ``iris-eval`` (``iris_train.data.load_dataset_folder``)
reads: one PNG per frame named by its zero-padded source frame number (file-name order = the
trajectory), 3-channel RGB (the ViSP images are grey: the grey value is repeated in R, G and B),
and, where the source has true poses, the cameras as nerfstudio ``transforms.json``
(``iris_runtime.camera_io.write_transforms_json``). ``OUT/sets.json`` records the package and
its version, the source files and the frame list of every scene. The whole of ``--out`` is
written into a temporary sibling folder and renamed into place, so a reader never sees half a
set; an existing ``--out`` is replaced only with ``--force``.

The sets (source: Debian ``visp-images-data``, ``/usr/share/visp-images-data/ViSP-images``):

- ``cube``: ``cube/image.NNNN.pgm``, a real camera moving over a poster with a cube on it, 384x288.
  Frames 17-70 move, 0-16 and 71-79 are still (``--check``); 4 scenes of 8 frames starting at
  18, 33, 48, 20 with steps 2, 2, 3, 4. No poses.
- ``castle``: ``mbt-depth/Castle-simu``, a Blender render of a castle and a cube, 640x480, with
  the true pose of every frame in ``CameraPose/Camera_NNN.txt``. Those 4x4 matrices are
  **cMo** (object-to-camera, OpenCV axes): with them the essential matrix of SIFT matches
  between frames 1-6, 1-11, 21-31, 30-40 leaves a median epipolar distance of 0.08-0.42 px,
  read as oMc 14-119 px (``castle_pose_check``; tests/test_real_sets.py checks it on the
  package). K: fx = fy = 700 at 640x480 and the principal point (u0, v0) of
  ``Config/chateau.xml``, which counts pixel centres from 0, so cx = u0 + 0.5 in IRIS's pixel
  convention. Two scenes: frames 1, 6, ..., 36 (8 frames) and 21, 23, ..., 39 (10 frames:
  ``iris-eval`` keeps 8 evenly, 21 23 27 29 31 33 37 39).
- ``castel``: ``mbt-depth/castel/castel/image_NNNN.pgm``, a real camera moving around a real
  castle model on a table (parallax between the towers and the room behind), 640x480, 30 frames
  of which 0-2 are still (``--check``); one scene of 8 frames spread over the moving ones (2, 6,
  10, 14, 17, 21, 25, 29). No poses (the package holds only the tracker's initial pose). The
  camera moves little: at the model's 64x64 neighbouring frames differ by about a pixel, so the
  best reference photo is hard to beat there (docs/REAL.md): a check of sharpness, not a bar.

Other sequences looked at and why they are not sets: ``CANDIDATES`` and docs/REAL.md.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from iris_runtime.camera_io import write_transforms_json  # noqa: E402
from iris_runtime.errors import InputError  # noqa: E402
from iris_runtime.fileio import atomic_write_json  # noqa: E402

#: Where Debian's visp-images-data puts the ViSP images.
VISP_ROOT = Path("/usr/share/visp-images-data/ViSP-images")
PACKAGE = "visp-images-data"
#: Castle-simu's focal length in pixels (fx = fy) at 640x480.
CASTLE_FOCAL = 700.0


@dataclass(frozen=True)
class SceneSpec:
    name: str
    frames: tuple[int, ...]


@dataclass(frozen=True)
class SetSpec:
    """One evaluation set: ``pattern`` (relative to the ViSP root) formatted with a frame number
    gives a source image; ``poses``: "castle" when true poses exist, else None."""
    name: str
    description: str
    pattern: str
    scenes: tuple[SceneSpec, ...]
    poses: str | None = None
    size: tuple[int, int] = field(default=(0, 0))      # (H, W) of the source images


def _strided_scenes(starts_steps) -> tuple[SceneSpec, ...]:
    """8-frame scenes ``start, start + step, ...``, named with their position first so that the
    folders sort in the listed order (a scene's index fixes its Rand permutation)."""
    return tuple(SceneSpec(f"{n}_start{s:02d}_step{k}", tuple(s + k * i for i in range(8)))
                 for n, (s, k) in enumerate(starts_steps))


SETS = {
    "cube": SetSpec("cube", "ViSP cube: a real camera over a poster and a cube (grey, 384x288)",
                    "cube/image.{:04d}.pgm", _strided_scenes(((18, 2), (33, 2), (48, 3), (20, 4))),
                    None, (288, 384)),
    "castle": SetSpec("castle", "ViSP Castle-simu: a Blender render with true poses (grey, 640x480)",
                      "mbt-depth/Castle-simu/Images/Image_{:04d}.pgm",
                      (SceneSpec("0_frames01-36_step5", tuple(range(1, 37, 5))),
                       SceneSpec("1_frames21-39_step2", tuple(range(21, 40, 2)))), "castle", (480, 640)),
    "castel": SetSpec("castel", "ViSP castel: a real camera moving around a real castle model "
                                "(grey, 640x480)", "mbt-depth/castel/castel/image_{:04d}.pgm",
                      (SceneSpec("0_frames02-29", (2, 6, 10, 14, 17, 21, 25, 29)),), None, (480, 640)),
}


# ----------------------------------------------------------------------------------------------
# Reading the sources
# ----------------------------------------------------------------------------------------------

def read_grey_as_rgb(path: Path) -> np.ndarray:
    """A grey image file -> uint8 [H, W, 3] with the grey value in R, G and B."""
    grey = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if grey is None:
        raise InputError(f"{path}: not a readable image")
    return np.repeat(grey[:, :, None], 3, axis=2)


def read_visp_intrinsics(xml_path: Path) -> np.ndarray:
    """K [3, 3] (IRIS pixel convention, centres at +0.5) from a ViSP tracker config's
    ``<camera><px><py><u0><v0>``, whose pixel centres are at integers."""
    try:
        cam = ET.parse(xml_path).getroot().find("camera")
        px, py, u0, v0 = (float(cam.find(k).text) for k in ("px", "py", "u0", "v0"))
    except (OSError, ET.ParseError, AttributeError, TypeError, ValueError) as e:
        raise InputError(f"{xml_path}: expected a ViSP config with <camera> px, py, u0, v0 "
                         f"({type(e).__name__}: {e})") from None
    return np.array([[px, 0.0, u0 + 0.5], [0.0, py, v0 + 0.5], [0.0, 0.0, 1.0]])


def read_castle_pose(path: Path) -> np.ndarray:
    """world_from_cam [4, 4] (OpenCV axes) of one ``CameraPose/Camera_NNN.txt``, which holds
    cMo, the object (world) to camera transform: its inverse."""
    try:
        cMo = np.loadtxt(path, dtype=np.float64)
    except (OSError, ValueError) as e:
        raise InputError(f"{path}: expected a 4x4 matrix ({e})") from None
    if cMo.shape != (4, 4) or not np.isfinite(cMo).all():
        raise InputError(f"{path}: expected a finite 4x4 matrix, got shape {cMo.shape}")
    return np.linalg.inv(cMo)


def castle_cameras(root: Path, frames) -> tuple[np.ndarray, np.ndarray]:
    """(world_from_cam [N, 4, 4], K [3, 3]) of Castle-simu ``frames``. fx = fy =
    ``CASTLE_FOCAL``, as the config says; the principal point is the config's."""
    base = root / "mbt-depth" / "Castle-simu"
    K = read_visp_intrinsics(base / "Config" / "chateau.xml")
    if not (K[0, 0] == K[1, 1] == CASTLE_FOCAL):
        raise InputError(f"{base / 'Config' / 'chateau.xml'}: expected px = py = {CASTLE_FOCAL}")
    poses = np.stack([read_castle_pose(base / "CameraPose" / f"Camera_{f:03d}.txt") for f in frames])
    return poses, K


def castle_pose_check(root: Path, pairs=((1, 6), (1, 11), (21, 31), (30, 40))) -> dict:
    """Median epipolar distance (pixels) of RANSAC-filtered SIFT matches between Castle-simu
    frame pairs under the poses read as cMo and read as oMc: which convention the files hold."""
    base = root / "mbt-depth" / "Castle-simu"
    K = read_visp_intrinsics(base / "Config" / "chateau.xml")
    Ki = np.linalg.inv(K)
    sift = cv2.SIFT_create()
    out = {}
    for a, b in pairs:
        feats = [sift.detectAndCompute(cv2.imread(str(base / "Images" / f"Image_{f:04d}.pgm"), 0), None)
                 for f in (a, b)]
        knn = cv2.BFMatcher().knnMatch(feats[0][1], feats[1][1], k=2)
        good = [m for m, n in knn if m.distance < 0.7 * n.distance]
        p = np.float64([feats[0][0][m.queryIdx].pt for m in good]) + 0.5
        q = np.float64([feats[1][0][m.trainIdx].pt for m in good]) + 0.5
        _, inl = cv2.findFundamentalMat(p, q, cv2.FM_RANSAC, 1.0, 0.999)
        p, q = p[inl.ravel() > 0], q[inl.ravel() > 0]
        cMo = [np.loadtxt(base / "CameraPose" / f"Camera_{f:03d}.txt") for f in (a, b)]
        dists = {}
        for name, cam_from_world in (("cMo", cMo), ("oMc", [np.linalg.inv(m) for m in cMo])):
            T = cam_from_world[1] @ np.linalg.inv(cam_from_world[0])        # camera a -> b
            t = T[:3, 3]
            E = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]]) @ T[:3, :3]
            lines = np.c_[p, np.ones(len(p))] @ (Ki.T @ E @ Ki).T
            d = np.abs((np.c_[q, np.ones(len(q))] * lines).sum(1)) / np.hypot(lines[:, 0], lines[:, 1])
            dists[name] = float(np.median(d))
        out[f"{a}-{b}"] = {"matches": int(len(p)), **dists}
    return out


# ----------------------------------------------------------------------------------------------
# Building
# ----------------------------------------------------------------------------------------------

def package_version() -> str | None:
    try:
        out = subprocess.run(["dpkg-query", "-W", "-f=${Version}", PACKAGE], capture_output=True,
                             text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None


def check_root(root: Path) -> Path:
    root = Path(root)
    if not (root / "cube").is_dir() and not (root / "mbt-depth").is_dir():
        raise InputError(f"--visp {root}: not a ViSP-images folder (install it with "
                         f"`apt-get install -y {PACKAGE}`)")
    return root


def build_set(spec: SetSpec, root: Path, out: Path) -> dict:
    """Write ``spec``'s scene folders under ``out / spec.name``; returns its sets.json entry."""
    entry = {"description": spec.description, "cameras": "transforms.json" if spec.poses else None,
             "scenes": {}}
    for scene in spec.scenes:
        folder = out / spec.name / scene.name
        folder.mkdir(parents=True)
        files = [root / spec.pattern.format(f) for f in scene.frames]
        missing = [str(f) for f in files if not f.is_file()]
        if missing:
            raise InputError(f"{spec.name}/{scene.name}: missing source frames {missing[:3]} "
                             f"(is {PACKAGE} complete?)")
        names = [f"{f:04d}.png" for f in scene.frames]
        for src, name in zip(files, names):
            image = read_grey_as_rgb(src)
            if spec.size != (0, 0) and image.shape[:2] != spec.size:
                raise InputError(f"{src}: expected {spec.size[1]}x{spec.size[0]}, got "
                                 f"{image.shape[1]}x{image.shape[0]}")
            if not cv2.imwrite(str(folder / name), image[:, :, ::-1]):
                raise OSError(f"{folder / name}: could not be written")
        if spec.poses == "castle":
            poses, K = castle_cameras(root, scene.frames)
            write_transforms_json(folder / "transforms.json", poses, K, spec.size, names)
        entry["scenes"][scene.name] = {"frames": list(scene.frames),
                                       "files": [str(f.relative_to(root)) for f in files]}
    return entry


def build(out: Path, root: Path = VISP_ROOT, sets=tuple(SETS), force: bool = False) -> dict:
    """Build ``sets`` from the ViSP images under ``root`` into ``out`` (replaced as a whole, only
    with ``force``); returns the sets.json document."""
    root, out = check_root(root), Path(out)
    unknown = [s for s in sets if s not in SETS]
    if unknown or not sets:
        raise InputError(f"--sets: expected names from {list(SETS)}, got {list(sets)}")
    if out.exists() and not force:
        raise InputError(f"--out {out}: exists (use --force to replace it)")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        doc = {"package": PACKAGE, "version": package_version(), "root": str(root),
               "rgb_from_grey": "the grey value repeated in R, G and B",
               "sets": {name: build_set(SETS[name], root, tmp) for name in sets}}
        atomic_write_json(tmp / "sets.json", doc)
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old.", dir=out.parent))
            os.replace(out, old / out.name)
            os.replace(tmp, out)
            shutil.rmtree(old)
        else:
            os.replace(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    return doc


# ----------------------------------------------------------------------------------------------
# Does the camera move over a still scene? (docs/ARCHITECTURE.md, "Conventions")
# ----------------------------------------------------------------------------------------------

#: Width the frames are brought to for the check; share of the width that counts as border.
CHECK_WIDTH = 256
BORDER = 0.12
#: Consecutive frames whose median flow is below this (pixels at CHECK_WIDTH) are still.
STILL_FLOW = 0.05


def _flow(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(a, b, None)


def _rigid_fraction(a: np.ndarray, b: np.ndarray, flow: np.ndarray) -> float | None:
    """Share of the textured, forward-backward-consistent flow vectors that one fundamental
    matrix explains within 1 px (MAGSAC): one rigid scene seen by a moving camera gives ~1,
    a second motion (a hand, a held object, a cut) leaves its pixels out."""
    h, w = a.shape
    ys, xs = np.mgrid[2:h - 2:3, 2:w - 2:3]
    p = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float32)
    f = flow[ys.ravel(), xs.ravel()]
    q = p + f
    back = cv2.remap(_flow(b, a), q[:, :1], q[:, 1:], cv2.INTER_LINEAR).reshape(-1, 2)
    texture = cv2.cornerMinEigenVal(a, 3, ksize=3)[ys.ravel(), xs.ravel()]
    ok = (np.linalg.norm(f + back, axis=1) < 0.5) & (texture > 1e-4) \
        & (q[:, 0] >= 0) & (q[:, 1] >= 0) & (q[:, 0] < w) & (q[:, 1] < h)
    if ok.sum() < 50:
        return None
    _, inl = cv2.findFundamentalMat(p[ok], q[ok], cv2.USAC_MAGSAC, 1.0, 0.999)
    return None if inl is None else float(inl.mean())


def motion_check(frames: list[np.ndarray], gap: int | None = None) -> dict:
    """Measurements of a sequence of grey uint8 frames [H, W]:

    still:        indices i where the camera does not move between frames i and i + 1 (median
                  flow over the whole frame < ``STILL_FLOW``: repeated frames, or a still camera
                  watching something small move)
    border_flow:  median over frame pairs ``gap`` apart (default: an eighth of the sequence) of
                  the median flow on the image border (``BORDER`` of each side), % of the width:
                  a camera that moves moves the border, an object in front of a still camera
                  does not
    rigid:        median over those pairs of ``_rigid_fraction``
    """
    if len(frames) < 2:
        raise InputError(f"frames: expected at least 2, got {len(frames)}")
    h, w = frames[0].shape
    size = (CHECK_WIDTH, max(16, round(h * CHECK_WIDTH / w)))
    small = [cv2.resize(f, size, interpolation=cv2.INTER_AREA) for f in frames]
    H, W = small[0].shape
    by, bx = max(1, round(BORDER * H)), max(1, round(BORDER * W))
    border = np.ones((H, W), bool)
    border[by:H - by, bx:W - bx] = False
    still = [i for i in range(len(small) - 1)
             if np.median(np.linalg.norm(_flow(small[i], small[i + 1]), axis=2)) < STILL_FLOW]
    gap = max(1, len(small) // 8) if gap is None else gap
    pairs = [(i, i + gap) for i in range(0, len(small) - gap, max(1, gap // 2))]
    moves, rigid = [], []
    for i, j in pairs:
        flow = _flow(small[i], small[j])
        moves.append(100.0 * float(np.median(np.linalg.norm(flow[border], axis=1))) / W)
        r = _rigid_fraction(small[i], small[j], flow)
        if r is not None:
            rigid.append(r)
    return {"frames": len(frames), "gap": gap, "still": still,
            "border_flow": float(np.median(moves)),
            "rigid": float(np.median(rigid)) if rigid else None}


def _read_video(path: Path) -> list[np.ndarray]:
    cap = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
    cap.release()
    return frames


def _read_glob(folder: Path, pattern: str) -> list[np.ndarray]:
    return [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in sorted(folder.glob(pattern))]


OPENCV_DATA = Path("/usr/share/doc/opencv-doc/examples/data")
#: Every sequence looked at: name -> (package, how to read it, what was decided and why). The
#: verdicts rest on ``--check``'s figures (docs/REAL.md) and on looking at the frames.
CANDIDATES = {
    "visp cube (frames 17-70)": (PACKAGE, lambda r: _read_glob(r / "cube", "image.*.pgm")[17:71],
                                 "set 'cube'"),
    "visp cube (all 80)": (PACKAGE, lambda r: _read_glob(r / "cube", "image.*.pgm"),
                           "still at 0-16 and 71-79: only 17-70 is used"),
    "visp Castle-simu": (PACKAGE, lambda r: _read_glob(r / "mbt-depth/Castle-simu/Images", "*.pgm"),
                         "set 'castle'"),
    "visp mbt-depth/castel": (PACKAGE, lambda r: _read_glob(r / "mbt-depth/castel/castel", "*.pgm"),
                              "set 'castel' (frames 2-29; small motion)"),
    "visp mbt/cube": (PACKAGE, lambda r: _read_glob(r / "mbt/cube", "*.pgm"),
                      "rejected: still camera (the border does not move), a hand moves the cube"),
    "visp mire-2": (PACKAGE, lambda r: _read_glob(r / "mire-2", "*.pgm"),
                    "rejected: still camera, the target box is moved by hand"),
    "visp ellipse-1": (PACKAGE, lambda r: _read_glob(r / "ellipse-1", "*.pgm"),
                       "rejected: a flat white shape on a flat black ground, nothing to match"),
    "visp line": (PACKAGE, lambda r: _read_glob(r / "line", "*.pgm"),
                  "rejected: a flat white shape on a flat black ground, nothing to match"),
    "visp video/cube.mpeg": (PACKAGE, lambda r: _read_video(r / "video/cube.mpeg"),
                             "rejected: the cube sequence again, as a video"),
    "opencv tree.avi": ("opencv-doc", lambda r: _read_video(OPENCV_DATA / "tree.avi"),
                        "rejected: still camera, a swaying tree and a passing hand"),
    "opencv vtest.avi": ("opencv-doc", lambda r: _read_video(OPENCV_DATA / "vtest.avi"),
                         "rejected: still camera, people walking"),
    "opencv Megamind.avi": ("opencv-doc", lambda r: _read_video(OPENCV_DATA / "Megamind.avi"),
                            "rejected: an animated film, moving characters and cuts"),
}


def check_candidates(root: Path = VISP_ROOT, names=None) -> dict:
    """``motion_check`` of every candidate whose package is installed (others: "not installed")."""
    out = {}
    for name, (package, read, verdict) in CANDIDATES.items():
        if names and name not in names:
            continue
        try:
            frames = read(Path(root))
        except (OSError, cv2.error):
            frames = []
        if len(frames) < 2 or any(f is None for f in frames):
            out[name] = {"package": package, "result": "not installed or unreadable"}
            continue
        out[name] = {"package": package, **motion_check(frames), "verdict": verdict}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="Sets: " + ", ".join(f"{k} ({v.description})"
                                                             for k, v in SETS.items()))
    ap.add_argument("--out", type=Path, help="folder to write the sets into (one sub-folder each)")
    ap.add_argument("--sets", default=",".join(SETS), help=f"comma-separated (default: all of {list(SETS)})")
    ap.add_argument("--visp", type=Path, default=VISP_ROOT, help=f"ViSP-images folder (default {VISP_ROOT})")
    ap.add_argument("--force", action="store_true", help="replace an existing --out")
    ap.add_argument("--check", action="store_true",
                    help="measure camera motion and rigidity of every candidate sequence instead")
    ap.add_argument("--json", type=Path, help="with --check: write the measurements here")
    args = ap.parse_args(argv)
    try:
        if args.check:
            res = check_candidates(args.visp)
            print(f"{'candidate':<28} {'frames':>6} {'gap':>4} {'still pairs':>11} "
                  f"{'border flow %W':>14} {'rigid':>6}  verdict")
            for name, r in res.items():
                if "frames" not in r:
                    print(f"{name:<28} {r['result']}")
                    continue
                rigid = "-" if r["rigid"] is None else f"{r['rigid']:.3f}"
                print(f"{name:<28} {r['frames']:>6} {r['gap']:>4} {len(r['still']):>11} "
                      f"{r['border_flow']:>14.2f} {rigid:>6}  {r['verdict']}")
            pose = castle_pose_check(check_root(args.visp))
            for pair, r in pose.items():
                print(f"castle poses, frames {pair}: {r['matches']} SIFT matches, median epipolar "
                      f"distance {r['cMo']:.3f} px as cMo, {r['oMc']:.3f} px as oMc")
            if args.json:
                atomic_write_json(args.json, {"candidates": res, "castle_poses": pose})
            return 0
        if args.out is None:
            ap.error("--out is needed (or --check)")
        sets = tuple(s.strip() for s in args.sets.split(",") if s.strip())
        doc = build(args.out, args.visp, sets, force=args.force)
    except InputError as exc:
        print(f"real_sets: error: {exc}", file=sys.stderr)
        return 2
    for name, entry in doc["sets"].items():
        for scene, s in entry["scenes"].items():
            cams = f", cameras {entry['cameras']}" if entry["cameras"] else ""
            print(f"{args.out / name / scene}: frames {s['frames']}{cams}")
    print(f"wrote {args.out / 'sets.json'} ({doc['package']} {doc['version']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
