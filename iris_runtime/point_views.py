"""The renderer feed on per-point pre-selected views (``io_spec.RENDERER_VIEWS``): a view-major
feed of ``raymarch.call_feed`` whose validity weights mark the (view, point) pairs to keep,
packed so the renderer runs its field on ``top_k`` view slots per point (numpy; no torch)."""
from __future__ import annotations

import numpy as np

from .io_spec import (COLOURS, CUES, DIRECTIONS, FIELD_MAPS, GRID, GROUPS, MASK, PAIRS,
                      POSITIONS)

__all__ = ["PAIR_GROUP", "select_point_views"]


#: Pairs per group of the selected-views renderer feed (``select_point_views``): each view's
#: kept pairs are padded to a multiple of this, not to the busiest view's count.
PAIR_GROUP = 128


def select_point_views(feed: dict[str, np.ndarray], group: int = PAIR_GROUP
                       ) -> dict[str, np.ndarray]:
    """The feed of the renderer on per-point pre-selected views (``io_spec.RENDERER_VIEWS``) from
    a view-major ``feed`` whose validity weights ``mask [v, r, s]`` mark the (view, point) pairs
    to keep (weight > 0): each view's kept pairs in groups of ``group`` (the last one padded), and
    per point its kept views, in view order, in slots 0 .. K - 1 with their weights (K: the most
    any point keeps; the rest weight 0). Same result as ``feed``: the renderer pools and attends
    over the valid views of each point."""
    mask = feed[MASK]
    v = mask.shape[0]
    weights = mask.reshape(v, -1)                                            # [v, r*s]
    flat = weights > 0
    counts = flat.sum(axis=1)
    K = max(1, int(flat.sum(axis=0).max()))
    n_groups = -(-counts // group)                                           # per view
    groups = np.repeat(np.arange(v), n_groups)
    if groups.size == 0:                                                     # nothing kept
        groups = np.zeros(1, np.int64)
    view, point = np.nonzero(flat)                                           # view-major
    rank = np.arange(len(view)) - np.repeat(np.cumsum(counts) - counts, counts)
    row = (np.cumsum(n_groups) - n_groups)[view] * group + rank              # in [0, P * G)
    slot = (np.cumsum(flat, axis=0) - 1)[view, point]                        # k of the pair

    def compact(x):
        out = np.zeros((len(groups) * group, x.shape[-1]), x.dtype)
        out[row] = x.reshape(v, -1, x.shape[-1])[view, point]
        return out.reshape(len(groups), group, x.shape[-1])

    pairs = np.zeros((K, flat.shape[1]), np.int64)
    pairs[slot, point] = row
    slots = np.zeros((K, flat.shape[1]), weights.dtype)
    slots[slot, point] = weights[view, point]
    out = {FIELD_MAPS: feed[FIELD_MAPS], GROUPS: groups.astype(np.int64),
           GRID: compact(feed[GRID]), CUES: compact(feed[CUES]),
           PAIRS: pairs.reshape(K, *mask.shape[1:]), MASK: slots.reshape(K, *mask.shape[1:]),
           POSITIONS: feed[POSITIONS], DIRECTIONS: feed[DIRECTIONS]}
    if COLOURS in feed:
        out[COLOURS] = compact(feed[COLOURS])
    return out
