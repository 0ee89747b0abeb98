"""Synthetic multi-view scenes rendered with pyrender (OpenGL rasterisation, headless through EGL).

Why pyrender: see ``docs/DATA.md`` (measured with ``benchmarks/renderer_choice.py``): it renders a
64x64 view, 3x3 supersampled, with exact z-depth in ~8 ms, where Mitsuba 3 (``scalar_rgb``) needs
~190 ms per view (64 samples per pixel) to get its Monte-Carlo noise down to ~36 dB PSNR.

**Environment.** PyOpenGL reads ``PYOPENGL_PLATFORM`` when it is first imported. This module sets
it to ``"egl"`` (headless GPU-less rendering through Mesa's EGL + llvmpipe) unless it is already
set, so import this module before anything that imports ``OpenGL`` or ``pyrender``; set
``PYOPENGL_PLATFORM=osmesa`` yourself to use OSMesa instead.

**Conventions** (DESIGN.md): cameras are OpenCV (x right, y down, z forward), ``world_from_cam``
is camera-to-world with the camera axes as rotation columns; ``K`` is in pixels with pixel
(row i, col j) centred at (j + 0.5, i + 0.5) and the principal point at the image centre. OpenGL
(and pyrender) cameras look down -z with y up: ``world_from_gl = world_from_cam @ diag(1, -1, -1, 1)``.
The world frame is z-up (floor at z = 0); it is *not* view 0's frame: use
``relative_to_first`` in ``iris_train.data`` to get the canonical frame.

**Scale.** Cameras sit 0.55-0.65 (rooms 0.5-0.6) from the point they look at, objects lie within
about 0.3 of it, so visible geometry is at camera depth ~0.25-0.95 (the model samples [0.1, 1.0]);
room walls behind the objects may reach ~1.25 in corners (96% of room pixels lie in 0.25-0.95).

**Rendering.** Each view is rendered at ``SUPERSAMPLE`` x the output size without MSAA and
reduced with an area filter (``cv2.INTER_AREA``). The factor is odd so that the centre sub-pixel of
every output pixel sits exactly on the output pixel centre: depth is read there, so ``depth`` is
the exact z-depth of the surface at the pixel centre (pyrender's built-in 4x MSAA would resolve
depth from an off-centre sample, measured 0.16-0.2 px away). Pixels with no geometry have
depth 0 (never inf).
"""
from __future__ import annotations

import contextlib
import functools
import math
import os
from dataclasses import dataclass, field
from typing import Any

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from iris_runtime.errors import InputError  # noqa: E402

__all__ = ["SceneData", "SceneSpec", "MeshSpec", "LightSpec", "KINDS", "GENERATOR_VERSION",
           "SUPERSAMPLE", "build_scene_spec", "render_spec", "render_scene", "look_at",
           "GL_FROM_CV"]

#: Bump when the generator's output changes, so cached scenes are regenerated.
GENERATOR_VERSION = 1
#: Scene kinds; ``kind=None`` draws one from the seed.
KINDS = ("turntable", "room")
#: Supersampling factor per axis (odd: see the module docstring). 3 -> 9 samples per pixel.
SUPERSAMPLE = 3
#: Marker colours (RGB, emissive on black metal: a fully covered pixel has this colour to within a
#: few levels; channels are 0 or 255 because pyrender applies a gamma curve to emissive values).
MARKER_COLORS = ((255, 0, 255), (0, 255, 255), (255, 255, 0), (0, 255, 0))
#: Marker sphere radius in scene units (~1.3-1.8 px at 64x64 and depth 0.6).
MARKER_RADIUS = 0.015
#: Icosphere subdivisions of markers: its faces lie at least 0.993 r from the centre.
MARKER_SUBDIVISIONS = 3
#: Flip between OpenCV and OpenGL camera axes (its own inverse).
GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])
_ZNEAR, _ZFAR = 0.02, 5.0


# ----------------------------------------------------------------------------------------------
# Output and backend-neutral scene description
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SceneData:
    """One multi-view scene. Views are ordered along the camera trajectory (the "Seq" order).

    images:         uint8   [V, H, W, 3] RGB
    world_from_cam: float64 [V, 4, 4]    camera-to-world, OpenCV axes
    K:              float64 [3, 3]       pixels, shared by all views, principal point at the centre
    depth:          float32 [V, H, W]    camera z-depth at pixel centres (along the optical axis,
                                         not euclidean distance); 0 where there is no geometry
    meta:           dict                 JSON-serialisable facts (seed, kind, fov, markers, ...);
                                         with ``markers=True`` also ``marker_coverage`` float32
                                         [V, M, H, W] (a numpy array: fraction of each pixel covered
                                         by marker m drawn alone, i.e. ignoring occlusion)
    """

    images: np.ndarray
    world_from_cam: np.ndarray
    K: np.ndarray
    depth: np.ndarray
    meta: dict = field(default_factory=dict)

    @property
    def n_views(self) -> int:
        return int(self.images.shape[0])

    @property
    def size(self) -> tuple[int, int]:
        """(height, width)."""
        return int(self.images.shape[1]), int(self.images.shape[2])


@dataclass
class MeshSpec:
    """A triangle mesh in world coordinates with per-vertex normals and texture coordinates."""

    positions: np.ndarray           # [N, 3] float32
    normals: np.ndarray             # [N, 3] float32, unit
    uvs: np.ndarray                 # [N, 2] float32 (textures repeat outside [0, 1])
    faces: np.ndarray               # [F, 3] uint32, counter-clockwise seen from the normal side
    texture: np.ndarray | None      # uint8 [h, w, 3] RGB base colour texture, or None
    color: tuple[float, float, float] = (1.0, 1.0, 1.0)   # base colour factor (multiplies texture)
    roughness: float = 0.8
    emissive: tuple[float, float, float] | None = None    # markers: unlit constant colour
    marker_index: int = -1                                # >= 0 for marker spheres
    name: str = ""


@dataclass
class LightSpec:
    kind: str                                  # "directional" or "point"
    color: tuple[float, float, float]
    intensity: float                           # pyrender units (lux for directional, cd for point)
    position: np.ndarray | None = None         # [3] world, point lights
    direction: np.ndarray | None = None        # [3] world, direction the light travels


@dataclass
class SceneSpec:
    """Everything a renderer needs: geometry, materials, lights, background and cameras."""

    kind: str
    seed: int
    size: tuple[int, int]                      # (height, width)
    K: np.ndarray                              # [3, 3] float64 pixels at ``size``
    world_from_cam: np.ndarray                 # [V, 4, 4] float64 OpenCV
    meshes: list[MeshSpec]
    lights: list[LightSpec]
    ambient: tuple[float, float, float]
    background: tuple[float, float, float]     # RGB in [0, 1] where no geometry is seen
    markers_world: np.ndarray                  # [M, 3] float64 marker centres (M may be 0)
    meta: dict[str, Any]


# ----------------------------------------------------------------------------------------------
# Textures (scikit-image's bundled photos + procedural patterns; no downloads)
# ----------------------------------------------------------------------------------------------

_PHOTO_NAMES = ("astronaut", "coffee", "chelsea", "rocket", "colorwheel", "immunohistochemistry",
                "brick", "grass", "gravel", "camera", "moon", "text", "page", "clock", "coins")
_TEXTURE_SIZE = 128


@functools.lru_cache(maxsize=1)
def _photos() -> tuple[np.ndarray, ...]:
    """The bundled photos as uint8 RGB, shrunk so that their short side is 256 (load once)."""
    import skimage.data

    out = []
    for name in _PHOTO_NAMES:
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


def _random_colour(rng: np.random.Generator, lo: float = 0.15, hi: float = 1.0) -> np.ndarray:
    return rng.uniform(lo, hi, size=3)


def _make_texture(rng: np.random.Generator) -> np.ndarray:
    """A random ``uint8 [128, 128, 3]`` texture: a photo crop (maybe tinted) or a pattern."""
    n = _TEXTURE_SIZE
    r = rng.random()
    if r < 0.6:
        photos = _photos()
        a = photos[rng.integers(len(photos))]
        side = int(rng.integers(64, min(a.shape[:2]) + 1))
        y = int(rng.integers(0, a.shape[0] - side + 1))
        x = int(rng.integers(0, a.shape[1] - side + 1))
        tex = cv2.resize(a[y:y + side, x:x + side], (n, n), interpolation=cv2.INTER_AREA)
        if rng.random() < 0.5:          # tint grey-ish photos so the palette is varied
            tex = np.clip(tex * (0.4 + 0.6 * _random_colour(rng)), 0, 255)
        return tex.astype(np.uint8)
    c0 = _random_colour(rng, 0.0, 1.0) * 255
    c1 = _random_colour(rng, 0.0, 1.0) * 255
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
# Meshes
# ----------------------------------------------------------------------------------------------

def _triplanar_mesh(vertices: np.ndarray, faces: np.ndarray, smooth: bool, tex_scale: float,
                    uv_offset: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Unshare vertices and give each face UVs from its dominant axis (box/triplanar mapping).

    Works for any primitive without seams inside a face. ``smooth`` keeps the shared vertex normals
    (spheres, capsules, tori), otherwise face normals are used (boxes, cylinders).
    """
    v = vertices[faces]                                             # [F, 3, 3]
    fn = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-12)
    if smooth:
        vn = np.zeros_like(vertices)
        np.add.at(vn, faces.ravel(), np.repeat(fn, 3, axis=0))
        vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)
        normals = vn[faces]
    else:
        normals = np.repeat(fn[:, None, :], 3, axis=1)
    axis = np.argmax(np.abs(fn), axis=1)                            # [F]
    keep = np.array([[1, 2], [0, 2], [0, 1]])[axis]                 # [F, 2] the other two axes
    uv = np.take_along_axis(v, keep[:, None, :].repeat(3, axis=1), axis=2)   # [F, 3, 2]
    uv = uv / tex_scale + uv_offset
    n = faces.shape[0] * 3
    return (v.reshape(n, 3).astype(np.float32), normals.reshape(n, 3).astype(np.float32),
            uv.reshape(n, 2).astype(np.float32), np.arange(n, dtype=np.uint32).reshape(-1, 3))


def _random_primitive(rng: np.random.Generator, radius: float):
    """A trimesh primitive of bounding radius about ``radius``; returns (mesh, smooth, name)."""
    import trimesh

    kind = str(rng.choice(["box", "icosphere", "cylinder", "capsule", "torus", "cone"]))
    r = radius
    if kind == "box":
        ext = rng.uniform(0.6, 1.4, size=3)
        ext = ext / np.linalg.norm(ext) * 2 * r
        return trimesh.creation.box(extents=ext), False, kind
    if kind == "icosphere":
        return trimesh.creation.icosphere(subdivisions=3, radius=r * rng.uniform(0.7, 1.0)), True, kind
    if kind == "cylinder":
        h = r * rng.uniform(0.8, 1.8)
        rad = math.sqrt(max(r * r - (h / 2) ** 2, (0.3 * r) ** 2))
        return trimesh.creation.cylinder(radius=rad, height=h, sections=32), False, kind
    if kind == "capsule":
        rad = r * rng.uniform(0.35, 0.55)
        h = max(2 * (r - rad), 0.01)
        return trimesh.creation.capsule(height=h, radius=rad, count=[16, 16]), True, kind
    if kind == "torus":
        minor = r * rng.uniform(0.2, 0.35)
        return trimesh.creation.torus(major_radius=r - minor, minor_radius=minor,
                                      major_sections=32, minor_sections=16), True, kind
    h = r * rng.uniform(1.0, 1.8)
    return trimesh.creation.cone(radius=r * rng.uniform(0.6, 0.9), height=h, sections=32), False, kind


def _random_rotation(rng: np.random.Generator, upright: bool) -> np.ndarray:
    """A rotation [3, 3]: about z only when ``upright`` (objects resting on the floor)."""
    a = rng.uniform(0, 2 * np.pi)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    if upright:
        return Rz
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def _object_mesh(rng: np.random.Generator, centre_xy: np.ndarray, radius: float,
                 floor_z: float = 0.0) -> MeshSpec:
    """A random textured primitive resting on the floor at ``centre_xy``."""
    mesh, smooth, name = _random_primitive(rng, radius)
    R = _random_rotation(rng, upright=rng.random() < 0.6)
    v = np.asarray(mesh.vertices, dtype=np.float64) @ R.T
    v[:, :2] += centre_xy
    v[:, 2] += floor_z - v[:, 2].min()                   # rest on the floor
    faces = np.asarray(mesh.faces, dtype=np.int64)
    pos, nrm, uv, f = _triplanar_mesh(v, faces, smooth, tex_scale=rng.uniform(0.05, 0.2),
                                      uv_offset=rng.uniform(0, 1, size=2))
    textured = rng.random() < 0.85
    return MeshSpec(pos, nrm, uv, f, _make_texture(rng) if textured else None,
                    color=tuple(_random_colour(rng, 0.6, 1.0) if textured else _random_colour(rng)),
                    roughness=float(rng.uniform(0.4, 1.0)), name=name)


def _quad(corners: np.ndarray, tex: np.ndarray | None, uv_extent: tuple[float, float],
          color=(1.0, 1.0, 1.0), roughness=0.9, name="quad") -> MeshSpec:
    """A quad from 4 corners [4, 3] given counter-clockwise as seen from the front side."""
    c = np.asarray(corners, dtype=np.float64)
    n = np.cross(c[1] - c[0], c[3] - c[0])
    n /= np.linalg.norm(n)
    uv = np.array([[0, 0], [uv_extent[0], 0], [uv_extent[0], uv_extent[1]], [0, uv_extent[1]]])
    return MeshSpec(c.astype(np.float32), np.repeat(n[None], 4, 0).astype(np.float32),
                    uv.astype(np.float32), np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32), tex,
                    color=tuple(color), roughness=roughness, name=name)


def _disc(radius: float, tex: np.ndarray | None, tex_scale: float, sections: int = 64) -> MeshSpec:
    """A flat disc at z = 0 facing +z (the turntable's ground)."""
    a = np.linspace(0, 2 * np.pi, sections, endpoint=False)
    ring = np.stack([radius * np.cos(a), radius * np.sin(a), np.zeros_like(a)], axis=1)
    pos = np.concatenate([np.zeros((1, 3)), ring])
    faces = np.stack([np.zeros(sections, int), 1 + np.arange(sections),
                      1 + (np.arange(sections) + 1) % sections], axis=1)
    nrm = np.tile([0.0, 0.0, 1.0], (sections + 1, 1))
    uv = pos[:, :2] / tex_scale
    return MeshSpec(pos.astype(np.float32), nrm.astype(np.float32), uv.astype(np.float32),
                    faces.astype(np.uint32), tex, roughness=0.9, name="ground")


def _marker_mesh(centre: np.ndarray, index: int) -> MeshSpec:
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=MARKER_SUBDIVISIONS, radius=MARKER_RADIUS)
    v = np.asarray(m.vertices) + centre
    nrm = np.asarray(m.vertex_normals)
    colour = tuple(c / 255.0 for c in MARKER_COLORS[index % len(MARKER_COLORS)])
    return MeshSpec(v.astype(np.float32), nrm.astype(np.float32), np.zeros((len(v), 2), np.float32),
                    np.asarray(m.faces, dtype=np.uint32), None, color=(0.0, 0.0, 0.0),
                    roughness=1.0, emissive=colour, marker_index=index, name=f"marker{index}")


def _place_discs(rng: np.random.Generator, n: int, region_radius: float, r_lo: float,
                 r_hi: float) -> list[tuple[np.ndarray, float]]:
    """Up to ``n`` non-overlapping discs (centre [2], radius) inside a disc of ``region_radius``."""
    out: list[tuple[np.ndarray, float]] = []
    for _ in range(n * 30):
        if len(out) == n:
            break
        r = rng.uniform(r_lo, r_hi)
        rho = region_radius * math.sqrt(rng.random())
        a = rng.uniform(0, 2 * np.pi)
        c = np.array([rho * math.cos(a), rho * math.sin(a)])
        if all(np.linalg.norm(c - c2) > r + r2 + 0.01 for c2, r2 in out):
            out.append((c, r))
    return out


# ----------------------------------------------------------------------------------------------
# Cameras
# ----------------------------------------------------------------------------------------------

def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0), roll: float = 0.0) -> np.ndarray:
    """``world_from_cam [4, 4]`` (OpenCV: x right, y down, z forward) at ``eye`` looking at ``target``.

    ``roll`` (radians) turns the camera about its optical axis.
    """
    eye = np.asarray(eye, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))     # right = forward x up
    x /= np.linalg.norm(x)
    y = np.cross(z, x)                                    # down, so that x, y, z is right-handed
    if roll:
        c, s = math.cos(roll), math.sin(roll)
        x, y = c * x + s * y, -s * x + c * y
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
    return T


def _arc_cameras(rng: np.random.Generator, n_views: int, target: np.ndarray, az_centre: float,
                 elev_range: tuple[float, float], dist_range: tuple[float, float] = (0.55, 0.65)
                 ) -> tuple[np.ndarray, dict]:
    """Cameras ordered along an arc around ``target``; arc span 10-90 degrees, slight jitter."""
    span = math.radians(rng.uniform(10.0, 90.0))
    elev0 = math.radians(rng.uniform(*elev_range))
    elev_drift = math.radians(rng.uniform(-8.0, 8.0))        # the arc may climb or descend
    dist = rng.uniform(*dist_range)
    direction = 1.0 if rng.random() < 0.5 else -1.0
    t = np.linspace(-0.5, 0.5, n_views) if n_views > 1 else np.zeros(1)
    poses = []
    for k in range(n_views):
        az = az_centre + direction * span * t[k] + math.radians(rng.normal(0, 0.5))
        el = elev0 + elev_drift * t[k] + math.radians(rng.normal(0, 0.7))
        d = dist + rng.normal(0, 0.01)
        eye = target + d * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az),
                                     math.sin(el)])
        aim = target + rng.normal(0, 0.01, size=3)
        poses.append(look_at(eye, aim, roll=math.radians(rng.normal(0, 1.5))))
    info = {"arc_deg": math.degrees(span), "elevation_deg": math.degrees(elev0),
            "distance": float(dist)}
    return np.stack(poses), info


def _intrinsics(size: tuple[int, int], yfov: float) -> np.ndarray:
    h, w = size
    f = (h / 2.0) / math.tan(yfov / 2.0)
    return np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------------------------
# Scene kinds
# ----------------------------------------------------------------------------------------------

def _lights_turntable(rng: np.random.Generator) -> list[LightSpec]:
    lights = []
    for _ in range(int(rng.integers(1, 4))):
        az, el = rng.uniform(0, 2 * np.pi), rng.uniform(math.radians(20), math.radians(80))
        d = -np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        lights.append(LightSpec("directional", tuple(0.6 + 0.4 * rng.random(3)),
                                float(rng.uniform(1.0, 4.0)), direction=d))
    return lights


def _build_turntable(rng: np.random.Generator, n_views: int) -> tuple[list, list, tuple, tuple, np.ndarray, np.ndarray, dict]:
    meshes = []
    ground_r = rng.uniform(0.36, 0.44)
    meshes.append(_disc(ground_r, _make_texture(rng), tex_scale=rng.uniform(0.1, 0.4)))
    placed = _place_discs(rng, int(rng.integers(3, 7)), region_radius=0.18, r_lo=0.05, r_hi=0.1)
    for c, r in placed:
        meshes.append(_object_mesh(rng, c, r))
    target = np.array([0.0, 0.0, rng.uniform(0.03, 0.07)])
    world_from_cam, info = _arc_cameras(rng, n_views, target, rng.uniform(0, 2 * np.pi), (12.0, 45.0))
    ambient = tuple(rng.uniform(0.1, 0.35) * (0.8 + 0.2 * rng.random(3)))
    background = tuple(rng.uniform(0.0, 1.0, 3))
    # Markers float around the objects, at heights the cameras see.
    markers = np.array([[0.09, 0.0, 0.16], [-0.07, 0.08, 0.12], [0.0, -0.1, 0.2], [0.05, 0.05, 0.24]])
    info.update(n_objects=len(placed))
    return meshes, _lights_turntable(rng), ambient, background, world_from_cam, markers, info


def _build_room(rng: np.random.Generator, n_views: int):
    """A box room (floor z = 0) seen from inside; the objects stand near the back wall (+y)."""
    meshes = []
    half_w = rng.uniform(0.55, 0.75)                 # room spans x in [-half_w, half_w]
    gap = rng.uniform(0.26, 0.32)                    # objects' centre to the back wall
    y_back = gap
    y_front = -(0.65 + 0.25)                         # cameras (<= 0.65 away) stay inside
    height = rng.uniform(0.55, 0.8)
    x0, x1, y0, y1, z1 = -half_w, half_w, y_front, y_back, height
    # Quads counter-clockwise as seen from inside the room (normals point inwards).
    walls = {
        "floor": [[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]],
        "ceiling": [[x0, y0, z1], [x0, y1, z1], [x1, y1, z1], [x1, y0, z1]],
        "back": [[x0, y1, 0], [x1, y1, 0], [x1, y1, z1], [x0, y1, z1]],
        "front": [[x1, y0, 0], [x0, y0, 0], [x0, y0, z1], [x1, y0, z1]],
        "left": [[x0, y0, 0], [x0, y1, 0], [x0, y1, z1], [x0, y0, z1]],
        "right": [[x1, y1, 0], [x1, y0, 0], [x1, y0, z1], [x1, y1, z1]],
    }
    for name, corners in walls.items():
        c = np.asarray(corners, dtype=np.float64)
        w_len = np.linalg.norm(c[1] - c[0])
        h_len = np.linalg.norm(c[3] - c[0])
        scale = rng.uniform(0.15, 0.5)
        meshes.append(_quad(c, _make_texture(rng), (w_len / scale, h_len / scale),
                            color=tuple(_random_colour(rng, 0.6, 1.0)), name=name))
    # A "painting" on the back wall and a box against a side wall add structure far from centre.
    pw, ph = rng.uniform(0.15, 0.3), rng.uniform(0.1, 0.2)
    px, pz = rng.uniform(-0.2, 0.2), rng.uniform(0.2, max(0.25, height - ph - 0.05))
    yb = y1 - 0.002
    meshes.append(_quad([[px - pw / 2, yb, pz], [px + pw / 2, yb, pz], [px + pw / 2, yb, pz + ph],
                         [px - pw / 2, yb, pz + ph]], _make_texture(rng), (1.0, 1.0), name="painting"))
    side = -1 if rng.random() < 0.5 else 1
    meshes.append(_object_mesh(rng, np.array([side * (half_w - 0.08), rng.uniform(-0.2, 0.1)]), 0.07))
    # The object cluster, centred at (0, 0) on the floor.
    placed = _place_discs(rng, int(rng.integers(3, 6)), region_radius=0.14, r_lo=0.05, r_hi=0.09)
    for c, r in placed:
        meshes.append(_object_mesh(rng, c, r))
    target = np.array([0.0, 0.0, rng.uniform(0.04, 0.09)])
    # Cameras on the -y side looking towards the back wall (azimuth -90 deg +- arc / 2).
    # Closer than on the turntable (0.5-0.6) so that the back wall stays near depth 1.
    world_from_cam, info = _arc_cameras(rng, n_views, target, -np.pi / 2 + rng.uniform(-0.15, 0.15),
                                        (8.0, 35.0), dist_range=(0.5, 0.6))
    # Point lights under the ceiling, plus ambient.
    lights = []
    for _ in range(int(rng.integers(1, 3))):
        p = np.array([rng.uniform(x0 + 0.1, x1 - 0.1), rng.uniform(y0 + 0.2, y1 - 0.1), z1 - 0.05])
        lights.append(LightSpec("point", tuple(0.6 + 0.4 * rng.random(3)),
                                float(rng.uniform(0.3, 1.0)), position=p))
    ambient = tuple(rng.uniform(0.15, 0.4) * (0.8 + 0.2 * rng.random(3)))
    markers = np.array([[0.09, -0.02, 0.16], [-0.08, 0.05, 0.13], [0.0, -0.1, 0.21], [0.04, 0.06, 0.25]])
    info.update(n_objects=len(placed) + 1, room_half_width=float(half_w), room_height=float(height))
    return meshes, lights, ambient, (0.0, 0.0, 0.0), world_from_cam, markers, info


def build_scene_spec(seed: int, n_views: int = 8, size: tuple[int, int] = (64, 64),
                     kind: str | None = None, markers: bool = False) -> SceneSpec:
    """The random scene of ``seed`` as a renderer-neutral description (deterministic per seed)."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError(f"seed: expected a non-negative int, got {seed!r}")
    if not isinstance(n_views, (int, np.integer)) or n_views < 1:
        raise InputError(f"n_views: expected a positive int, got {n_views!r}")
    if (len(size) != 2 or not all(isinstance(s, (int, np.integer)) and s > 0 for s in size)):
        raise InputError(f"size: expected (height, width) positive ints, got {size!r}")
    rng = np.random.default_rng([int(seed), 0x1815])
    kind_drawn = KINDS[int(rng.integers(len(KINDS)))]     # drawn always, so streams do not shift
    kind = kind_drawn if kind is None else kind
    if kind not in KINDS:
        raise InputError(f"kind: expected one of {KINDS} or None, got {kind!r}")
    yfov = math.radians(rng.uniform(40.0, 70.0))
    build = _build_turntable if kind == "turntable" else _build_room
    meshes, lights, ambient, background, world_from_cam, marker_pts, info = build(rng, int(n_views))
    if markers:
        meshes += [_marker_mesh(p, i) for i, p in enumerate(marker_pts)]
    else:
        marker_pts = np.zeros((0, 3))
    K = _intrinsics(tuple(int(s) for s in size), yfov)
    meta = {"seed": int(seed), "kind": kind, "generator_version": GENERATOR_VERSION,
            "yfov_deg": math.degrees(yfov), "supersample": SUPERSAMPLE,
            "depth_background": 0.0, "world_up": [0.0, 0.0, 1.0], **info}
    return SceneSpec(kind, int(seed), (int(size[0]), int(size[1])), K, world_from_cam, meshes,
                     lights, ambient, background, marker_pts, meta)


# ----------------------------------------------------------------------------------------------
# pyrender backend
# ----------------------------------------------------------------------------------------------

@contextlib.contextmanager
def _single_sample_framebuffers():
    """Make pyrender allocate its 'multisample' framebuffer with 0 samples (plain buffers).

    pyrender hard-codes 4x MSAA and resolves depth from one off-centre sample; we supersample
    ourselves instead and read depth at pixel centres. The patch is scoped to our render calls.
    """
    import pyrender.renderer as prr

    original = prr.glRenderbufferStorageMultisample

    def storage(target, samples, fmt, width, height):
        return original(target, 0, fmt, width, height)

    prr.glRenderbufferStorageMultisample = storage
    try:
        yield
    finally:
        prr.glRenderbufferStorageMultisample = original


@functools.lru_cache(maxsize=4)
def _renderer(width: int, height: int):
    """One offscreen renderer (an EGL context) per size and process, created on first use."""
    try:
        import pyrender
        return pyrender.OffscreenRenderer(width, height)
    except Exception as e:  # EGL missing/broken: say what to do
        raise RuntimeError(
            f"cannot create a pyrender offscreen renderer with PYOPENGL_PLATFORM="
            f"{os.environ.get('PYOPENGL_PLATFORM')!r} ({type(e).__name__}: {e}). Install Mesa's "
            f"EGL (libegl1) or set PYOPENGL_PLATFORM=osmesa before importing iris_train.synthetic."
        ) from e


def _pyrender_scene(spec: SceneSpec):
    import pyrender
    from pyrender.constants import GLTF

    scene = pyrender.Scene(bg_color=np.array([*spec.background, 1.0]), ambient_light=np.array(spec.ambient))
    sampler = pyrender.Sampler(magFilter=GLTF.LINEAR, minFilter=GLTF.LINEAR_MIPMAP_LINEAR,
                               wrapS=GLTF.REPEAT, wrapT=GLTF.REPEAT)
    marker_nodes = {}
    for m in spec.meshes:
        if m.emissive is not None:
            # Black metal reflects (almost) nothing: no diffuse, specular f0 = base colour = 0,
            # only Schlick's Fresnel term at grazing angles adds a few levels of 255.
            mat = pyrender.MetallicRoughnessMaterial(baseColorFactor=[0.0, 0.0, 0.0, 1.0],
                                                     metallicFactor=1.0, roughnessFactor=1.0,
                                                     emissiveFactor=list(m.emissive))
        else:
            tex = None
            if m.texture is not None:
                tex = pyrender.Texture(source=m.texture, source_channels="RGB", sampler=sampler)
            mat = pyrender.MetallicRoughnessMaterial(baseColorFactor=[*m.color, 1.0],
                                                     baseColorTexture=tex, metallicFactor=0.0,
                                                     roughnessFactor=float(m.roughness))
        prim = pyrender.Primitive(positions=m.positions, normals=m.normals, texcoord_0=m.uvs,
                                  indices=m.faces, material=mat, mode=GLTF.TRIANGLES)
        node = scene.add(pyrender.Mesh([prim], name=m.name))
        if m.marker_index >= 0:
            marker_nodes[m.marker_index] = node
    for light in spec.lights:
        pose = np.eye(4)
        if light.kind == "directional":
            # pyrender lights shine along their node's -z axis.
            z = -np.asarray(light.direction, dtype=np.float64)
            z /= np.linalg.norm(z)
            x = np.cross([0.0, 0.0, 1.0] if abs(z[2]) < 0.99 else [1.0, 0.0, 0.0], z)
            x /= np.linalg.norm(x)
            pose[:3, 0], pose[:3, 1], pose[:3, 2] = x, np.cross(z, x), z
            scene.add(pyrender.DirectionalLight(color=np.array(light.color), intensity=light.intensity),
                      pose=pose)
        else:
            pose[:3, 3] = light.position
            scene.add(pyrender.PointLight(color=np.array(light.color), intensity=light.intensity),
                      pose=pose)
    return scene, marker_nodes


def render_spec(spec: SceneSpec, supersample: int = SUPERSAMPLE) -> SceneData:
    """Render every camera of ``spec`` with pyrender (EGL); see the module docstring for AA/depth."""
    import pyrender

    if supersample < 1 or supersample % 2 == 0:
        raise InputError(f"supersample: expected an odd positive int, got {supersample}")
    h, w = spec.size
    s = supersample
    scene, marker_nodes = _pyrender_scene(spec)
    K = spec.K
    cam = pyrender.IntrinsicsCamera(fx=K[0, 0] * s, fy=K[1, 1] * s, cx=K[0, 2] * s, cy=K[1, 2] * s,
                                    znear=_ZNEAR, zfar=_ZFAR)
    cam_node = scene.add(cam, pose=np.eye(4))
    renderer = _renderer(w * s, h * s)
    V = spec.world_from_cam.shape[0]
    images = np.empty((V, h, w, 3), np.uint8)
    depth = np.empty((V, h, w), np.float32)
    coverage = np.zeros((V, len(marker_nodes), h, w), np.float32) if marker_nodes else None
    seg_colours = {node: np.array(MARKER_COLORS[i % len(MARKER_COLORS)], np.uint8)
                   for i, node in marker_nodes.items()}
    with _single_sample_framebuffers():
        for v in range(V):
            scene.set_pose(cam_node, spec.world_from_cam[v] @ GL_FROM_CV)
            colour, z = renderer.render(scene)
            # Area average of s x s sub-pixels = box-filtered anti-aliasing (in sRGB values).
            images[v] = cv2.resize(colour, (w, h), interpolation=cv2.INTER_AREA) if s > 1 else colour
            depth[v] = z[s // 2::s, s // 2::s]             # the sub-pixel at each pixel centre
            if coverage is not None:
                # One segmentation pass per marker, drawn alone: markers never hide each other.
                for i, node in marker_nodes.items():
                    seg, _ = renderer.render(scene, flags=pyrender.RenderFlags.SEG,
                                             seg_node_map={node: seg_colours[node]})
                    hit = np.all(seg == seg_colours[node], axis=-1).astype(np.float32)
                    coverage[v, i] = hit.reshape(h, s, w, s).mean(axis=(1, 3))
    meta = dict(spec.meta)
    if spec.markers_world.shape[0]:
        meta["markers"] = {"centers_world": spec.markers_world.tolist(), "radius": MARKER_RADIUS,
                           "colors": [list(MARKER_COLORS[i % len(MARKER_COLORS)])
                                      for i in range(spec.markers_world.shape[0])],
                           "subdivisions": MARKER_SUBDIVISIONS}
        meta["marker_coverage"] = coverage
    return SceneData(images=images, world_from_cam=spec.world_from_cam.astype(np.float64),
                     K=spec.K.astype(np.float64), depth=depth, meta=meta)


def render_scene(seed: int, n_views: int = 8, size: tuple[int, int] = (64, 64),
                 kind: str | None = None, markers: bool = False) -> SceneData:
    """Generate and render the synthetic scene of ``seed``; same seed -> bitwise same arrays.

    ``size`` is (height, width); ``kind`` is "turntable", "room" or None (drawn from the seed);
    ``markers`` adds small emissive spheres at ``meta["markers"]["centers_world"]`` (for tests).
    """
    return render_spec(build_scene_spec(seed, n_views, size, kind, markers))
