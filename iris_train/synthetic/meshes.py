"""Meshes of the classic kinds: textured primitives, quads, the ground disc, markers.

Every mesh is unshared and UV-mapped per face (``triplanar_mesh``), so any triangle soup can be
textured without seams inside a face; the capture kinds' shapes (``shapes.py``) reuse it.
"""
from __future__ import annotations

import math

import numpy as np

from .scene import MARKER_COLORS, MARKER_RADIUS, MARKER_SUBDIVISIONS, MeshSpec
from .textures import make_texture, random_colour
def triplanar_mesh(vertices: np.ndarray, faces: np.ndarray, smooth: bool, tex_scale: float,
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


def random_primitive(rng: np.random.Generator, radius: float):
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


def random_rotation(rng: np.random.Generator, upright: bool) -> np.ndarray:
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


def object_mesh(rng: np.random.Generator, centre_xy: np.ndarray, radius: float,
                 floor_z: float = 0.0) -> MeshSpec:
    """A random textured primitive resting on the floor at ``centre_xy``."""
    mesh, smooth, name = random_primitive(rng, radius)
    R = random_rotation(rng, upright=rng.random() < 0.6)
    v = np.asarray(mesh.vertices, dtype=np.float64) @ R.T
    v[:, :2] += centre_xy
    v[:, 2] += floor_z - v[:, 2].min()                   # rest on the floor
    faces = np.asarray(mesh.faces, dtype=np.int64)
    pos, nrm, uv, f = triplanar_mesh(v, faces, smooth, tex_scale=rng.uniform(0.05, 0.2),
                                      uv_offset=rng.uniform(0, 1, size=2))
    textured = rng.random() < 0.85
    return MeshSpec(pos, nrm, uv, f, make_texture(rng) if textured else None,
                    color=tuple(random_colour(rng, 0.6, 1.0) if textured else random_colour(rng)),
                    roughness=float(rng.uniform(0.4, 1.0)), name=name)


def box_room_walls(x0: float, x1: float, y0: float, y1: float, z1: float) -> dict[str, list]:
    """The six quads of a box room over [x0, x1] x [y0, y1] x [0, z1] (floor z = 0), by name,
    each counter-clockwise as seen from inside the room (normals point inwards)."""
    return {
        "floor": [[x0, y0, 0], [x1, y0, 0], [x1, y1, 0], [x0, y1, 0]],
        "ceiling": [[x0, y0, z1], [x0, y1, z1], [x1, y1, z1], [x1, y0, z1]],
        "back": [[x0, y1, 0], [x1, y1, 0], [x1, y1, z1], [x0, y1, z1]],
        "front": [[x1, y0, 0], [x0, y0, 0], [x0, y0, z1], [x1, y0, z1]],
        "left": [[x0, y0, 0], [x0, y1, 0], [x0, y1, z1], [x0, y0, z1]],
        "right": [[x1, y1, 0], [x1, y0, 0], [x1, y0, z1], [x1, y1, z1]],
    }


def quad(corners: np.ndarray, tex: np.ndarray | None, uv_extent: tuple[float, float],
          color=(1.0, 1.0, 1.0), roughness=0.9, name="quad") -> MeshSpec:
    """A quad from 4 corners [4, 3] given counter-clockwise as seen from the front side."""
    c = np.asarray(corners, dtype=np.float64)
    n = np.cross(c[1] - c[0], c[3] - c[0])
    n /= np.linalg.norm(n)
    uv = np.array([[0, 0], [uv_extent[0], 0], [uv_extent[0], uv_extent[1]], [0, uv_extent[1]]])
    return MeshSpec(c.astype(np.float32), np.repeat(n[None], 4, 0).astype(np.float32),
                    uv.astype(np.float32), np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32), tex,
                    color=tuple(color), roughness=roughness, name=name)


def disc(radius: float, tex: np.ndarray | None, tex_scale: float, sections: int = 64) -> MeshSpec:
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


def marker_mesh(centre: np.ndarray, index: int) -> MeshSpec:
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=MARKER_SUBDIVISIONS, radius=MARKER_RADIUS)
    v = np.asarray(m.vertices) + centre
    nrm = np.asarray(m.vertex_normals)
    colour = tuple(c / 255.0 for c in MARKER_COLORS[index % len(MARKER_COLORS)])
    return MeshSpec(v.astype(np.float32), nrm.astype(np.float32), np.zeros((len(v), 2), np.float32),
                    np.asarray(m.faces, dtype=np.uint32), None, color=(0.0, 0.0, 0.0),
                    roughness=1.0, emissive=colour, marker_index=index, name=f"marker{index}")


def place_discs(rng: np.random.Generator, n: int, region_radius: float, r_lo: float,
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
