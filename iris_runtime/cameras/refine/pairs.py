"""The refinement's evidence: what the photos say about each pair of views.

SIFT matches of every pair (``features``), kept where the essential matrix at the model's focal
explains them (``two_view.essential_pose``, which also gives the pair's relative pose), and the
tracks they link (``tracks``). Every later stage reads this evidence and nothing else of the
photos.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import InputError
from ...validation import check_world_from_cam
from ..features import match_features, scene_features
from ..solve import check_focal
from ..tracks import Tracks, build_tracks
from ..two_view import MAX_ERROR, essential_pose, pixel_scale

__all__ = ["PairOptions", "Evidence", "read_pairs", "check_start"]


@dataclass(frozen=True)
class PairOptions:
    """How the photos are read.

    max_keypoints: keypoints matched per photo, the strongest of the solve's
                   ``features.MAX_FEATURES`` (SIFT describes no others). The matching's cost
                   grows with their square, and a start needs fewer than a mapper. 0: the
                   solve's.
    small_size:    photos under ``features.MIN_SIZE`` are enlarged to this longer side before
                   SIFT reads them (the solve enlarges them to ``features.LOW_TEXTURE_SIZE``):
                   fewer pixels to read for about the same keypoints.
    """
    max_keypoints: int = 1024
    small_size: int = 192


@dataclass(frozen=True)
class Evidence:
    """The photos' evidence, in ``canonical_order``: their ``features`` (found in the photos
    enlarged ``k`` times, of ``image_size`` (H, W) then; ``px`` its ``pixel_scale``), the
    model's ``focal`` in those pixels, the principal point ``centre``, per pair (a, b) the
    matches its essential matrix explains ``inliers {(a, b): int64 [M, 2]}`` and its relative
    pose ``relative {(a, b): (cam_b_from_cam_a [4, 4] (unit translation), inliers)}``, and
    the ``tracks`` the inliers link."""
    features: list
    k: int
    image_size: tuple[int, int]
    px: float
    focal: float
    centre: np.ndarray
    inliers: dict
    relative: dict
    tracks: Tracks


def check_start(world_from_cam, focal, V: int) -> tuple[np.ndarray, float]:
    """The model's cameras as float64 ``[V, 4, 4]`` (rigid: ``validation.check_world_from_cam``)
    and its focal as a float (``solve.check_focal``), else ``InputError``."""
    poses = np.asarray(world_from_cam, dtype=np.float64)
    if poses.shape != (V, 4, 4) or not np.isfinite(poses).all():
        raise InputError(f"world_from_cam: expected finite float [{V}, 4, 4] (one pose per photo),"
                         f" got shape {poses.shape}")
    return check_world_from_cam(poses, "world_from_cam", batch=True), check_focal(focal)


def read_pairs(photos: list, focal: float, options: PairOptions) -> Evidence:
    """The ``Evidence`` of ``photos`` (in ``canonical_order``) at the model's ``focal`` (pixels
    of the photos)."""
    features, k = scene_features(photos, small_size=options.small_size,
                                 max_features=options.max_keypoints or None)
    H, W = features[0].image_size
    px = pixel_scale((H, W))
    f = focal * k
    inliers, relative = {}, {}
    V = len(photos)
    for a in range(V):
        for b in range(a + 1, V):
            m = match_features(features[a], features[b])
            pair = essential_pose(features[a].uv[m[:, 0]], features[b].uv[m[:, 1]], f, (H, W),
                                  MAX_ERROR * px)
            if pair is not None:
                inliers[a, b] = m[pair[0]]
                relative[a, b] = (pair[1], float(pair[0].sum()))
    return Evidence(features, k, (H, W), px, f, np.array([W / 2.0, H / 2.0]), inliers, relative,
                    build_tracks(features, inliers))
