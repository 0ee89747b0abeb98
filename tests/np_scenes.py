"""Photos of a textured room corner, ray-cast in numpy: a torch-free scene with true cameras for
the camera solve's tests (three perpendicular textured planes, so the scene is not a plane)."""
from __future__ import annotations

import math

import cv2
import numpy as np

#: Planes (normal, offset, two in-plane axes, half extents): floor z = 0, back wall y = 1,
#: side wall x = -1, each textured over [-1.5, 1.5]^2 of its axes.
_PLANES = (((0.0, 0.0, 1.0), 0.0, (1, 0, 0), (0, 1, 0)),
           ((0.0, -1.0, 0.0), -1.0, (1, 0, 0), (0, 0, 1)),
           ((1.0, 0.0, 0.0), -1.0, (0, 1, 0), (0, 0, 1)))
_EXTENT = 1.5
_TEXTURE = 512


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """world_from_cam [4, 4] (OpenCV axes) at ``eye`` looking at ``target``."""
    z = np.asarray(target, float) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(z, x), z, eye
    return T


def textures(seed: int) -> list[np.ndarray]:
    """One blotchy grey texture per plane (blurred noise at two scales: blobs SIFT finds)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in _PLANES:
        fine = cv2.GaussianBlur(rng.random((_TEXTURE, _TEXTURE)).astype(np.float32), (0, 0), 2.0)
        coarse = cv2.GaussianBlur(rng.random((_TEXTURE, _TEXTURE)).astype(np.float32), (0, 0), 9.0)
        t = fine - fine.mean() + 2.0 * (coarse - coarse.mean())
        out.append(((t - t.min()) / (t.max() - t.min()) * 255.0).astype(np.float32))
    return out


def cameras(n: int, arc_deg: float, radius: float = 3.0, elevation_deg: float = 25.0
            ) -> np.ndarray:
    """n cameras on an arc around the corner, all looking at it -> world_from_cam [n, 4, 4]."""
    target = np.array([-0.2, 0.2, 0.4])
    out = []
    for k in range(n):
        az = math.radians(-45.0 + arc_deg * (k / max(n - 1, 1) - 0.5))
        el = math.radians(elevation_deg + 4.0 * math.sin(k))
        eye = target + radius * np.array([math.cos(el) * math.cos(az),
                                          math.cos(el) * math.sin(az), math.sin(el)])
        out.append(look_at(eye, target))
    return np.stack(out)


def render(world_from_cam: np.ndarray, focal: float, size: tuple[int, int], seed: int = 0
           ) -> np.ndarray:
    """uint8 RGB photos [V, H, W, 3] of the corner from ``world_from_cam [V, 4, 4]`` at ``focal``
    pixels (principal point at the centre, pixel centres at +0.5)."""
    H, W = size
    tex = textures(seed)
    v, u = np.mgrid[0:H, 0:W].astype(np.float64) + 0.5
    rays = np.stack([(u - W / 2) / focal, (v - H / 2) / focal, np.ones_like(u)], -1)
    photos = []
    for T in world_from_cam:
        d = rays @ T[:3, :3].T
        o = T[:3, 3]
        best = np.full((H, W), np.inf)
        value = np.zeros((H, W), np.float32)
        for (n, off, a1, a2), t_img in zip(_PLANES, tex):
            n = np.asarray(n)
            denom = d @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                s = (off - o @ n) / denom
            X = o + s[..., None] * d
            c1, c2 = X @ np.asarray(a1, float), X @ np.asarray(a2, float)
            hit = (s > 0) & (np.abs(c1) <= _EXTENT) & (np.abs(c2) <= _EXTENT) & (s < best)
            mx = ((c1 + _EXTENT) / (2 * _EXTENT) * (_TEXTURE - 1)).astype(np.float32)
            my = ((c2 + _EXTENT) / (2 * _EXTENT) * (_TEXTURE - 1)).astype(np.float32)
            sample = cv2.remap(t_img, np.nan_to_num(mx), np.nan_to_num(my), cv2.INTER_LINEAR)
            value = np.where(hit, sample, value)
            best = np.where(hit, s, best)
        photos.append(np.repeat(np.clip(value, 0, 255).astype(np.uint8)[..., None], 3, axis=2))
    return np.stack(photos)
