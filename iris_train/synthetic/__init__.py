"""Synthetic multi-view scenes rendered with pyrender (OpenGL rasterisation, headless through EGL).

Why pyrender: see ``docs/DATA.md`` (measured with ``benchmarks/renderer_choice.py``): it renders a
64x64 view, 3x3 supersampled, with exact z-depth in ~8 ms, where Mitsuba 3 (``scalar_rgb``) needs
~190 ms per view (64 samples per pixel) to get its Monte-Carlo noise down to ~36 dB PSNR.

**Kinds.** The classic kinds "turntable" and "room" (``classic.py``, frozen: the held-out and
validation scenes) and the capture kinds "walk", "orbit", "handheld", "indoor" (``capture.py``):
scenes shaped like real captures, with wide fields of view, off-centre principal points,
object walks and hand-held paths, photo textures, object-like shapes, per-scene depth ranges and
photometric camera effects (``photometric.py``). docs/DATA.md lists their ranges.

**Environment.** PyOpenGL reads ``PYOPENGL_PLATFORM`` when it is first imported. This package sets
it to ``"egl"`` (headless GPU-less rendering through Mesa's EGL + llvmpipe) unless it is already
set, so import it before anything that imports ``OpenGL`` or ``pyrender``; set
``PYOPENGL_PLATFORM=osmesa`` yourself to use OSMesa instead.

**Conventions** (docs/ARCHITECTURE.md): cameras are OpenCV (x right, y down, z forward), ``world_from_cam``
is camera-to-world with the camera axes as rotation columns; ``K`` is in pixels with pixel
(row i, col j) centred at (j + 0.5, i + 0.5). OpenGL (and pyrender) cameras look down -z with y
up: ``world_from_gl = world_from_cam @ diag(1, -1, -1, 1)``. The world frame is z-up; it is *not*
view 0's frame: use ``relative_to_first`` in ``iris_train.data`` to get the canonical frame.

**Scale.** Classic kinds: cameras sit 0.55-0.65 (rooms 0.5-0.6) from the point they look at,
objects lie within about 0.3 of it, so visible geometry is at camera depth ~0.25-0.95 (the model
samples [0.1, 1.0]); room walls behind the objects may reach ~1.25 in corners. Capture kinds:
world and cameras are scaled so that the scene's median valid depth is drawn from 0.25-0.75
(``render.py``).

**Rendering.** Each view is rendered at ``SUPERSAMPLE`` x the output size without MSAA and
reduced with an area filter (``cv2.INTER_AREA``). The factor is odd so that the centre
sub-pixel of every output pixel sits exactly on the output pixel centre: depth is read there, so
``depth`` is the exact z-depth of the surface at the pixel centre (pyrender's built-in 4x MSAA
would resolve depth from an off-centre sample, measured 0.16-0.2 px away). Pixels with no
geometry have depth 0 (never inf). ``downsample_scene`` makes the 64 and 128 training sizes from
one 256 render.
"""
from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from . import photometric  # noqa: E402
from .build import (ALL_KINDS, DEPTH_TARGET_RANGE, GENERATOR_VERSION, KIND_VERSIONS, KINDS,  # noqa: E402
                    build_scene_spec, capture_kind, resolve_kind)
from .cameras import look_at  # noqa: E402
from .capture import CAPTURE_KINDS  # noqa: E402
from .paths import FOV_RANGE_DEG, PRINCIPAL_OFFSET  # noqa: E402
from .render import downsample_scene, render_spec  # noqa: E402
from .scene import (GL_FROM_CV, MARKER_COLORS, MARKER_RADIUS, MARKER_SUBDIVISIONS,  # noqa: E402
                    SUPERSAMPLE, LightSpec, MeshSpec, SceneData, SceneSpec)

__all__ = ["SceneData", "SceneSpec", "MeshSpec", "LightSpec", "KINDS", "CAPTURE_KINDS", "ALL_KINDS",
           "GENERATOR_VERSION", "KIND_VERSIONS", "SUPERSAMPLE", "FOV_RANGE_DEG", "PRINCIPAL_OFFSET",
           "DEPTH_TARGET_RANGE", "MARKER_COLORS", "MARKER_RADIUS", "MARKER_SUBDIVISIONS",
           "build_scene_spec", "render_spec", "render_scene", "downsample_scene", "look_at",
           "capture_kind", "resolve_kind", "kind_version", "photometric", "GL_FROM_CV", "LARGE_RENDER"]


#: Capture renders with at least this many rows are not supersampled (see ``render_scene``).
LARGE_RENDER = 192


def kind_version(kind: str) -> int:
    """The generator version of ``kind`` (what a cached scene of that kind must carry)."""
    return KIND_VERSIONS[kind]


def render_scene(seed: int, n_views: int = 8, size: tuple[int, int] = (64, 64),
                 kind: str | None = None, markers: bool = False, clean: bool = False,
                 supersample: int | None = None) -> SceneData:
    """Generate and render the synthetic scene of ``seed``; same seed -> bitwise same arrays.

    ``size`` is (height, width); ``kind`` is None (a classic kind drawn from the seed),
    "turntable", "room", a capture kind or "capture" (the seed's capture kind); ``markers`` adds
    small emissive spheres at ``meta["markers"]["centers_world"]`` (for tests). Capture kinds get
    the seed's photometric camera effects unless ``clean`` (classic kinds never do; depth, poses
    and K are the same either way). ``supersample`` None: ``SUPERSAMPLE``, except capture renders
    of ``LARGE_RENDER`` rows or more, which are rendered without (they are made to be area-
    downsampled to the training sizes, which anti-aliases them; 3x3 would cost 4x the time).
    """
    spec = build_scene_spec(seed, n_views, size, kind, markers)
    if supersample is None:
        large = spec.kind in CAPTURE_KINDS and spec.size[0] >= LARGE_RENDER
        supersample = 1 if large else SUPERSAMPLE
    scene = render_spec(spec, supersample)
    if spec.kind in CAPTURE_KINDS and not clean:
        scene = SceneData(photometric.apply(scene.images, seed), scene.world_from_cam, scene.K,
                          scene.depth, {**scene.meta, "photometric": True})
    return scene
