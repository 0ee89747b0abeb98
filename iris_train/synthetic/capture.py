"""The capture kinds: scenes shaped like real captures (generator version 2).

* ``walk``     — objects on a table or on the floor inside a closed, photo-textured rotunda; a
                 person walks 60-270 degrees around them (``paths.object_walk``).
* ``orbit``    — the same content on a turntable-like arc of 10-90 degrees (as the classic kinds).
* ``handheld`` — a cluttered tabletop against a wall, filmed forward-facing by hand: small
                 translations, pans, tilts and roll (``paths.forward_path``).
* ``indoor``   — a furnished box room seen from inside with larger pans.

Each builder works in its own units (camera to target distance ~0.5) and returns the scene's
*anchors*: the centres of the objects the cameras are aimed at; ``render.render_spec`` then
scales world and cameras so that the median valid depth equals the drawn ``depth_target``.
"""
from __future__ import annotations

import math

import numpy as np

from .meshes import box_room_walls, disc, place_discs, quad
from .paths import forward_path, object_walk
from .scene import LightSpec, MeshSpec
from .shapes import box_mesh, object_on_ground
from .textures import make_photo_texture, random_colour

#: Capture kinds, in the order that ``kind="capture"`` cycles through by seed.
CAPTURE_KINDS = ("walk", "orbit", "handheld", "indoor")


def _lights(rng: np.random.Generator, n_max: int = 3) -> tuple[list[LightSpec], tuple]:
    lights = []
    for _ in range(int(rng.integers(1, n_max + 1))):
        az, el = rng.uniform(0, 2 * np.pi), rng.uniform(math.radians(20), math.radians(85))
        d = -np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        warm = np.array([1.0, rng.uniform(0.85, 1.0), rng.uniform(0.65, 1.0)])
        lights.append(LightSpec("directional", tuple(warm * (0.7 + 0.3 * rng.random())),
                                float(rng.uniform(0.8, 3.5)), direction=d))
    ambient = tuple(rng.uniform(0.15, 0.45) * (0.85 + 0.15 * rng.random(3)))
    return lights, ambient


def _rotunda(rng: np.random.Generator, radius: float, z0: float, z1: float) -> list[MeshSpec]:
    """A closed cylinder (walls in 3-8 photo-textured panels, floor and ceiling discs), inside
    faces only: the backdrop of the object kinds, never a flat colour."""
    meshes = []
    n_panels = int(rng.integers(3, 9))
    seg = 48 // n_panels
    a = np.linspace(0, 2 * np.pi, n_panels * seg + 1) + rng.uniform(0, 2 * np.pi)
    height = z1 - z0
    for p in range(n_panels):
        tex = make_photo_texture(rng)
        scale = rng.uniform(0.25, 1.0) * height
        colour = tuple(random_colour(rng, 0.65, 1.0))
        # One mesh per panel: seg quads, counter-clockwise seen from inside, u along the arc.
        ang = a[p * seg:(p + 1) * seg + 1]
        ring = radius * np.stack([np.cos(ang), np.sin(ang)], 1)
        pos = np.concatenate([np.c_[ring, np.full(seg + 1, z0)], np.c_[ring, np.full(seg + 1, z1)]])
        nrm = -np.c_[np.cos(ang), np.sin(ang), np.zeros(seg + 1)]
        u = radius * (ang - ang[0]) / scale
        uv = np.concatenate([np.c_[u, np.zeros(seg + 1)], np.c_[u, np.full(seg + 1, height / scale)]])
        i = np.arange(seg)
        faces = np.concatenate([np.stack([i + 1, i, i + seg + 1], 1),
                                np.stack([i + 1, i + seg + 1, i + seg + 2], 1)])
        meshes.append(MeshSpec(pos.astype(np.float32), np.concatenate([nrm, nrm]).astype(np.float32),
                               uv.astype(np.float32), faces.astype(np.uint32), tex, color=colour,
                               roughness=0.9, name="wall"))
    floor = disc(radius, make_photo_texture(rng), tex_scale=rng.uniform(0.15, 0.6) * radius)
    floor.positions[:, 2] = z0
    meshes.append(floor)
    ceiling = disc(radius, make_photo_texture(rng, photo=0.3), tex_scale=radius)
    ceiling.positions[:, 2] = z1
    ceiling.normals[:] = (0.0, 0.0, -1.0)
    ceiling.faces = ceiling.faces[:, ::-1].copy()
    meshes.append(ceiling)
    return meshes


def _clutter(rng: np.random.Generator, radius: float, ground_z: float, n: int,
             cameras: np.ndarray, clearance: float) -> tuple[list[MeshSpec], list[np.ndarray], float]:
    """Up to ``n`` smaller objects around the main one (sometimes on a book-like box), none within
    ``clearance`` of a camera centre ``cameras [V, 3]`` -> ``(meshes, anchors, top height)``."""
    meshes, anchors, top = [], [], ground_z
    for c, r in place_discs(rng, n, region_radius=1.8 * radius, r_lo=0.18 * radius, r_hi=0.4 * radius):
        if np.linalg.norm(c) < 0.9 * radius + r:
            continue
        centre = np.array([*c, ground_z + r])
        if np.linalg.norm(cameras - centre, axis=1).min() < 2 * r + clearance:
            continue
        z = ground_z
        if rng.random() < 0.2:
            h = r * rng.uniform(0.3, 0.7)
            meshes.append(box_mesh(np.array([*(c - r), z]), np.array([*(c + r), z + h]),
                                   make_photo_texture(rng), tex_scale=2 * r, name="stand"))
            z += h
        m, t = object_on_ground(rng, c, r * 0.9, z)
        meshes.append(m)
        top = max(top, t)
        anchors.append(np.array([*c, 0.5 * (z + t)]))
    return meshes, anchors, top


def build_object(rng: np.random.Generator, n_views: int, yfov: float, path: str):
    """``walk`` / ``orbit``: see the module docstring."""
    dist = 0.5
    fill = rng.uniform(0.45, 0.85)
    radius = min(dist * math.tan(fill * yfov / 2), 0.36 * dist)
    table = rng.random() < 0.5
    meshes = []
    if table:
        half = rng.uniform(1.3 * radius, max(1.4 * radius, 0.6 * dist), size=2)
        thick = rng.uniform(0.02, 0.05)
        meshes.append(box_mesh(np.array([-half[0], -half[1], -thick]), np.array([half[0], half[1], 0.0]),
                               make_photo_texture(rng), tex_scale=rng.uniform(0.1, 0.4), name="table"))
        floor_z = -rng.uniform(0.6, 1.0) * dist
    else:
        floor_z = 0.0
    main, top = object_on_ground(rng, np.zeros(2), radius * rng.uniform(0.7, 1.0), 0.0)
    meshes.append(main)
    anchor = np.array([0.0, 0.0, 0.5 * top])
    target = anchor + rng.normal(0, 0.1 * radius, size=3)
    # Cameras at least 0.3 dist above the ground, so the ground under them is not too near.
    el_min = math.degrees(math.asin(float(np.clip((0.3 * dist - target[2]) / dist, 0.0, 0.7))))
    if path == "walk":
        world_from_cam, info = object_walk(rng, n_views, target, dist, (max(5.0, el_min), 45.0),
                                           (60.0, 270.0), aim_sd=0.15 * radius)
    else:
        from .cameras import arc_cameras
        world_from_cam, info = arc_cameras(rng, n_views, target, rng.uniform(0, 2 * np.pi),
                                           (max(10.0, el_min + 2), 50.0),
                                           dist_range=(0.95 * dist, 1.05 * dist))
        info["path"] = "orbit"
    objects, anchors, top2 = _clutter(rng, radius, 0.0, int(rng.integers(0, 5)),
                                      world_from_cam[:, :3, 3], 0.25 * dist)
    meshes += objects
    wall_r = rng.uniform(1.4, 2.2) * dist
    cam_top = float(world_from_cam[:, 2, 3].max())
    ceiling = max(cam_top + 0.3 * dist, max(top, top2) + 0.3 * dist, rng.uniform(1.2, 2.2) * dist)
    meshes += _rotunda(rng, wall_r, floor_z, ceiling)
    lights, ambient = _lights(rng)
    info.update(n_objects=1 + len(anchors), table=bool(table), object_radius=float(radius))
    return meshes, lights, ambient, world_from_cam, np.stack([anchor, *anchors]), info


def _box_room(rng: np.random.Generator, x0, x1, y0, y1, z1) -> list[MeshSpec]:
    """A closed box room (floor z = 0), faces pointing inwards, photo-textured."""
    walls = box_room_walls(x0, x1, y0, y1, z1)
    meshes = []
    for name, corners in walls.items():
        c = np.asarray(corners, dtype=np.float64)
        w_len, h_len = np.linalg.norm(c[1] - c[0]), np.linalg.norm(c[3] - c[0])
        scale = rng.uniform(0.2, 0.8)
        meshes.append(quad(c, make_photo_texture(rng), (w_len / scale, h_len / scale),
                           color=tuple(random_colour(rng, 0.65, 1.0)), name=name))
    return meshes


def _pictures(rng: np.random.Generator, y: float, x_range, z_range, n: int) -> list[MeshSpec]:
    """Framed photos hung on the wall at ``y`` (facing -y)."""
    out = []
    for _ in range(n):
        w, h = rng.uniform(0.1, 0.35), rng.uniform(0.08, 0.3)
        px, pz = rng.uniform(*x_range), rng.uniform(*z_range)
        yb = y - 0.003
        out.append(quad([[px - w / 2, yb, pz], [px + w / 2, yb, pz], [px + w / 2, yb, pz + h],
                         [px - w / 2, yb, pz + h]], make_photo_texture(rng, photo=1.0), (1.0, 1.0),
                        name="picture"))
    return out


def build_handheld(rng: np.random.Generator, n_views: int, yfov: float):
    """``handheld``: a cluttered table against a wall, filmed forward-facing."""
    dist = 0.5
    half_w = dist * math.tan(yfov / 2) * 1.6 + 0.2
    depth_y = rng.uniform(0.5, 0.9) * dist                  # table depth towards the wall
    y_wall = depth_y + rng.uniform(0.02, 0.3)
    table_z = rng.uniform(0.3, 0.5)
    meshes = _box_room(rng, -half_w - 0.3, half_w + 0.3, -dist - 0.6, y_wall, table_z + rng.uniform(0.6, 1.0))
    meshes.append(box_mesh(np.array([-half_w, -0.15 * dist, table_z - 0.04]),
                           np.array([half_w, y_wall - 0.005, table_z]), make_photo_texture(rng),
                           tex_scale=rng.uniform(0.1, 0.4), name="table"))
    meshes += _pictures(rng, y_wall, (-0.5 * half_w, 0.5 * half_w), (table_z + 0.05, table_z + 0.4),
                        int(rng.integers(0, 3)))
    anchors = []
    n = int(rng.integers(3, 9))
    for c, r in place_discs(rng, n, region_radius=1.0, r_lo=0.04, r_hi=0.12):
        xy = np.array([c[0] * 0.8 * half_w, -0.1 * dist + (c[1] + 1) / 2 * (depth_y + 0.05 * dist)])
        if xy[1] + r > y_wall - 0.01:
            continue
        # Object sizes follow the field of view, so that narrow views are not filled by one.
        m, top = object_on_ground(rng, xy, r * rng.uniform(0.8, 1.6) * math.tan(yfov / 2) / 0.577,
                                  table_z)
        meshes.append(m)
        anchors.append(np.array([xy[0], xy[1], 0.5 * (table_z + top)]))
    if not anchors:
        m, top = object_on_ground(rng, np.array([0.0, 0.3 * dist]), 0.08, table_z)
        meshes.append(m)
        anchors.append(np.array([0.0, 0.3 * dist, 0.5 * (table_z + top)]))
    centre = np.mean(anchors, 0)
    pitch = math.radians(rng.uniform(15, 60))
    back = dist * math.cos(pitch)
    eye = centre + np.array([rng.uniform(-0.05, 0.05), -back, dist * math.sin(pitch)])
    half_fov = yfov / 2
    world_from_cam, info = forward_path(rng, n_views, eye, centre, baseline=rng.uniform(0.05, 0.3) * dist,
                                        pan_deg=math.degrees(half_fov) * rng.uniform(0.2, 0.55),
                                        tilt_deg=math.degrees(half_fov) * rng.uniform(0.1, 0.3),
                                        roll_deg=rng.uniform(2, 12))
    lights, ambient = _lights(rng)
    info.update(n_objects=len(anchors), pitch_deg=math.degrees(pitch))
    # Aim anchor: the cluster's centre, which the whole path looks at.
    return meshes, lights, ambient, world_from_cam, centre[None], info


def build_indoor(rng: np.random.Generator, n_views: int, yfov: float):
    """``indoor``: a furnished room (boxes as furniture, objects, pictures), larger pans."""
    hx, hy = rng.uniform(0.7, 1.1), rng.uniform(0.7, 1.1)
    height = rng.uniform(0.8, 1.2)
    meshes = _box_room(rng, -hx, hx, -hy, hy, height)
    meshes += _pictures(rng, hy, (-0.6 * hx, 0.6 * hx), (0.35, 0.7 * height), int(rng.integers(1, 4)))
    anchors, boxes = [], []
    # Furniture against the back and side walls, objects on top of it and on the floor.
    for _ in range(int(rng.integers(2, 5))):
        w, d, h = rng.uniform(0.15, 0.5), rng.uniform(0.12, 0.3), rng.uniform(0.1, 0.45)
        side = rng.integers(3)
        if side == 0:
            x, y = rng.uniform(-hx + w, hx - w), hy - d
        else:
            x, y = (hx - d if side == 1 else -hx + d), rng.uniform(-0.2, hy - w)
        lo, hi = np.array([x - w, y - d, 0.0]), np.array([x + w, y + d, h])
        boxes.append((lo, hi))
        meshes.append(box_mesh(lo, hi, make_photo_texture(rng), tex_scale=rng.uniform(0.1, 0.4),
                               color=tuple(random_colour(rng, 0.6, 1.0)), name="furniture"))
        if rng.random() < 0.8:
            m, top = object_on_ground(rng, np.array([x, y]), min(w, d) * rng.uniform(0.5, 0.9), h)
            meshes.append(m)
            anchors.append(np.array([x, y, 0.5 * (h + top)]))
    for c, r in place_discs(rng, int(rng.integers(1, 4)), 0.35, 0.05, 0.12):
        xy = c + np.array([0.0, 0.3 * hy])
        m, top = object_on_ground(rng, xy, r, 0.0)
        meshes.append(m)
        anchors.append(np.array([*xy, 0.5 * top]))
    focus = anchors[int(rng.integers(len(anchors)))]
    # Stand 0.45-0.6 from the focus, at least 0.3 from the walls and clear of the furniture.
    margin = 0.3
    for _ in range(100):
        az = rng.uniform(-np.pi, np.pi)
        eye_xy = focus[:2] + rng.uniform(0.45, 0.6) * np.array([math.cos(az), math.sin(az)])
        inside = abs(eye_xy[0]) < hx - margin and abs(eye_xy[1]) < hy - margin
        clear = min(np.linalg.norm(a[:2] - eye_xy) for a in anchors) > 0.3
        if inside and clear and all(np.any((eye_xy < lo[:2] - 0.2) | (eye_xy > hi[:2] + 0.2)) for lo, hi in boxes):
            break
    else:
        eye_xy = np.zeros(2)
    eye = np.array([*eye_xy, rng.uniform(0.25, min(0.6, height - 0.15))])
    half_fov = yfov / 2
    world_from_cam, info = forward_path(rng, n_views, eye, focus, baseline=rng.uniform(0.05, 0.25),
                                        pan_deg=math.degrees(half_fov) * rng.uniform(0.3, 0.55),
                                        tilt_deg=math.degrees(half_fov) * rng.uniform(0.1, 0.3),
                                        roll_deg=rng.uniform(2, 10))
    lights, ambient = _lights(rng)
    info.update(n_objects=len(anchors), room_half=[float(hx), float(hy)], room_height=float(height))
    return meshes, lights, ambient, world_from_cam, focus[None], info
