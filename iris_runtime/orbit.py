"""A smooth closed camera path through and around a set of cameras, looking at the scene centre.

Used by ``iris-render --orbit N`` on the predicted cameras of the input views. Conventions of
docs/ARCHITECTURE.md: OpenCV camera axes (x right, y down, z forward), ``world_from_cam`` 4x4.

The path, in three steps:

1. **Scene centre** (the look-at target): the point closest, in least squares, to the optical axes
   of the cameras — when it is well defined (axes not parallel) and lies in front of every camera
   at a depth in (near, 10 * far]. Otherwise (one camera, or nearly parallel axes as in a
   forward-facing capture): the point at depth (near + far) / 2 on the mean optical axis.
2. **Ellipse of camera centres**: centred at the mean camera centre m, in the plane through m
   perpendicular to the viewing direction (m -> target) when the target lies outside the cloud of
   centres (forward-facing), or in the best-fit plane of the centres when the cameras surround the
   target. Axes are the principal directions of the centres in that plane, semi-axes sqrt(2) times
   their standard deviation (points spread evenly on an ellipse have exactly that deviation, so
   the ellipse passes through or just around the cameras), each at least ``min_radius`` times the
   distance to the target so that a single camera or a tight cluster still gives a visible orbit.
   The path starts at the angle of view 0 and is periodic: frame n would be frame 0 again.
3. **Orientation**: look at the target with the cameras' mean "down" (y) axis as the vertical
   reference. A look-at keeps the scene centred on every frame and is smooth along the ellipse;
   slerping the input rotations instead would follow the inputs' own aim, which for a handful of
   predicted cameras wobbles and can drift off the scene between them.
"""
from __future__ import annotations

import numpy as np

from .errors import InputError
from .validation import check_integer

__all__ = ["orbit_poses", "look_at", "scene_centre"]


def _unit(v: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), eps)


def look_at(centre: np.ndarray, target: np.ndarray, down: np.ndarray,
            right_hint: np.ndarray | None = None, roll: float = 0.0) -> np.ndarray:
    """``world_from_cam [4, 4]`` of a camera at ``centre`` whose z axis points at ``target`` and
    whose y axis is as close as possible to ``down`` (OpenCV: y points down in the image), then
    turned by ``roll`` radians about its optical axis. ``right_hint``: the x axis to aim for when
    z is parallel to ``down``."""
    z = _unit(np.asarray(target, float) - np.asarray(centre, float))
    x = np.cross(down, z)
    if np.linalg.norm(x) < 1e-6:               # looking along the vertical: use the right hint
        hint = np.array([1.0, 0.0, 0.0]) if right_hint is None else np.asarray(right_hint, float)
        x = hint - (hint @ z) * z
        if np.linalg.norm(x) < 1e-6:
            x = np.cross(z, [0.0, 0.0, 1.0]) if abs(z[2]) < 0.9 else np.cross(z, [1.0, 0.0, 0.0])
    x = _unit(x)
    y = np.cross(z, x)
    if roll:
        c, s = np.cos(roll), np.sin(roll)
        x, y = c * x + s * y, -s * x + c * y
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, centre
    return T


def scene_centre(world_from_cam: np.ndarray, near: float, far: float) -> np.ndarray:
    """The look-at target of the path (step 1 of the module docstring)."""
    centres = world_from_cam[:, :3, 3]
    forwards = world_from_cam[:, :3, 2]
    forwards = forwards / np.linalg.norm(forwards, axis=1, keepdims=True)
    if len(centres) >= 2:
        P = np.eye(3)[None] - forwards[:, :, None] * forwards[:, None, :]     # [V, 3, 3]
        A, b = P.sum(0), (P @ centres[:, :, None]).sum(0)[:, 0]
        eig = np.linalg.eigvalsh(A)
        if eig[0] > 1e-3 * eig[-1]:
            p = np.linalg.solve(A, b)
            depths = ((p - centres) * forwards).sum(1)
            if np.all(depths > near) and np.all(depths <= 10 * far):
                return p
    return centres.mean(0) + _unit(forwards.mean(0)) * 0.5 * (near + far)


def orbit_poses(world_from_cam, n: int, *, near: float, far: float,
                min_radius: float = 0.05) -> np.ndarray:
    """``n`` poses ``[n, 4, 4]`` (float64) on a closed path around cameras ``world_from_cam
    [V, 4, 4]`` (see the module docstring). ``min_radius``: smallest semi-axis, as a fraction of
    the distance from the mean camera centre to the scene centre."""
    T = np.asarray(world_from_cam, dtype=np.float64)
    if T.ndim != 3 or T.shape[1:] != (4, 4) or len(T) == 0 or not np.all(np.isfinite(T)):
        raise InputError(f"world_from_cam: expected finite [V, 4, 4] poses, got shape {T.shape}")
    n = check_integer(n, "n")
    centres = T[:, :3, 3]
    target = scene_centre(T, near, far)
    m = centres.mean(0)
    view = target - m
    dist = float(np.linalg.norm(view))
    offsets = centres - m
    spread = float(np.sqrt((offsets ** 2).sum(1).mean()))
    down = T[:, :3, 1].mean(0)
    right = T[:, :3, 0].mean(0)
    if dist < 1e-9:                            # degenerate: fall back to the mean optical axis
        view, dist = T[:, :3, 2].mean(0), 0.5 * (near + far)
    if dist > spread:
        # Forward-facing: ellipse in the plane perpendicular to the viewing direction.
        normal = _unit(view)
    else:
        # Cameras around the target: best-fit plane of the centres.
        normal = np.linalg.svd(offsets, full_matrices=True)[2][-1]
    basis = np.linalg.svd(np.eye(3) - np.outer(normal, normal))[0][:, :2]     # plane axes
    flat = offsets @ basis                                                     # [V, 2]
    if len(centres) >= 2 and np.abs(flat).max() > 1e-12:
        _, sv, axes2 = np.linalg.svd(flat, full_matrices=True)
        sv = np.pad(sv, (0, 2 - len(sv)))
        e1, e2 = basis @ axes2[0], basis @ axes2[1]
        std = sv / np.sqrt(len(centres))
    else:                                      # one camera (or all at one place): image axes
        e1 = _unit(right - (right @ normal) * normal)
        e2 = np.cross(normal, e1)
        std = np.zeros(2)
    floor = min_radius * max(dist, 1e-6)
    a, b = np.maximum(np.sqrt(2.0) * std, floor)
    # Keep a right-handed, consistently oriented frame so that the path turns the same way for
    # the same cameras, and start at view 0's angle.
    if np.dot(np.cross(e1, e2), normal) < 0:
        e2 = -e2
    rel0 = offsets[0]
    theta0 = float(np.arctan2((rel0 @ e2) / b, (rel0 @ e1) / a))
    thetas = theta0 + 2.0 * np.pi * np.arange(n) / n
    out = np.empty((n, 4, 4))
    for k, th in enumerate(thetas):
        c = m + a * np.cos(th) * e1 + b * np.sin(th) * e2
        out[k] = look_at(c, target, down, right_hint=right)
    return out
