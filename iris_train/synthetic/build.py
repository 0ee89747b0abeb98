"""``build_scene_spec``: the renderer-neutral description of the scene of a seed and kind."""
from __future__ import annotations

import math

import numpy as np

from iris_runtime.errors import InputError

from .cameras import intrinsics
from .capture import CAPTURE_KINDS, build_handheld, build_indoor, build_object
from .classic import build_room, build_turntable
from .meshes import marker_mesh
from .paths import draw_intrinsics, intrinsics_off_centre
from .scene import SUPERSAMPLE, SceneSpec

#: Classic scene kinds; ``kind=None`` draws one of them from the seed (as in version 1).
KINDS = ("turntable", "room")
#: Every kind ``build_scene_spec`` accepts; "capture" is the capture kind of the seed
#: (``capture_kind``: they alternate by seed, so any run of seeds is balanced).
ALL_KINDS = KINDS + CAPTURE_KINDS + ("capture",)
#: Generator version of each kind: a cached scene of another version is regenerated. The classic
#: kinds are frozen at 1 (the held-out and validation scenes); the capture kinds started at 2
#: (3: packaged meshes, no supersampling from 192 rows).
KIND_VERSIONS = {"turntable": 1, "room": 1, **{k: 3 for k in CAPTURE_KINDS}}
#: The newest version of any kind.
GENERATOR_VERSION = max(KIND_VERSIONS.values())
#: Range of the capture kinds' median valid depth (drawn per scene; the model samples [0.1, 1]).
DEPTH_TARGET_RANGE = (0.25, 0.75)


def capture_kind(seed: int) -> str:
    """The capture kind that ``kind="capture"`` gives scene ``seed``."""
    return CAPTURE_KINDS[int(seed) % len(CAPTURE_KINDS)]


def resolve_kind(seed: int, kind: str | None) -> str:
    """The concrete kind of scene ``seed`` for a requested ``kind`` (None, "capture" or a kind)."""
    if kind is None:
        rng = np.random.default_rng([int(seed), 0x1815])
        return KINDS[int(rng.integers(len(KINDS)))]
    if kind not in ALL_KINDS:
        raise InputError(f"kind: expected one of {ALL_KINDS} or None, got {kind!r}")
    return capture_kind(seed) if kind == "capture" else kind


def _check(seed, n_views, size) -> None:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed: expected a non-negative int, got {seed!r}")
    if not isinstance(n_views, (int, np.integer)) or n_views < 1:
        raise InputError(f"n_views: expected a positive int, got {n_views!r}")
    if (len(size) != 2 or not all(isinstance(s, (int, np.integer)) and s > 0 for s in size)):
        raise InputError(f"size: expected (height, width) positive ints, got {size!r}")


def build_scene_spec(seed: int, n_views: int = 8, size: tuple[int, int] = (64, 64),
                     kind: str | None = None, markers: bool = False) -> SceneSpec:
    """The random scene of ``seed`` as a renderer-neutral description (deterministic per seed).

    ``kind``: None (a classic kind drawn from the seed), "turntable", "room", a capture kind
    (``CAPTURE_KINDS``) or "capture" (the seed's capture kind)."""
    _check(seed, n_views, size)
    if kind in CAPTURE_KINDS or kind == "capture":
        return _capture_spec(int(seed), int(n_views), (int(size[0]), int(size[1])),
                             resolve_kind(seed, kind), markers)
    rng = np.random.default_rng([int(seed), 0x1815])
    kind_drawn = KINDS[int(rng.integers(len(KINDS)))]     # drawn always, so streams do not shift
    kind = kind_drawn if kind is None else kind
    if kind not in KINDS:
        raise InputError(f"kind: expected one of {ALL_KINDS} or None, got {kind!r}")
    yfov = math.radians(rng.uniform(40.0, 70.0))
    build = build_turntable if kind == "turntable" else build_room
    meshes, lights, ambient, background, world_from_cam, marker_pts, info = build(rng, int(n_views))
    if markers:
        meshes += [marker_mesh(p, i) for i, p in enumerate(marker_pts)]
    else:
        marker_pts = np.zeros((0, 3))
    K = intrinsics(tuple(int(s) for s in size), yfov)
    meta = {"seed": int(seed), "kind": kind, "generator_version": KIND_VERSIONS[kind],
            "yfov_deg": math.degrees(yfov), "supersample": SUPERSAMPLE,
            "depth_background": 0.0, "world_up": [0.0, 0.0, 1.0], **info}
    return SceneSpec(kind, int(seed), (int(size[0]), int(size[1])), K, world_from_cam, meshes,
                     lights, ambient, background, marker_pts, meta)


def _capture_spec(seed: int, n_views: int, size: tuple[int, int], kind: str, markers: bool) -> SceneSpec:
    rng = np.random.default_rng([seed, 0x2025, CAPTURE_KINDS.index(kind)])
    yfov, offset = draw_intrinsics(rng)
    if kind in ("walk", "orbit"):
        meshes, lights, ambient, world_from_cam, anchors, info = build_object(rng, n_views, yfov, kind)
    elif kind == "handheld":
        meshes, lights, ambient, world_from_cam, anchors, info = build_handheld(rng, n_views, yfov)
    else:
        meshes, lights, ambient, world_from_cam, anchors, info = build_indoor(rng, n_views, yfov)
    depth_target = float(rng.uniform(*DEPTH_TARGET_RANGE))
    marker_pts = np.zeros((0, 3))
    if markers:
        # Around the first anchor, where the cameras look (the coverage pass ignores occlusion).
        r = 0.04
        marker_pts = anchors[0] + np.array([[r, 0, r], [-r, r, 0], [0, -r, 1.5 * r], [0, 0, -0.5 * r]])
        meshes = meshes + [marker_mesh(p, i) for i, p in enumerate(marker_pts)]
    K = intrinsics_off_centre(size, yfov, offset)
    meta = {"seed": seed, "kind": kind, "generator_version": KIND_VERSIONS[kind],
            "yfov_deg": math.degrees(yfov), "principal_offset": [float(o) for o in offset],
            "supersample": SUPERSAMPLE, "depth_background": 0.0, "world_up": [0.0, 0.0, 1.0],
            "depth_target": depth_target, **info}
    return SceneSpec(kind, seed, size, K, world_from_cam, meshes, lights, ambient, (0.0, 0.0, 0.0),
                     marker_pts, meta, depth_target=depth_target, anchors_world=np.asarray(anchors))
