"""Textures: photographs that registry packages ship, and procedural patterns (nothing downloaded).

``make_texture`` is the classic kinds' texture (scikit-image's photos only; unchanged so that their
scenes stay bitwise the same). ``make_photo_texture`` is the capture kinds': a larger pool of real
photographs from scikit-image, Debian's ``opencv-doc`` sample data and ViSP's
``visp-images-data`` (single photos only: ViSP's image *sequences* are evaluation sets and are
never used as textures), more pattern families, and optional grey. The photo files must be there
(the pool decides the scenes): a missing one raises with the package to install.
"""
from __future__ import annotations

import functools
from pathlib import Path

import cv2
import numpy as np

PHOTO_NAMES_V1 = ("astronaut", "coffee", "chelsea", "rocket", "colorwheel", "immunohistochemistry",
                "brick", "grass", "gravel", "camera", "moon", "text", "page", "clock", "coins")
TEXTURE_SIZE = 128


@functools.lru_cache(maxsize=1)
def photos_v1() -> tuple[np.ndarray, ...]:
    """The bundled photos as uint8 RGB, shrunk so that their short side is 256 (load once)."""
    import skimage.data

    out = []
    for name in PHOTO_NAMES_V1:
        a = np.asarray(getattr(skimage.data, name)())
        if a.ndim == 2:
            a = np.repeat(a[:, :, None], 3, axis=2)
        a = a[:, :, :3].astype(np.uint8)
        s = 256 / min(a.shape[:2])
        if s < 1:
            a = cv2.resize(a, (round(a.shape[1] * s), round(a.shape[0] * s)),
                           interpolation=cv2.INTER_AREA)
        out.append(np.ascontiguousarray(a))
    return tuple(out)


def random_colour(rng: np.random.Generator, lo: float = 0.15, hi: float = 1.0) -> np.ndarray:
    return rng.uniform(lo, hi, size=3)


def make_texture(rng: np.random.Generator) -> np.ndarray:
    """A random ``uint8 [128, 128, 3]`` texture: a photo crop (maybe tinted) or a pattern."""
    n = TEXTURE_SIZE
    r = rng.random()
    if r < 0.6:
        photos = photos_v1()
        a = photos[rng.integers(len(photos))]
        side = int(rng.integers(64, min(a.shape[:2]) + 1))
        y = int(rng.integers(0, a.shape[0] - side + 1))
        x = int(rng.integers(0, a.shape[1] - side + 1))
        tex = cv2.resize(a[y:y + side, x:x + side], (n, n), interpolation=cv2.INTER_AREA)
        if rng.random() < 0.5:          # tint grey-ish photos so the palette is varied
            tex = np.clip(tex * (0.4 + 0.6 * random_colour(rng)), 0, 255)
        return tex.astype(np.uint8)
    c0 = random_colour(rng, 0.0, 1.0) * 255
    c1 = random_colour(rng, 0.0, 1.0) * 255
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    if r < 0.75:                        # checkerboard
        k = int(rng.choice([8, 16, 32]))
        m = ((i // k + j // k) % 2).astype(np.float64)
    elif r < 0.9:                       # stripes at a random angle
        th = rng.uniform(0, np.pi)
        period = rng.uniform(8, 32)
        m = (np.sin((i * np.cos(th) + j * np.sin(th)) * 2 * np.pi / period) > 0).astype(np.float64)
    else:                               # smooth blobs (low-frequency noise)
        m = cv2.resize(rng.random((6, 6)), (n, n), interpolation=cv2.INTER_CUBIC)
        m = np.clip((m - m.min()) / max(np.ptp(m), 1e-6), 0, 1)
    tex = c0 * (1 - m[..., None]) + c1 * m[..., None]
    return np.clip(tex, 0, 255).astype(np.uint8)



# ----------------------------------------------------------------------------------------------
# Capture kinds: the larger photo pool
# ----------------------------------------------------------------------------------------------

#: scikit-image photos bundled with the wheel (no pooch download).
SKIMAGE_PHOTOS = ("astronaut", "brick", "camera", "cat", "chelsea", "clock", "coffee", "coins",
                  "colorwheel", "grass", "gravel", "hubble_deep_field", "immunohistochemistry",
                  "moon", "page", "retina", "rocket", "text")
#: Debian ``opencv-doc``: OpenCV's sample photos (BSD-3-Clause).
OPENCV_DOC_DIR = Path("/usr/share/doc/opencv-doc/examples/data")
OPENCV_DOC_PHOTOS = ("HappyFish.jpg", "aero1.jpg", "aloeL.jpg", "apple.jpg", "baboon.jpg",
                     "basketball1.png", "blox.jpg", "board.jpg", "box_in_scene.png", "building.jpg",
                     "butterfly.jpg", "chicky_512.png", "fruits.jpg", "graf1.png", "home.jpg",
                     "leuvenA.jpg", "messi5.jpg", "orange.jpg", "rubberwhale1.png", "smarties.png",
                     "squirrel_cls.jpg", "starry_night.jpg", "stuff.jpg", "sudoku.png",
                     "left01.jpg", "notes.png", "cards.png")
#: Debian ``visp-images-data`` (GPL-2): single photos; never the sequences (cube, mbt,
#: mbt-depth, video, mire-2, ellipse-1, line, calibration), which are or may become test sets.
VISP_DIR = Path("/usr/share/visp-images-data/ViSP-images")
VISP_PHOTOS = ("Klimt/Klimt.png", "Solvay/Solvay_conference_1927_Version2_1024x705.png",
               "AprilTag/AprilTag.pgm")
#: Short side of the pooled photos (pixels): crops of 64 up to this size become textures.
PHOTO_SIDE = 320


def _shrink(a: np.ndarray, side: int) -> np.ndarray:
    if a.ndim == 2:
        a = np.repeat(a[:, :, None], 3, axis=2)
    a = np.ascontiguousarray(a[:, :, :3].astype(np.uint8))
    s = side / min(a.shape[:2])
    if s < 1:
        a = cv2.resize(a, (round(a.shape[1] * s), round(a.shape[0] * s)), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(a)


@functools.lru_cache(maxsize=1)
def photo_pool() -> tuple[np.ndarray, ...]:
    """Every pooled photo as uint8 RGB with its short side at most ``PHOTO_SIDE`` (loaded once).

    Raises ``RuntimeError`` naming the Debian package when a photo file is missing.
    """
    import skimage.data

    out = [_shrink(np.asarray(getattr(skimage.data, n)()), PHOTO_SIDE) for n in SKIMAGE_PHOTOS]
    for folder, names, package in ((OPENCV_DOC_DIR, OPENCV_DOC_PHOTOS, "opencv-doc"),
                                   (VISP_DIR, VISP_PHOTOS, "visp-images-data")):
        for name in names:
            bgr = cv2.imread(str(folder / name), cv2.IMREAD_COLOR)
            if bgr is None:
                raise RuntimeError(f"texture photo {folder / name} is missing: the capture kinds "
                                   f"need the Debian package {package} (apt-get install {package})")
            out.append(_shrink(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), PHOTO_SIDE))
    return tuple(out)


def photo_crop(rng: np.random.Generator, n: int, min_side: int = 48) -> np.ndarray:
    """A random square crop of a pooled photo resized to ``n x n`` uint8 RGB."""
    pool = photo_pool()
    a = pool[int(rng.integers(len(pool)))]
    side = int(rng.integers(min_side, min(a.shape[:2]) + 1))
    y = int(rng.integers(0, a.shape[0] - side + 1))
    x = int(rng.integers(0, a.shape[1] - side + 1))
    crop = a[y:y + side, x:x + side]
    if rng.random() < 0.5:
        crop = crop[:, ::-1]
    k = int(rng.integers(4))
    return np.ascontiguousarray(cv2.resize(np.rot90(crop, k), (n, n), interpolation=cv2.INTER_AREA))


def _pattern(rng: np.random.Generator, n: int) -> np.ndarray:
    """A procedural pattern in [0, 1] of shape [n, n]: checks, stripes, blobs, dots or noise."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    r = rng.random()
    if r < 0.2:
        k = int(rng.choice([4, 8, 16, 32]))
        return ((i // k + j // k) % 2).astype(np.float64)
    if r < 0.4:
        th = rng.uniform(0, np.pi)
        period = rng.uniform(4, 32)
        return (np.sin((i * np.cos(th) + j * np.sin(th)) * 2 * np.pi / period) > 0).astype(np.float64)
    if r < 0.6:
        g = int(rng.integers(4, 16))
        m = cv2.resize(rng.random((g, g)), (n, n), interpolation=cv2.INTER_CUBIC)
        return np.clip((m - m.min()) / max(np.ptp(m), 1e-6), 0, 1)
    if r < 0.8:
        period = rng.uniform(6, 24)
        d = np.hypot((i % period) - period / 2, (j % period) - period / 2)
        return (d < period * rng.uniform(0.15, 0.4)).astype(np.float64)
    # multi-octave value noise: wood/stone-like grain
    m = np.zeros((n, n))
    for octave in range(4):
        g = 4 * 2 ** octave
        m += cv2.resize(rng.random((g, g)), (n, n), interpolation=cv2.INTER_CUBIC) / 2 ** octave
    return np.clip((m - m.min()) / max(np.ptp(m), 1e-6), 0, 1)


def make_photo_texture(rng: np.random.Generator, n: int = 256, photo: float = 0.75) -> np.ndarray:
    """A random ``uint8 [n, n, 3]`` texture: a photo crop (probability ``photo``; sometimes tinted
    or overlaid with a pattern) or a two-colour procedural pattern."""
    if rng.random() < photo:
        tex = photo_crop(rng, n).astype(np.float64)
        r = rng.random()
        if r < 0.25:
            tex = tex * (0.5 + 0.5 * random_colour(rng))
        elif r < 0.35:
            m = _pattern(rng, n)[..., None]
            tex = tex * (1 - 0.5 * m) + 0.5 * m * random_colour(rng, 0.0, 1.0) * 255
        return np.clip(tex, 0, 255).astype(np.uint8)
    m = _pattern(rng, n)[..., None]
    c0 = random_colour(rng, 0.0, 1.0) * 255
    c1 = random_colour(rng, 0.0, 1.0) * 255
    return np.clip(c0 * (1 - m) + c1 * m, 0, 255).astype(np.uint8)
