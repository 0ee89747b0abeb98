"""The scene store: encoded scenes kept for rendering, bounded in memory, least recently used
evicted first.

A ``Scene`` is what ``IrisRuntime.encode`` leaves (field maps and the model-resolution photos,
read-only arrays), so a store entry costs the bytes of its arrays; the store holds at most
``max_bytes`` of them and at most ``max_scenes`` entries, and a scene that alone exceeds the byte
bound is refused (413) rather than evicting everything. Scene ids are random URL-safe tokens
(unguessable: without a bearer token, knowing an id is what gives access to its scene).
"""
from __future__ import annotations

import secrets
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass

from ..scene import Scene
from .errors import NotFound, PayloadTooLarge

__all__ = ["StoredScene", "SceneStore", "scene_nbytes"]


def scene_nbytes(scene: Scene) -> int:
    """Bytes of the arrays a ``Scene`` holds (what keeping it costs): its photos (at most
    ``colour.MAX_PHOTO_SIDE`` a side) with the pyramid levels renders add to them (at most a
    third more), and its model-resolution arrays."""
    arrays = (scene.field_maps, scene.world_from_cam, scene.focal, scene.K,
              scene.reference_images, scene.image_index, scene.encoder_focal,
              scene.encoder_world_from_cam)
    photos = sum(p.nbytes for p in scene.photos) if scene.photos is not None else 0
    return sum(a.nbytes for a in arrays if a is not None) + photos * 4 // 3


@dataclass(frozen=True)
class StoredScene:
    scene_id: str
    scene: Scene
    nbytes: int
    created: float          # time.time() when stored
    cameras: str            # the cameras asked for at encode (``manifest.CAMERAS``)


class SceneStore:
    """LRU of ``StoredScene`` bounded by ``max_bytes`` and ``max_scenes`` (thread-safe);
    ``on_evict()`` is called per eviction (metrics)."""

    def __init__(self, max_bytes: int, max_scenes: int, on_evict=None):
        if max_bytes < 1 or max_scenes < 1:
            raise ValueError("max_bytes and max_scenes must be positive")
        self.max_bytes = int(max_bytes)
        self.max_scenes = int(max_scenes)
        self._items: OrderedDict[str, StoredScene] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()
        self._on_evict = on_evict or (lambda: None)

    def __len__(self) -> int:
        return len(self._items)

    @property
    def nbytes(self) -> int:
        return self._bytes

    def put(self, scene: Scene, cameras: str) -> StoredScene:
        """Store ``scene`` under a new id, evicting the least recently used scenes to make room;
        ``PayloadTooLarge`` when it alone is over the byte bound."""
        size = scene_nbytes(scene)
        if size > self.max_bytes:
            raise PayloadTooLarge(f"images: the encoded scene takes {size / 2**20:.1f} MB, more "
                                  f"than the scene store holds ({self.max_bytes / 2**20:.1f} MB, "
                                  f"iris-serve --store-mb); send fewer photos")
        entry = StoredScene(secrets.token_urlsafe(12), scene, size, time.time(), cameras)
        with self._lock:
            while self._items and (self._bytes + size > self.max_bytes
                                   or len(self._items) >= self.max_scenes):
                _, old = self._items.popitem(last=False)
                self._bytes -= old.nbytes
                self._on_evict()
            self._items[entry.scene_id] = entry
            self._bytes += size
        return entry

    def get(self, scene_id: str) -> StoredScene:
        """The scene of ``scene_id`` (now the most recently used), or ``NotFound``."""
        with self._lock:
            entry = self._items.get(scene_id)
            if entry is not None:
                self._items.move_to_end(scene_id)
                return entry
        raise NotFound(self._unknown(scene_id))

    def delete(self, scene_id: str) -> None:
        """Forget ``scene_id``, or ``NotFound``."""
        with self._lock:
            entry = self._items.pop(scene_id, None)
            if entry is not None:
                self._bytes -= entry.nbytes
                return
        raise NotFound(self._unknown(scene_id))

    def _unknown(self, scene_id: str) -> str:
        shown = scene_id if len(scene_id) <= 64 else scene_id[:64] + "..."
        return (f"scene_id: no scene {shown!r} (never made, deleted, or evicted: the store keeps "
                f"the {self.max_scenes} most recently used scenes within "
                f"{self.max_bytes / 2**20:.0f} MB); POST /scenes to encode it again")
