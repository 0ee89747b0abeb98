"""The classic scene kinds, "turntable" and "room" (generator version 1, kept bitwise unchanged:
the held-out and validation scenes of ``iris_train.data`` are rendered from them)."""
from __future__ import annotations

import math

import numpy as np

from .cameras import arc_cameras
from .meshes import box_room_walls, disc, object_mesh, place_discs, quad
from .scene import LightSpec
from .textures import make_texture, random_colour
def lights_turntable(rng: np.random.Generator) -> list[LightSpec]:
    lights = []
    for _ in range(int(rng.integers(1, 4))):
        az, el = rng.uniform(0, 2 * np.pi), rng.uniform(math.radians(20), math.radians(80))
        d = -np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        lights.append(LightSpec("directional", tuple(0.6 + 0.4 * rng.random(3)),
                                float(rng.uniform(1.0, 4.0)), direction=d))
    return lights


def build_turntable(rng: np.random.Generator, n_views: int) -> tuple[list, list, tuple, tuple, np.ndarray, np.ndarray, dict]:
    meshes = []
    ground_r = rng.uniform(0.36, 0.44)
    meshes.append(disc(ground_r, make_texture(rng), tex_scale=rng.uniform(0.1, 0.4)))
    placed = place_discs(rng, int(rng.integers(3, 7)), region_radius=0.18, r_lo=0.05, r_hi=0.1)
    for c, r in placed:
        meshes.append(object_mesh(rng, c, r))
    target = np.array([0.0, 0.0, rng.uniform(0.03, 0.07)])
    world_from_cam, info = arc_cameras(rng, n_views, target, rng.uniform(0, 2 * np.pi), (12.0, 45.0))
    ambient = tuple(rng.uniform(0.1, 0.35) * (0.8 + 0.2 * rng.random(3)))
    background = tuple(rng.uniform(0.0, 1.0, 3))
    # Markers float around the objects, at heights the cameras see.
    markers = np.array([[0.09, 0.0, 0.16], [-0.07, 0.08, 0.12], [0.0, -0.1, 0.2], [0.05, 0.05, 0.24]])
    info.update(n_objects=len(placed))
    return meshes, lights_turntable(rng), ambient, background, world_from_cam, markers, info


def build_room(rng: np.random.Generator, n_views: int):
    """A box room (floor z = 0) seen from inside; the objects stand near the back wall (+y)."""
    meshes = []
    half_w = rng.uniform(0.55, 0.75)                 # room spans x in [-half_w, half_w]
    gap = rng.uniform(0.26, 0.32)                    # objects' centre to the back wall
    y_back = gap
    y_front = -(0.65 + 0.25)                         # cameras (<= 0.65 away) stay inside
    height = rng.uniform(0.55, 0.8)
    x0, x1, y0, y1, z1 = -half_w, half_w, y_front, y_back, height
    walls = box_room_walls(x0, x1, y0, y1, z1)
    for name, corners in walls.items():
        c = np.asarray(corners, dtype=np.float64)
        w_len = np.linalg.norm(c[1] - c[0])
        h_len = np.linalg.norm(c[3] - c[0])
        scale = rng.uniform(0.15, 0.5)
        meshes.append(quad(c, make_texture(rng), (w_len / scale, h_len / scale),
                            color=tuple(random_colour(rng, 0.6, 1.0)), name=name))
    # A "painting" on the back wall and a box against a side wall add structure far from centre.
    pw, ph = rng.uniform(0.15, 0.3), rng.uniform(0.1, 0.2)
    px, pz = rng.uniform(-0.2, 0.2), rng.uniform(0.2, max(0.25, height - ph - 0.05))
    yb = y1 - 0.002
    meshes.append(quad([[px - pw / 2, yb, pz], [px + pw / 2, yb, pz], [px + pw / 2, yb, pz + ph],
                         [px - pw / 2, yb, pz + ph]], make_texture(rng), (1.0, 1.0), name="painting"))
    side = -1 if rng.random() < 0.5 else 1
    meshes.append(object_mesh(rng, np.array([side * (half_w - 0.08), rng.uniform(-0.2, 0.1)]), 0.07))
    # The object cluster, centred at (0, 0) on the floor.
    placed = place_discs(rng, int(rng.integers(3, 6)), region_radius=0.14, r_lo=0.05, r_hi=0.09)
    for c, r in placed:
        meshes.append(object_mesh(rng, c, r))
    target = np.array([0.0, 0.0, rng.uniform(0.04, 0.09)])
    # Cameras on the -y side looking towards the back wall (azimuth -90 deg +- arc / 2).
    # Closer than on the turntable (0.5-0.6) so that the back wall stays near depth 1.
    world_from_cam, info = arc_cameras(rng, n_views, target, -np.pi / 2 + rng.uniform(-0.15, 0.15),
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

