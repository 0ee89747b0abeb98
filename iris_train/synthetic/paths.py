"""Cameras of the capture kinds: wide intrinsics ranges and the paths real captures take.

* ``draw_intrinsics``: vertical field of view 25-90 degrees, square pixels, principal point off
  the centre by up to 8 % of the image size per axis (``K`` carries it; the model itself assumes
  a centred one, see docs/DATA.md for which consumers honour ``K``'s principal point).
* ``object_walk``: a person walking around an object: 60-270 degrees of azimuth at an uneven pace,
  varying distance and height, aim jitter, hand-held roll / pitch / yaw noise.
* ``forward_path``: hand-held, forward-facing: small translations and rotation-heavy pans (yaw,
  pitch, roll) over a scene with depth.
Paths are ordered along the trajectory (the "Seq" order), as the classic arcs.
"""
from __future__ import annotations

import math

import numpy as np

from .cameras import look_at

#: Vertical field of view range of the capture kinds (degrees).
FOV_RANGE_DEG = (25.0, 90.0)
#: Largest principal-point offset from the image centre, as a fraction of the size per axis.
PRINCIPAL_OFFSET = 0.08


def intrinsics_off_centre(size: tuple[int, int], yfov: float, offset: np.ndarray) -> np.ndarray:
    """``K [3, 3]`` of a pinhole with vertical field of view ``yfov`` (radians), square pixels and
    the principal point at the centre + ``offset`` (fractions of (width, height)). ``K`` is
    proportional to the size (pixel centres at +0.5), so a downsampled render has ``K / factor``."""
    h, w = size
    f = (h / 2.0) / math.tan(yfov / 2.0)
    return np.array([[f, 0.0, w * (0.5 + offset[0])], [0.0, f, h * (0.5 + offset[1])], [0.0, 0.0, 1.0]])


def draw_intrinsics(rng: np.random.Generator) -> tuple[float, np.ndarray]:
    """``(yfov radians, principal-point offset [2])`` of one capture."""
    yfov = math.radians(rng.uniform(*FOV_RANGE_DEG))
    return yfov, rng.uniform(-PRINCIPAL_OFFSET, PRINCIPAL_OFFSET, size=2)


def camera_rotation(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Rotation [3, 3] about the camera's own axes (OpenCV: yaw about y (down), pitch about x
    (right), roll about z (forward)), applied as ``R_world_from_cam @ camera_rotation(...)``."""
    cy, sy, cp, sp, cr, sr = (math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch),
                              math.cos(roll), math.sin(roll))
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    Rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1]])
    return Ry @ Rx @ Rz


def _smooth(rng: np.random.Generator, t: np.ndarray, amplitude: float) -> np.ndarray:
    """A smooth random curve over ``t`` in [0, 1] with values within about +-``amplitude``."""
    f = rng.uniform(0.3, 1.5, size=2)
    ph = rng.uniform(0, 2 * np.pi, size=2)
    w = rng.dirichlet([1.0, 1.0])
    return amplitude * (w[0] * np.sin(2 * np.pi * f[0] * t + ph[0]) + w[1] * np.sin(2 * np.pi * f[1] * t + ph[1]))


def _progress(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` increasing positions in [0, 1] at an uneven pace (first 0, last 1)."""
    if n == 1:
        return np.zeros(1)
    steps = rng.uniform(0.4, 1.6, size=n - 1)
    return np.concatenate([[0.0], np.cumsum(steps) / steps.sum()])


def object_walk(rng: np.random.Generator, n_views: int, target: np.ndarray, dist: float,
                elev_range_deg: tuple[float, float], span_range_deg: tuple[float, float],
                aim_sd: float, shake_deg: float = 1.5) -> tuple[np.ndarray, dict]:
    """Cameras walking around ``target`` at about ``dist``; see the module docstring."""
    span = math.radians(rng.uniform(*span_range_deg))
    az0 = rng.uniform(0, 2 * np.pi)
    direction = 1.0 if rng.random() < 0.5 else -1.0
    t = _progress(rng, n_views)
    elev0 = rng.uniform(*elev_range_deg)
    el = np.radians(np.clip(elev0 + _smooth(rng, t, rng.uniform(0, 12)), elev_range_deg[0], 70.0))
    radius = dist * (1 + _smooth(rng, t, rng.uniform(0, 0.15)))
    aim = target + np.stack([_smooth(rng, t, aim_sd) for _ in range(3)], 1)
    poses = []
    for k in range(n_views):
        az = az0 + direction * span * t[k]
        eye = target + radius[k] * np.array([math.cos(el[k]) * math.cos(az),
                                             math.cos(el[k]) * math.sin(az), math.sin(el[k])])
        T = look_at(eye, aim[k], roll=math.radians(rng.normal(0, 2 * shake_deg)))
        T[:3, :3] = T[:3, :3] @ camera_rotation(*np.radians(rng.normal(0, shake_deg, size=2)), 0.0)
        poses.append(T)
    info = {"path": "walk", "arc_deg": math.degrees(span), "elevation_deg": float(elev0),
            "distance": float(dist)}
    return np.stack(poses), info


def forward_path(rng: np.random.Generator, n_views: int, eye: np.ndarray, target: np.ndarray,
                 baseline: float, pan_deg: float, tilt_deg: float, roll_deg: float,
                 shake_deg: float = 1.0) -> tuple[np.ndarray, dict]:
    """Hand-held cameras near ``eye`` aimed at ``target``: a smooth translation of total extent
    about ``baseline`` (mostly sideways), and on top of the aim, pans within +-``pan_deg`` (yaw),
    +-``tilt_deg`` (pitch) and +-``roll_deg`` (roll) along the path, plus per-view shake of
    ``shake_deg``. The target stays within those angles of the optical axis."""
    base = look_at(eye, target)
    t = _progress(rng, n_views)
    lateral = rng.uniform(0.5, 1.0) * (1.0 if rng.random() < 0.5 else -1.0)
    move = np.stack([baseline * lateral * (t - 0.5) + _smooth(rng, t, 0.15 * baseline),
                     _smooth(rng, t, 0.3 * baseline), _smooth(rng, t, 0.4 * baseline)], 1)
    sweep = rng.uniform(0.4, 1.0) * (1.0 if rng.random() < 0.5 else -1.0)
    yaw = pan_deg * (0.7 * sweep * (2 * t - 1) + _smooth(rng, t, 0.3))
    pitch = _smooth(rng, t, tilt_deg)
    roll = rng.uniform(-0.3, 0.3) * roll_deg + _smooth(rng, t, 0.7 * roll_deg)
    poses = []
    for k in range(n_views):
        T = look_at(eye + base[:3, :3] @ move[k], target)
        shake = np.radians(np.clip(rng.normal(0, shake_deg, size=3), -2 * shake_deg, 2 * shake_deg))
        T[:3, :3] = T[:3, :3] @ camera_rotation(math.radians(yaw[k]) + shake[0],
                                                math.radians(pitch[k]) + shake[1],
                                                math.radians(roll[k]) + shake[2])
        poses.append(T)
    info = {"path": "forward", "baseline": float(baseline), "pan_deg": float(np.ptp(yaw)),
            "distance": float(np.linalg.norm(target - eye))}
    return np.stack(poses), info
