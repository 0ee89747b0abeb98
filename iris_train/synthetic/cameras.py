"""Cameras of the classic kinds: ``look_at``, arcs around a point, centred-pinhole intrinsics."""
from __future__ import annotations

import math

import numpy as np

from iris_runtime.orbit import look_at as _look_at

def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0), roll: float = 0.0) -> np.ndarray:
    """``world_from_cam [4, 4]`` (OpenCV: x right, y down, z forward) at ``eye`` looking at
    ``target`` with ``up`` up in the image, turned by ``roll`` radians about the optical axis:
    ``iris_runtime.orbit.look_at`` (bitwise) in the z-up terms of the scene generator."""
    return _look_at(np.asarray(eye, dtype=np.float64), target, -np.asarray(up, dtype=np.float64),
                    roll=roll)


def arc_cameras(rng: np.random.Generator, n_views: int, target: np.ndarray, az_centre: float,
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


def intrinsics(size: tuple[int, int], yfov: float) -> np.ndarray:
    h, w = size
    f = (h / 2.0) / math.tan(yfov / 2.0)
    return np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])
