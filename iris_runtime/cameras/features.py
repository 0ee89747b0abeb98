"""Step 1 of the camera solve: SIFT features of each photo and their matches between two photos.

Sparse features, not dense flow, because a keypoint matched by its descriptor survives a wide gap
between two views (dense DIS flow did worse on the same pairs: docs/record/cameras.md, "Repeated
patterns, in detail"). Conventions: pixel coordinates with pixel (row i, col j) centred at
(j + 0.5, i + 0.5) (docs/ARCHITECTURE.md), OpenCV's keypoints shifted by +0.5 to it.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np

from ..errors import InputError

__all__ = ["Features", "extract_features", "match_features", "canonical_order", "grey",
           "enlargement", "enlarge", "scene_features", "twin_distance", "distinct_keypoints",
           "contrast_threshold", "MAX_FEATURES", "CONTRAST_THRESHOLD", "SMALL_CONTRAST_THRESHOLD",
           "MAX_RATIO", "MAX_DISTANCE", "MIN_SIZE", "LOW_TEXTURE_SIZE", "MIN_KEYPOINTS",
           "DISTINCT_DISTANCE", "TWIN_MIN_PIXELS", "MIRROR"]

#: Keypoints kept per photo (the strongest by SIFT response); matching costs grow with the square.
MAX_FEATURES = 2048
#: OpenCV's SIFT contrast threshold: half its default, so low-texture photos keep enough keypoints.
CONTRAST_THRESHOLD = 0.02
#: ... and for photos under ``MIN_SIZE``, enlarged before the solve: the cubic enlargement smooths
#: every edge, and at 0.02 a 64x64 photo keeps too few keypoints for the wide pairs
#: (docs/CAMERAS.md, "Small photos"; 0.0075 chosen on the validation scenes at 64x64).
SMALL_CONTRAST_THRESHOLD = 0.0075
#: Lowe's ratio test: best / second-best descriptor distance below this (COLMAP's default).
MAX_RATIO = 0.8
#: Largest accepted descriptor distance between unit RootSIFT vectors (COLMAP's default).
MAX_DISTANCE = 0.7
#: Photos shorter than this on their longer side are enlarged by a whole factor (cubic) before
#: the solve, at once to ``LOW_TEXTURE_SIZE``: SIFT finds few keypoints in small photos
#: (docs/CAMERAS.md, "Small photos").
MIN_SIZE = 256
#: Photos whose median keypoint count is below ``MIN_KEYPOINTS`` and whose longer side is under
#: ``LOW_TEXTURE_SIZE`` are solved enlarged by the whole factor that brings them to it (256 ->
#: 512): enlarged twice, a low-texture photo gives about twice the keypoints, enough matches to
#: bridge wide gaps (docs/CAMERAS.md, "Low-texture photos"; 600 chosen on the validation scenes).
#: Larger photos are left as they are: 320x240 photos doubled take two to three times as long
#: to solve (``benchmarks/encode_cost.py --set features.LOW_TEXTURE_SIZE=640``).
LOW_TEXTURE_SIZE = 320
MIN_KEYPOINTS = 600
#: RootSIFT descriptors are stored as uint8 round(512 x), the scale COLMAP uses (entries <= 0.5).
_DESCRIPTOR_SCALE = 512.0


@dataclass(frozen=True)
class Features:
    """SIFT keypoints of one photo.

    uv:          float64 [N, 2]  keypoint positions (pixel centres at +0.5)
    descriptors: uint8 [N, 128]  RootSIFT descriptors, scaled by 512
    image_size:  (H, W)          the photo they were found in
    """
    uv: np.ndarray
    descriptors: np.ndarray
    image_size: tuple[int, int]

    def __len__(self) -> int:
        return self.uv.shape[0]

    def subset(self, index: np.ndarray) -> "Features":
        return Features(self.uv[index], self.descriptors[index], self.image_size)

    @cached_property
    def unit(self) -> np.ndarray:
        """float32 [N, 128]: the descriptors as unit vectors, computed once: a photo is matched
        with every other photo of its scene."""
        d = self.descriptors.astype(np.float32)
        return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-6)


def grey(photo: np.ndarray) -> np.ndarray:
    """uint8 [H, W] grey of a uint8 RGB photo [H, W, 3] (a grey [H, W] photo is returned as is)."""
    if photo.ndim == 2:
        return photo
    return cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY)


def enlargement(image_size: tuple[int, int]) -> int:
    """The whole factor k >= 1 by which photos of ``image_size`` (H, W) are enlarged for the
    solve: the smallest with k * max(H, W) >= ``MIN_SIZE``. Pixel coordinates map as u -> k u
    (pixel edges at whole numbers, centres at +0.5), so cameras solved on the enlarged photos
    hold for the photos with the focal divided by k."""
    return max(1, -(-MIN_SIZE // max(image_size)))


def contrast_threshold(image_size: tuple[int, int]) -> float:
    """The SIFT contrast threshold for photos of ``image_size`` (H, W) as given: lower for photos
    under ``MIN_SIZE``, which are found enlarged."""
    return SMALL_CONTRAST_THRESHOLD if max(image_size) < MIN_SIZE else CONTRAST_THRESHOLD


def scene_features(photos, small_size: int = LOW_TEXTURE_SIZE,
                   max_features: int | None = None) -> tuple[list[Features], int]:
    """SIFT features of the photos of one scene (uint8, one size) and the whole factor ``k`` of
    the enlarged photos they were found in (``Features.uv`` in their pixels): ``enlargement``,
    raised to reach ``LOW_TEXTURE_SIZE`` when the photos' median keypoint count is below
    ``MIN_KEYPOINTS``: the smallest whole k with k x longer side >= it. Photos enlarged anyway
    (under ``MIN_SIZE``) are enlarged that far at once: nearly all of them are low-texture at
    ``MIN_SIZE``, and one SIFT pass is spared (docs/CAMERAS.md, "Small photos"); their keypoints
    are found at ``contrast_threshold``. ``small_size``: the longer side photos under ``MIN_SIZE``
    are enlarged to at least (``refine`` takes a smaller one). ``max_features``: keypoints kept
    per photo (default ``MAX_FEATURES``); below it, the strongest of what it would keep, the
    others never described. The factor depends on the set of photos, not on their order."""
    size = np.asarray(photos[0]).shape[:2]
    k = enlargement(size)
    small = k > 1
    if small:
        k = -(-small_size // max(size))
    k_low = max(k, -(-LOW_TEXTURE_SIZE // max(size)))
    threshold = contrast_threshold(size)
    # Enough keypoints found to tell whether the photos reach MIN_KEYPOINTS.
    n = max(max_features, MIN_KEYPOINTS) if max_features else None
    feats = [extract_features(enlarge(np.asarray(p), k), max_features=n,
                              contrast_threshold=threshold) for p in photos]
    if not small and k_low > k and np.median([len(f) for f in feats]) < MIN_KEYPOINTS:
        k = k_low
        feats = [extract_features(enlarge(np.asarray(p), k), max_features=n,
                                  contrast_threshold=threshold) for p in photos]
    if max_features:
        feats = [f.subset(np.arange(min(len(f), max_features))) for f in feats]
    return feats, k


def enlarge(photo: np.ndarray, k: int) -> np.ndarray:
    """``photo`` enlarged k times on each side (cubic), or itself when k == 1."""
    if k == 1:
        return photo
    return cv2.resize(photo, (photo.shape[1] * k, photo.shape[0] * k),
                      interpolation=cv2.INTER_CUBIC)


def extract_features(photo: np.ndarray, max_features: int | None = None,
                     contrast_threshold: float | None = None) -> Features:
    """SIFT keypoints of a uint8 photo ([H, W, 3] RGB or [H, W] grey), at most ``max_features``
    (default ``MAX_FEATURES``), found at ``contrast_threshold`` (default ``CONTRAST_THRESHOLD``).

    The keypoints are sorted by a key of their own values (response, position, scale, angle),
    not by the order OpenCV's threads found them in, so the same photo gives the same features.
    """
    image = grey(photo)
    n = max_features or MAX_FEATURES
    # OpenCV keeps every keypoint whose response reaches the n-th largest (a set, not an order)
    # before computing descriptors; the order is then fixed below.
    threshold = CONTRAST_THRESHOLD if contrast_threshold is None else contrast_threshold
    sift = cv2.SIFT_create(nfeatures=n, contrastThreshold=threshold)
    keypoints, desc = sift.detectAndCompute(image, None)
    H, W = image.shape
    if desc is None or len(keypoints) == 0:
        return Features(np.zeros((0, 2)), np.zeros((0, 128), np.uint8), (H, W))
    kp = np.array([(k.response, k.pt[0], k.pt[1], k.size, k.angle) for k in keypoints])
    order = np.lexsort(kp.T[::-1])[::-1][:n]                    # strongest first
    desc = desc[order].astype(np.float64)
    desc /= np.maximum(desc.sum(axis=1, keepdims=True), 1e-12)   # RootSIFT: L1, then sqrt
    desc = np.clip(np.rint(np.sqrt(desc) * _DESCRIPTOR_SCALE), 0, 255).astype(np.uint8)
    return Features(kp[order, 1:3] + 0.5, desc, (H, W))


def match_features(a: Features, b: Features) -> np.ndarray:
    """Matches ``int64 [M, 2]`` (index in a, index in b) of two photos' features: each keypoint's
    nearest descriptor in the other photo, kept when it passes the ratio test (``MAX_RATIO``), is
    close enough (``MAX_DISTANCE``) and is mutual (b's nearest in a is the same keypoint)."""
    if len(a) < 2 or len(b) < 2:
        return np.zeros((0, 2), np.int64)
    # Nearest and second nearest from the similarities: |x - y|^2 = 2 - 2 x.y for unit vectors.
    sim = a.unit @ b.unit.T
    rows = np.arange(sim.shape[0])
    nearest = np.argmax(sim, axis=1)
    best = sim[rows, nearest]
    sim[rows, nearest] = -np.inf              # in place (no copy of [Na, Nb]), restored below
    second = sim.max(axis=1)
    sim[rows, nearest] = best
    d_best = np.sqrt(np.maximum(2.0 - 2.0 * best, 0.0))
    d_second = np.sqrt(np.maximum(2.0 - 2.0 * second, 0.0))
    ok = (d_best < MAX_RATIO * d_second) & (d_best < MAX_DISTANCE)
    ia = np.flatnonzero(ok)
    ib = nearest[ia]
    mutual = np.argmax(sim[:, ib], axis=0) == ia
    return np.stack([ia[mutual], ib[mutual]], axis=1).astype(np.int64)


#: A keypoint is distinct when no other keypoint of its own photo (more than ``TWIN_MIN_PIXELS``
#: away) has a descriptor this close (RootSIFT, unit vectors): on a repeated texture every
#: keypoint has near twins, and a match one period off is as close as the right one
#: (docs/CAMERAS.md, "Repeated patterns"; 0.35 chosen on the validation scenes; 0: off).
DISTINCT_DISTANCE = 0.35
TWIN_MIN_PIXELS = 8.0


#: SIFT's descriptor of a mirrored patch is a permutation of the original's: the 4x4 cells'
#: rows reversed and the 8 orientation bins negated (OpenCV's layout: (row, column, bin)).
#: A texture tiled with mirrored copies has its repeats found only through it.
_row, _col, _bin = np.meshgrid(np.arange(4), np.arange(4), np.arange(8), indexing="ij")
MIRROR = np.arange(128).reshape(4, 4, 8)[3 - _row, _col, -_bin % 8].ravel()
del _row, _col, _bin


def twin_distance(f: Features, mirrored: bool = False) -> np.ndarray:
    """float [N]: each keypoint's descriptor distance to its nearest twin in its own photo (the
    closest other keypoint more than ``TWIN_MIN_PIXELS`` away; 2.0, the largest, when none).
    mirrored: compare with the other keypoints' mirrored descriptors (``MIRROR``) instead."""
    if len(f) < 2:
        return np.full(len(f), 2.0)
    u = f.unit
    sim = u @ (u[:, MIRROR] if mirrored else u).T
    x, y = f.uv[:, 0].astype(np.float32), f.uv[:, 1].astype(np.float32)
    near = (x[:, None] - x[None]) ** 2 + (y[:, None] - y[None]) ** 2 < TWIN_MIN_PIXELS ** 2
    sim[near] = -1.0
    return np.sqrt(np.maximum(2.0 - 2.0 * sim.max(axis=1), 0.0))


def distinct_keypoints(f: Features) -> np.ndarray:
    """bool [N]: the keypoints without a twin closer than ``DISTINCT_DISTANCE`` in their own
    photo (``twin_distance``); none when ``DISTINCT_DISTANCE`` is 0 (the distinction off)."""
    if DISTINCT_DISTANCE <= 0:
        return np.zeros(len(f), bool)
    return twin_distance(f) > DISTINCT_DISTANCE


def canonical_order(photos) -> np.ndarray:
    """``perm`` int64 [V]: the order the solve looks at the photos in, fixed by their content
    (ascending SHA-256 of each photo's bytes and shape; identical photos keep their given order).

    Matching and the robust estimators depend on which photo comes first, so the solve runs in
    this order and the caller's order only decides which view the result is rooted at: the same
    photos in any order give the same cameras.
    """
    keys = []
    for k, x in enumerate(photos):
        x = np.ascontiguousarray(x)
        if x.dtype != np.uint8:
            raise InputError(f"photos[{k}]: expected uint8, got {x.dtype}")
        keys.append(hashlib.sha256(repr(x.shape).encode() + x.tobytes()).hexdigest())
    return np.array(sorted(range(len(keys)), key=lambda k: (keys[k], k)), dtype=np.int64)
