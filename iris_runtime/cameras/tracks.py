"""Step 3 of the camera solve: tracks, the keypoints that see one 3D point, across all photos.

A track is a connected component of the graph whose nodes are keypoints and whose edges are the
pairs' F-consistent matches. A component holding two keypoints of one photo contradicts itself
(one point cannot be seen twice in one photo) and is dropped. Tracks are stored as a table
``keypoint [T, V]`` (the keypoint index of track t in view v, -1 where the track has none), so
the rest of the solve works on whole arrays.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .features import Features

__all__ = ["Tracks", "build_tracks"]


@dataclass(frozen=True)
class Tracks:
    """keypoint: int64 [T, V], the keypoint of each track in each view (-1: none);
    uv: float64 [T, V, 2], its position (NaN where there is none)."""
    keypoint: np.ndarray
    uv: np.ndarray

    def __len__(self) -> int:
        return self.keypoint.shape[0]

    @property
    def observed(self) -> np.ndarray:
        """bool [T, V]: the track has a keypoint in the view."""
        return self.keypoint >= 0


def _components(n: int, edges: np.ndarray) -> np.ndarray:
    """Component label (its smallest node) of each of n nodes linked by ``edges int64 [E, 2]``:
    minimum-label propagation along the edges, then pointer jumping, until nothing changes."""
    label = np.arange(n)
    if len(edges) == 0:
        return label
    a, b = edges[:, 0], edges[:, 1]
    while True:
        m = np.minimum(label[a], label[b])
        new = label.copy()
        np.minimum.at(new, a, m)
        np.minimum.at(new, b, m)
        new = new[new]                                  # jump to the label's own label
        if np.array_equal(new, label):
            return label
        label = new


def build_tracks(features: list[Features], matches: dict[tuple[int, int], np.ndarray]) -> Tracks:
    """Tracks of ``features`` (one per view) from ``matches`` {(i, j): int64 [M, 2] keypoint
    pairs}. Tracks come in the order of their smallest keypoint (view-major), so the table is a
    function of the features and matches alone."""
    V = len(features)
    offsets = np.cumsum([0] + [len(f) for f in features])
    edges = [np.stack([offsets[i] + m[:, 0], offsets[j] + m[:, 1]], 1)
             for (i, j), m in sorted(matches.items()) if len(m)]
    edges = np.concatenate(edges) if edges else np.zeros((0, 2), np.int64)
    n = int(offsets[-1])
    label = _components(n, edges)
    node = np.unique(edges) if len(edges) else np.zeros(0, np.int64)
    view = np.searchsorted(offsets, node, side="right") - 1
    lab = label[node]
    # Drop components with two keypoints in one view; keep those with two views or more.
    key = lab * V + view
    uniq, counts = np.unique(key, return_counts=True)
    bad = np.unique(uniq[counts > 1] // V)
    keep = ~np.isin(lab, bad)
    node, view, lab = node[keep], view[keep], lab[keep]
    tracks, track_of = np.unique(lab, return_inverse=True)
    keypoint = np.full((len(tracks), V), -1, np.int64)
    keypoint[track_of, view] = node - offsets[view]
    uv = np.full((len(tracks), V, 2), np.nan)
    for v in range(V):
        has = keypoint[:, v] >= 0
        uv[has, v] = features[v].uv[keypoint[has, v]]
    return Tracks(keypoint, uv)
