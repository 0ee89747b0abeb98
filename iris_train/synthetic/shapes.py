"""Object shapes of the capture kinds: beyond primitives, shapes that look like real objects.

Each builder returns ``(vertices [N, 3], faces [F, 3], smooth)`` in object units (bounding radius
about 1), and ``object_on_ground`` scales, turns, places
and textures it. Families: the classic primitives; superquadrics (boxes with rounded edges,
pillows, cushions, stars); solids of revolution with a random profile (vases, bottles, bowls,
cups); star-shaped prisms (extruded outlines); noise-displaced blobs (stones, fruit); and meshes of real objects that registry packages ship
(``packaged.py``).
"""
from __future__ import annotations

import functools
import math

import numpy as np

from .meshes import random_primitive, random_rotation, triplanar_mesh
from .scene import MeshSpec
from .textures import make_photo_texture, random_colour

#: Shape families and their draw weights.
FAMILIES = {"primitive": 0.12, "superquadric": 0.18, "revolved": 0.18, "prism": 0.1, "blob": 0.1,
            "packaged": 0.32}


@functools.lru_cache(maxsize=4)
def _unit_sphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    import trimesh
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def superquadric(rng: np.random.Generator):
    """A superquadric: every unit direction n of an icosphere moved to the surface point r n with
    r = F(n)^(-e1/2), F the inside-outside function (exact, no parametric poles)."""
    n, faces = _unit_sphere(4)
    e1, e2 = rng.uniform(0.1, 1.6, size=2)
    a = rng.uniform(0.5, 1.0, size=3)
    x, y, z = (np.abs(n[:, k]) / a[k] + 1e-12 for k in range(3))
    F = (x ** (2 / e2) + y ** (2 / e2)) ** (e2 / e1) + z ** (2 / e1)
    v = n * (F ** (-e1 / 2))[:, None]
    return v, faces, True


def revolved(rng: np.random.Generator):
    """A solid of revolution about z (vase, bottle, bowl, cup) from a smooth random profile."""
    import trimesh
    kind = rng.choice(["vase", "bottle", "bowl"])
    t = np.linspace(0.0, 1.0, 24)
    if kind == "bottle":
        neck = rng.uniform(0.55, 0.75)
        body, top = rng.uniform(0.6, 1.0), rng.uniform(0.15, 0.3)
        r = np.where(t < neck, body, top + (body - top) * np.clip(1 - (t - neck) / 0.15, 0, 1) ** 2)
        h = rng.uniform(1.6, 2.4)
    elif kind == "bowl":
        r = rng.uniform(0.8, 1.0) * np.sqrt(np.clip(t * (2 - t), 0, 1)) + 0.25 * (1 - t)
        h = rng.uniform(0.5, 0.9)
    else:
        k = rng.uniform(1.0, 3.0)
        r = 0.55 + 0.3 * np.sin(np.pi * k * t + rng.uniform(0, np.pi)) + rng.uniform(-0.2, 0.2) * t
        h = rng.uniform(1.2, 2.0)
    r = np.clip(r, 0.12, 1.0)
    # Closed at the bottom and top so that the solid has no hole.
    profile = np.concatenate([[[0.0, 0.0]], np.stack([r, t * h], 1), [[0.0, h]]])
    m = trimesh.creation.revolve(profile, sections=40)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64), True


def prism(rng: np.random.Generator):
    """A star-shaped outline (fan-triangulated from its centre) extruded along z."""
    import trimesh
    m = int(rng.integers(3, 13))
    angles = np.sort(rng.uniform(0, 2 * np.pi, m)) if rng.random() < 0.5 else \
        np.linspace(0, 2 * np.pi, m, endpoint=False)
    radii = rng.uniform(0.4, 1.0, m) if rng.random() < 0.6 else np.where(np.arange(m) % 2, 0.45, 1.0)
    outline = np.stack([radii * np.cos(angles), radii * np.sin(angles)], 1)
    verts = np.concatenate([[[0.0, 0.0]], outline])
    faces = np.stack([np.zeros(m, int), 1 + np.arange(m), 1 + (np.arange(m) + 1) % m], 1)
    mesh = trimesh.creation.extrude_triangulation(verts, faces, height=rng.uniform(0.3, 1.6))
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64), False


def blob(rng: np.random.Generator):
    """An icosphere displaced along its normals by a few random low-frequency waves."""
    n, faces = _unit_sphere(4)
    r = np.ones(len(n))
    for _ in range(int(rng.integers(2, 6))):
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        r += rng.uniform(0.05, 0.25) * np.sin(rng.uniform(1.0, 4.0) * (n @ d) + rng.uniform(0, 2 * np.pi))
    v = n * r[:, None] * rng.uniform(0.6, 1.0, size=3)
    return v, faces, True


def primitive(rng: np.random.Generator):
    mesh, smooth, _ = random_primitive(rng, 1.0)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64), smooth


def packaged(rng: np.random.Generator):
    from .packaged import random_packaged
    v, f, _ = random_packaged(rng)
    return v, f, True


_BUILDERS = {"primitive": primitive, "superquadric": superquadric, "revolved": revolved,
             "prism": prism, "blob": blob, "packaged": packaged}


def random_shape(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, bool, str]:
    """``(vertices [N, 3], faces [F, 3], smooth, family)`` of a random family, normalised to a
    bounding radius of 1 about its centre."""
    names = list(FAMILIES)
    p = np.array([FAMILIES[k] for k in names])
    family = names[int(rng.choice(len(names), p=p / p.sum()))]
    v, f, smooth = _BUILDERS[family](rng)
    v = v - 0.5 * (v.min(0) + v.max(0))
    v = v / max(np.linalg.norm(v, axis=1).max(), 1e-9)
    return v, f, smooth, family


def object_on_ground(rng: np.random.Generator, centre_xy: np.ndarray, radius: float,
                     ground_z: float = 0.0, upright: float = 0.7) -> tuple[MeshSpec, float]:
    """A random textured shape of bounding radius ``radius`` resting on ``z = ground_z`` at
    ``centre_xy`` -> ``(mesh, top height)``."""
    v, faces, smooth, family = random_shape(rng)
    R = random_rotation(rng, upright=rng.random() < upright)
    v = (v @ R.T) * radius
    v[:, :2] += centre_xy - 0.5 * (v[:, :2].min(0) + v[:, :2].max(0))
    v[:, 2] += ground_z - v[:, 2].min()
    pos, nrm, uv, f = triplanar_mesh(v, faces, smooth, tex_scale=radius * rng.uniform(0.6, 2.5),
                                     uv_offset=rng.uniform(0, 1, size=2))
    textured = rng.random() < 0.85
    mesh = MeshSpec(pos, nrm, uv, f, make_photo_texture(rng) if textured else None,
                    color=tuple(random_colour(rng, 0.6, 1.0) if textured else random_colour(rng)),
                    roughness=float(rng.uniform(0.3, 1.0)), name=family)
    return mesh, float(v[:, 2].max())


def box_mesh(lo: np.ndarray, hi: np.ndarray, tex: np.ndarray | None, tex_scale: float,
             color=(1.0, 1.0, 1.0), name: str = "box") -> MeshSpec:
    """An axis-aligned textured box from corner ``lo`` to ``hi`` (tables, shelves, books)."""
    import trimesh
    m = trimesh.creation.box(bounds=np.stack([lo, hi]))
    pos, nrm, uv, f = triplanar_mesh(np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64),
                                     False, tex_scale=tex_scale, uv_offset=np.zeros(2))
    return MeshSpec(pos, nrm, uv, f, tex, color=tuple(color), roughness=0.8, name=name)


def rotation_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
