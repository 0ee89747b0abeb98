"""The scenes an ``iris-train`` run draws from: the synthetic training scenes of a ``TrainConfig``
(classic, and capture-like ones beside them), at the model's size and at ``colour_size``, and the
per-scene lookup of their cached teachers (``pseudo_poses``).

Kept apart from the loop (``train``) and from the pseudo-poses (``pseudo_poses``), which both
import it: the capture scenes' render size is one number the solve and the training share.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .config import ModelConfig, TrainConfig
from .data import CAPTURE_VALIDATION_SEEDS, VALIDATION_SEEDS, SyntheticScenes
from .synthetic import CAPTURE_KINDS, capture_kind

#: Render size of the capture-like training scenes: the teacher's solve sees them at this size,
#: the model at its own (one 256 cache serves 64 and 128 models).
CAPTURE_RENDER_SIZE = (256, 256)


class SceneSets:
    """Several scene sets drawn as one: index ``i`` runs through ``parts[0]``, then ``parts[1]``,
    ... (so a uniform draw weights each part by its size). ``part_of(i)`` gives the set and the
    index inside it, which is what the on-disk teacher caches are keyed by."""

    def __init__(self, parts: Sequence):
        self.parts = [p for p in parts if len(p)]
        self._starts = np.cumsum([0] + [len(p) for p in self.parts])

    def __len__(self) -> int:
        return int(self._starts[-1])

    def part_of(self, index: int) -> tuple:
        if not 0 <= index < len(self):
            raise IndexError(f"index {index} out of range for {len(self)} scenes")
        k = int(np.searchsorted(self._starts, index, side="right")) - 1
        return self.parts[k], index - int(self._starts[k])

    def __getitem__(self, index: int):
        part, local = self.part_of(int(index))
        return part[local]


def per_scene(scenes, cached, compute):
    """scene index -> ``cached(scenes, index)`` for a ``SyntheticScenes`` (read from beside its
    cache, computed and written when missing), else ``compute(images)``; kept in memory. For
    the pair teacher and the solved cameras alike; a ``SceneSets`` is looked up per part."""
    memo: dict[int, object] = {}

    def one(sets, index: int):
        if isinstance(sets, SceneSets):
            return one(*sets.part_of(index))
        if hasattr(sets, "cache_dir") and hasattr(sets, "seeds"):
            return cached(sets, index)
        return compute(sets[index].images)

    def lookup(index: int):
        if index not in memo:
            memo[index] = one(scenes, index)
        return memo[index]
    return lookup


def capture_seeds(cfg: TrainConfig) -> list[int]:
    """The capture seeds a run draws: 0 .. ``cfg.capture_scenes``-1, those of
    ``cfg.capture_kinds`` only when it names some. ``ValueError`` for an unknown kind."""
    kinds = [k.strip() for k in cfg.capture_kinds.split(",") if k.strip()]
    unknown = sorted(set(kinds) - set(CAPTURE_KINDS))
    if unknown:
        raise ValueError(f"capture_kinds: unknown kind(s) {unknown}; expected names from "
                         f"{list(CAPTURE_KINDS)}, comma-separated")
    seeds = range(cfg.capture_scenes)
    return [s for s in seeds if not kinds or capture_kind(s) in kinds]


def training_scenes(cfg: TrainConfig, mcfg: ModelConfig):
    """The run's training scenes at the model's size: classic seeds 0 .. ``cfg.train_scenes``-1
    (rendered at ``classic_render_size`` when set), then, with ``cfg.capture_scenes``, the
    ``capture_seeds`` (rendered at CAPTURE_RENDER_SIZE), as one ``SceneSets``.
    ``ValueError`` for counts that would reach the validation scenes."""
    if cfg.capture_scenes > min(CAPTURE_VALIDATION_SEEDS):
        raise ValueError(f"capture_scenes: at most {min(CAPTURE_VALIDATION_SEEDS)} (the capture "
                         f"validation scenes start there), got {cfg.capture_scenes}")
    if cfg.train_scenes > min(VALIDATION_SEEDS):
        raise ValueError(f"train_scenes: at most {min(VALIDATION_SEEDS)} (the validation "
                         f"scenes start there), got {cfg.train_scenes}")
    size = (mcfg.image_height, mcfg.image_width)
    side = cfg.classic_render_size
    scenes = SyntheticScenes(range(cfg.train_scenes), size=size,
                             render_size=(side, side) if side else None)
    if cfg.capture_scenes:
        capture = SyntheticScenes(capture_seeds(cfg), size=size, kind="capture",
                                  render_size=CAPTURE_RENDER_SIZE)
        scenes = SceneSets([scenes, capture])
    return scenes


def colour_size_scenes(cfg: TrainConfig):
    """The training scenes at ``cfg.colour_size`` (square), indexed as ``training_scenes``:
    the classic scenes (their cached renders: ``classic_render_size`` must be that size), then
    the capture ones (CAPTURE_RENDER_SIZE). ``ValueError`` for a size no cache holds."""
    side = cfg.colour_size
    if cfg.classic_render_size != side:
        raise ValueError(f"colour_size: the classic scenes are cached at classic_render_size "
                         f"({cfg.classic_render_size}); expected colour_size equal to it, got {side}")
    if cfg.capture_scenes and CAPTURE_RENDER_SIZE != (side, side):
        raise ValueError(f"colour_size: the capture scenes are rendered at {CAPTURE_RENDER_SIZE}; "
                         f"expected colour_size {CAPTURE_RENDER_SIZE[0]}, got {side}")
    size = (side, side)
    scenes = SyntheticScenes(range(cfg.train_scenes), size=size, render_size=size)
    if cfg.capture_scenes:
        capture = SyntheticScenes(capture_seeds(cfg), size=size, kind="capture",
                                  render_size=CAPTURE_RENDER_SIZE)
        scenes = SceneSets([scenes, capture])
    return scenes
