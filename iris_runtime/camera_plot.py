"""Pictures of cameras, numpy + OpenCV only (the runtime has neither matplotlib nor torch).

    from iris_runtime.camera_plot import align_poses, draw_cameras
    aligned, _ = align_poses(pred_world_from_cam, true_world_from_cam)   # predicted, in the true frame
    image = draw_cameras(aligned, pred_K, reference=true_world_from_cam, reference_focal=true_K)

More sets in the same frame (e.g. a second estimate of some of the cameras, aligned the same way)
go in ``others``, one ``CameraSet`` each.

``draw_cameras`` draws every camera as a frustum (apex at the centre, the image rectangle at a
fixed distance along the optical axis, a small filled triangle on the image's top edge so that roll
is visible) with its index, in an **orthographic** view from a fixed elevated viewpoint: 30 degrees
above the cameras' mean horizon, 35 degrees to the side of their mean viewing direction. "Up" is
minus the mean of the cameras' y axes (OpenCV: y points down in the image), so a turntable or a
handheld sweep is seen from above and behind whatever the world frame. The view is fitted to the
extent of all cameras (predicted and reference); the frustum length is 12 % of that extent, so the
picture looks the same at any scale, and a scale bar gives the scene's units.

Degenerate input never produces NaN or an exception: a single camera, all cameras at one point
(drawn with a nominal frustum length and a note, no scale bar), predicted cameras collapsed next to
true ones (a note gives their spread as a fraction of the true one), coordinates of 1e-9 or 1e9,
non-orthonormal rotations (drawn with their nearest rotation), non-finite cameras (left out, with
a note).

``align_similarity`` is Umeyama's least-squares similarity (1991) between camera centres, with
the degenerate cases made well-defined (see there); ``apply_similarity`` / ``align_poses`` move
predicted poses into the true frame, so that a picture compares like with like (pose-free
predictions have their own frame and scale).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from .errors import InputError
from .geometry import nearest_rotation

__all__ = ["draw_cameras", "CameraSet", "align_similarity", "apply_similarity", "align_poses",
           "PRED_COLOUR", "TRUE_COLOUR", "OTHER_COLOUR"]

#: Default colours (RGB): predicted cameras red, reference (true) cameras blue, a further set
#: (``CameraSet``) green.
PRED_COLOUR = (214, 39, 40)
TRUE_COLOUR = (31, 119, 180)
OTHER_COLOUR = (44, 160, 44)

_ELEVATION_DEG = 30.0
_AZIMUTH_DEG = 35.0
_FRUSTUM_FRACTION = 0.12         # frustum length / extent of the camera set
_COLLAPSE_RTOL = 1e-9            # spread <= this x coordinate magnitude: "all at one point"
_PRED_COLLAPSE_FRACTION = 0.01   # predicted spread < 1 % of the true spread: "collapsed" note
_MAX_HALF_FOV = 5.0              # tan of the half field of view drawn is clamped to [0.02, 5]
_MIN_HALF_FOV = 0.02


# ----------------------------------------------------------------------------------------------
# Similarity alignment
# ----------------------------------------------------------------------------------------------

def _skew(a: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def _rodrigues(axis: np.ndarray, theta: float) -> np.ndarray:
    """Rotation by ``theta`` about the unit ``axis``."""
    return (math.cos(theta) * np.eye(3) + math.sin(theta) * _skew(axis)
            + (1.0 - math.cos(theta)) * np.outer(axis, axis))


def _check_rotation(R, name: str) -> np.ndarray | None:
    if R is None:
        return None
    R = np.asarray(R, dtype=np.float64)
    if R.shape == (4, 4):
        R = R[:3, :3]
    if R.shape != (3, 3) or not np.isfinite(R).all():
        raise InputError(f"{name}: expected a finite 3x3 rotation (or 4x4 pose), got shape "
                         f"{R.shape}")
    return nearest_rotation(R)


def align_similarity(pred_centres, true_centres, *, pred_rotation=None, true_rotation=None
                     ) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity from predicted to true camera centres (Umeyama 1991).

    ``pred_centres, true_centres [N, 3]`` (row k of one is camera k of the other) -> ``(s, R, t)``
    with ``s >= 0``, ``R [3, 3]`` a rotation (det +1) and ``t [3]`` minimising
    ``sum_k |true_k - (s R pred_k + t)|^2``. Computed in float64.

    The minimiser is not unique in three degenerate cases; the result is then defined as follows
    (``pred_rotation`` / ``true_rotation``: rotation of the *first* camera, 3x3 or a 4x4 pose,
    optional; "R0" below is ``true_rotation @ pred_rotation.T``, the rotation that turns the first
    predicted camera into the first true one, or the identity when they are not given):

    - **the predicted centres are all equal** (a collapsed prediction; also N = 1), or the true ones
      are, or the two sets are exactly uncorrelated: the optimal scale is 0, every predicted centre
      maps to the true centroid (``t``), and R does not change the residual at all: ``s = 0``,
      ``R = R0``, ``t = mean(true_centres)``. So a collapsed prediction is drawn at the true
      centroid with its orientations turned by the first camera's rotation offset;
    - **the centres are collinear** (N = 2, cameras on a line): rotations about the line are free;
      of those, R is the one closest to R0 (closed form);
    - otherwise (planar or general position) the result is Umeyama's, unique.

    "All equal" means a spread (RMS distance from the centroid) of at most 1e-12 times the largest
    coordinate magnitude (so float rounding of large coordinates counts as collapsed).
    """
    P = np.asarray(pred_centres, dtype=np.float64)
    Q = np.asarray(true_centres, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3 or P.shape != Q.shape or P.shape[0] < 1:
        raise InputError(f"pred_centres, true_centres: expected two [N, 3] arrays with N >= 1, got "
                         f"shapes {P.shape} and {Q.shape}")
    if not (np.isfinite(P).all() and np.isfinite(Q).all()):
        raise InputError("pred_centres, true_centres: contain NaN or inf")
    Rp = _check_rotation(pred_rotation, "pred_rotation")
    Rq = _check_rotation(true_rotation, "true_rotation")
    R0 = np.eye(3) if Rp is None or Rq is None else Rq @ Rp.T

    # Umeyama is equivariant under scaling each set: solve for P / a, Q / b (a, b powers of two
    # near their magnitudes: exact, no overflow in the squares), then s = s' b / a, t = t' b.
    a = _power_of_two_scale(P)
    b = _power_of_two_scale(Q)
    s, R, t = _umeyama(P / a, Q / b, R0)
    return s * b / a, R, t * b


def _power_of_two_scale(X: np.ndarray) -> float:
    m = float(np.abs(X).max())
    return 2.0 ** math.ceil(math.log2(m)) if m > 0 else 1.0


def _umeyama(P: np.ndarray, Q: np.ndarray, R0: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    N = P.shape[0]
    mu_p, mu_q = P.mean(0), Q.mean(0)
    Pc, Qc = P - mu_p, Q - mu_q
    var_p = float(np.mean(np.sum(Pc * Pc, axis=1)))
    var_q = float(np.mean(np.sum(Qc * Qc, axis=1)))

    def collapsed(var, X):
        return not math.sqrt(var) > 1e-12 * max(float(np.abs(X).max()), 1e-300)

    Sigma = Qc.T @ Pc / N
    U, D, Vt = np.linalg.svd(Sigma)
    if collapsed(var_p, P) or collapsed(var_q, Q) or not D[0] > 0:
        return 0.0, R0, mu_q
    S = np.ones(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2] = -1.0
    R = (U * S) @ Vt
    s = float(np.sum(D * S) / var_p)
    if D[1] <= 1e-9 * D[0]:
        # Rank 1 (collinear centres): any rotation about the line's image is as good; take the
        # one closest to R0: maximise tr(Rot(a, th) M) with M = R R0^T over th.
        a = R @ Vt[0]
        a = a / np.linalg.norm(a)
        M = R @ R0.T
        c = float(np.trace(M) - a @ M @ a)
        b = float(np.trace(_skew(a) @ M))
        if abs(b) + abs(c) > 0:
            R = _rodrigues(a, math.atan2(b, c)) @ R
            R = nearest_rotation(R)
    t = mu_q - s * R @ mu_p
    return s, R, t


def apply_similarity(world_from_cam, s: float, R, t) -> np.ndarray:
    """Move poses ``world_from_cam [..., 4, 4]`` by ``x -> s R x + t``: rotations become
    ``R @ R_k``, centres ``s R c_k + t`` (a camera stays a rigid pose; its size is not scaled)."""
    T = np.array(world_from_cam, dtype=np.float64)
    R = np.asarray(R, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    T[..., :3, :3] = R @ T[..., :3, :3]
    T[..., :3, 3] = s * T[..., :3, 3] @ R.T + t
    T[..., 3, :] = (0.0, 0.0, 0.0, 1.0)
    return T


def align_poses(pred_world_from_cam, true_world_from_cam):
    """Predicted poses ``[N, 4, 4]`` moved into the frame of the true ones ``[N, 4, 4]`` by
    ``align_similarity`` of their centres (first cameras' rotations for the degenerate cases)
    -> ``(aligned [N, 4, 4], (s, R, t))``."""
    P = np.asarray(pred_world_from_cam, dtype=np.float64)
    Q = np.asarray(true_world_from_cam, dtype=np.float64)
    if P.ndim != 3 or P.shape[1:] != (4, 4) or P.shape != Q.shape or P.shape[0] < 1:
        raise InputError(f"pred_world_from_cam, true_world_from_cam: expected two [N, 4, 4] arrays "
                         f"with N >= 1, got shapes {P.shape} and {Q.shape}")
    s, R, t = align_similarity(P[:, :3, 3], Q[:, :3, 3], pred_rotation=P[0, :3, :3],
                               true_rotation=Q[0, :3, :3])
    return apply_similarity(P, s, R, t), (s, R, t)


# ----------------------------------------------------------------------------------------------
# Drawing
# ----------------------------------------------------------------------------------------------

def _check_cameras(T, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.ndim == 2 and T.shape == (4, 4):
        T = T[None]
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise InputError(f"{name}: expected world_from_cam [N, 4, 4] (or one 4x4), got shape "
                         f"{T.shape}")
    return T


def _half_extents(focal, n: int, name: str) -> np.ndarray:
    """tan of the half field of view ``[n, 2, 2]``: per camera ((x_left, x_right), (y_top, y_bottom))
    on the z = 1 plane, from K ``[3, 3]`` / ``[n, 3, 3]`` (image width = 2 cx, height = 2 cy), a
    normalised focal (fx/W) scalar, or ``[2]`` (fx/W, fy/H). None: focal 1 (53 degrees)."""
    default = np.array([[-0.5, 0.5], [-0.5, 0.5]])
    if focal is None:
        return np.broadcast_to(default, (n, 2, 2)).copy()
    f = np.asarray(focal, dtype=np.float64)
    if f.ndim == 0 or f.shape == (1,):
        f = np.repeat(f.reshape(1), 2)
    if f.shape == (2,):
        with np.errstate(divide="ignore", invalid="ignore"):
            h = 0.5 / f
        out = np.array([[-h[0], h[0]], [-h[1], h[1]]])
        out = np.broadcast_to(out, (n, 2, 2)).copy()
    elif f.shape == (3, 3) or (f.ndim == 3 and f.shape[1:] == (3, 3) and f.shape[0] == n):
        Ks = np.broadcast_to(f, (n, 3, 3))
        fx, fy, cx, cy = Ks[:, 0, 0], Ks[:, 1, 1], Ks[:, 0, 2], Ks[:, 1, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            out = np.stack([np.stack([-cx / fx, cx / fx], -1), np.stack([-cy / fy, cy / fy], -1)], 1)
    else:
        raise InputError(f"{name}: expected K [3, 3] or [N, 3, 3], a normalised focal (fx/W) or "
                         f"[fx/W, fy/H], got shape {f.shape}")
    bad = ~np.isfinite(out).all(axis=(1, 2)) | (out[:, :, 1] <= out[:, :, 0]).any(axis=1)
    out[bad] = default
    sign = np.sign(out)
    return sign * np.clip(np.abs(out), _MIN_HALF_FOV, _MAX_HALF_FOV)


def _frustum(T: np.ndarray, half: np.ndarray, length: float) -> np.ndarray:
    """Points of one frustum ``[8, 3]``: centre, 4 image corners (TL, TR, BR, BL), 3 of the up
    triangle (left, right, apex) on the top edge."""
    (x0, x1), (y0, y1) = half
    w = x1 - x0
    tri_h = 0.25 * (y1 - y0)
    cam = np.array([[0, 0, 0], [x0, y0, 1], [x1, y0, 1], [x1, y1, 1], [x0, y1, 1],
                    [x0 + 0.3 * w, y0, 1], [x1 - 0.3 * w, y0, 1], [0.5 * (x0 + x1), y0 - tri_h, 1]],
                   dtype=np.float64)
    cam[1:] *= length
    return cam @ T[:3, :3].T + T[:3, 3]


def _view_axes(rotations: np.ndarray) -> np.ndarray:
    """Rows: screen right, screen up, viewing direction (into the picture), from the cameras'
    mean up and forward directions (see the module docstring)."""
    up = -rotations[:, :, 1].mean(0)
    if not np.linalg.norm(up) > 0.3:              # cameras disagree about "up"
        up = np.array([0.0, -1.0, 0.0])
    up = up / np.linalg.norm(up)
    fwd = rotations[:, :, 2].mean(0)
    fwd = fwd - (fwd @ up) * up
    if not np.linalg.norm(fwd) > 1e-3:            # looking straight up or down
        helper = np.eye(3)[int(np.argmin(np.abs(up)))]
        fwd = helper - (helper @ up) * up
    fwd = fwd / np.linalg.norm(fwd)
    side = np.cross(up, fwd)
    el, az = math.radians(_ELEVATION_DEG), math.radians(_AZIMUTH_DEG)
    view = math.cos(el) * (math.cos(az) * fwd + math.sin(az) * side) - math.sin(el) * up
    view = view / np.linalg.norm(view)
    right = np.cross(view, up)
    right = right / np.linalg.norm(right)
    screen_up = np.cross(right, view)
    return np.stack([right, screen_up, view])


def _nice_length(target: float) -> float:
    """1, 2 or 5 times a power of ten, at most ``target`` (> 0)."""
    e = math.floor(math.log10(target))
    for m in (5.0, 2.0, 1.0):
        if m * 10.0 ** e <= target:
            return m * 10.0 ** e
    return 10.0 ** e


def _index_label(indices: list[int]) -> str:
    """"3", "0-7" for a run of consecutive indices, else "1,4,6"."""
    indices = sorted(indices)
    if len(indices) > 2 and indices == list(range(indices[0], indices[-1] + 1)):
        return f"{indices[0]}-{indices[-1]}"
    return ",".join(str(i) for i in indices)


def _spread(C: np.ndarray) -> float:
    return float(np.linalg.norm(C - C.mean(0), axis=1).max()) if len(C) else 0.0


def _is_collapsed(C: np.ndarray) -> bool:
    if len(C) < 2:
        return True
    spread = _spread(C)
    return not (spread > _COLLAPSE_RTOL * float(np.abs(C).max()) and spread > 1e-250)


@dataclass(frozen=True)
class CameraSet:
    """A further set of cameras for ``draw_cameras(..., others=[...])``, in the picture's frame.

    world_from_cam: [N, 4, 4]  OpenCV camera-to-world
    focal:          their intrinsics, as ``draw_cameras``' ``focal`` (None: focal 1)
    name:           the legend entry
    colour:         RGB
    labels:         [N] ints drawn beside the cameras (None: 0..N-1); e.g. frame indices when
                    the set holds some of the frames
    """
    world_from_cam: np.ndarray
    focal: object = None
    name: str = "other"
    colour: tuple[int, int, int] = OTHER_COLOUR
    labels: Sequence[int] | None = None


def draw_cameras(world_from_cam, focal=None, *, reference=None, reference_focal=None,
                 colours: Sequence[Sequence[int]] | None = None, size: tuple[int, int] = (360, 480),
                 labels: bool = True, title: str | None = None,
                 names: tuple[str, str] = ("predicted", "true"),
                 others: Sequence[CameraSet] = ()) -> np.ndarray:
    """Picture of camera frustums -> RGB ``uint8 [H, W, 3]`` (white background).

    ``world_from_cam [N, 4, 4]`` (OpenCV camera-to-world; one 4x4 also accepted): the cameras
    (e.g. predicted), drawn in ``colours[0]``. ``focal``: their intrinsics, ``K [3, 3]`` or
    ``[N, 3, 3]`` in pixels (the image is taken as 2 cx by 2 cy pixels), a normalised focal fx/W
    or ``[fx/W, fy/H]`` (the model's), or None (focal 1). ``reference [M, 4, 4]``: other cameras
    in the same frame (e.g. the true ones), drawn underneath in ``colours[1]`` with
    ``reference_focal`` (default: ``focal``). ``others``: further ``CameraSet``s in the same
    frame, drawn between the two, each in its colour, with its labels and legend entry.
    ``labels``: index of each camera beside its centre. ``names``: legend entries of the two
    sets (the second shown when ``reference`` is given). ``title``: one line at the top. Camera
    k and reference k are joined by a thin grey line when N == M.

    See the module docstring for the viewpoint and the degenerate cases.
    """
    H, W = (int(v) for v in size)
    if H < 32 or W < 32:
        raise InputError(f"size: expected (H, W) of at least 32x32, got {tuple(size)}")
    pred = _check_cameras(world_from_cam, "world_from_cam")
    ref = None if reference is None else _check_cameras(reference, "reference")
    colour_pred, colour_ref = (tuple(int(c) for c in col) for col in
                               (colours if colours is not None else (PRED_COLOUR, TRUE_COLOUR)))
    sets = [("pred", pred, _half_extents(focal, len(pred), "focal"))]
    if ref is not None:
        sets.insert(0, ("ref", ref, _half_extents(focal if reference_focal is None else
                                                  reference_focal, len(ref), "reference_focal")))
    # Per set: legend name, colour, labels, drawing rank (reference under the others under pred).
    style = {"pred": (names[0], colour_pred, None, 2), "ref": (names[1], colour_ref, None, 0)}
    if isinstance(others, CameraSet):
        others = (others,)
    for k, other in enumerate(others):
        if not isinstance(other, CameraSet):
            raise InputError(f"others[{k}]: expected a CameraSet, got {type(other).__name__}")
        T = _check_cameras(other.world_from_cam, f"others[{k}].world_from_cam")
        tags = None
        if other.labels is not None:
            tags = np.asarray(other.labels)
            if tags.shape != (len(T),) or not np.issubdtype(tags.dtype, np.integer):
                raise InputError(f"others[{k}].labels: expected {len(T)} integers (one per "
                                 f"camera) or None, got {other.labels!r}")
        key = f"other{k}"
        sets.insert(1 + k if ref is not None else k,
                    (key, T, _half_extents(other.focal, len(T), f"others[{k}].focal")))
        style[key] = (str(other.name), tuple(int(c) for c in other.colour), tags, 1)
    notes = []
    kept = {}
    for key, T, half in sets:
        finite = np.isfinite(T).all(axis=(1, 2))
        if not finite.all():
            notes.append(f"{int((~finite).sum())} non-finite camera(s) not drawn")
        idx = np.flatnonzero(finite)
        poses = np.zeros((len(idx), 4, 4))
        if len(idx):
            M = T[idx, :3, :3]
            size_m = np.abs(M).max(axis=(1, 2), keepdims=True)
            M = np.where(size_m > 0, M / np.where(size_m > 0, size_m, 1.0), np.eye(3))
            poses[:, :3, :3] = nearest_rotation(M)
        poses[:, :3, 3] = T[idx, :3, 3]
        poses[:, 3, 3] = 1.0
        kept[key] = (idx, poses, half[idx])
    # Work in coordinates divided by a power of two near their magnitude (exact, and no overflow
    # or underflow in the squares below whatever the scene's unit); the scale bar undoes it.
    magnitude = max([float(np.abs(p[:, :3, 3]).max()) for _, p, _ in kept.values() if len(p)],
                    default=0.0)
    coord_scale = 2.0 ** math.ceil(math.log2(magnitude)) if magnitude > 0 else 1.0
    for _, p, _ in kept.values():
        p[:, :3, 3] /= coord_scale

    # Normalised coordinates: centred on all cameras, in units of their spread.
    centres = np.concatenate([p[:, :3, 3] for _, p, _ in kept.values()]) if kept else np.zeros((0, 3))
    all_collapsed = _is_collapsed(centres)
    if len(centres) == 0:
        notes.append("no cameras")
        origin, unit = np.zeros(3), 1.0
    elif all_collapsed:
        origin, unit = centres.mean(0), 1.0
        if len(centres) > 1:
            notes.append("all cameras at one point (no scale)")
    else:
        origin = centres.mean(0)
        unit = _spread(centres)
    for key in [k for k in kept if k != "ref"] if ref is not None and not all_collapsed else ():
        if len(kept[key][0]) > 1 and len(kept["ref"][0]) > 1:
            sp, sr = _spread(kept[key][1][:, :3, 3]), _spread(kept["ref"][1][:, :3, 3])
            if sr > 0 and sp < _PRED_COLLAPSE_FRACTION * sr:
                notes.append(f"{style[key][0]} cameras collapsed (spread {100 * sp / sr:.2g} % "
                             f"of {names[1]})")
    length = 1.0 if all_collapsed else 2.0 * _FRUSTUM_FRACTION     # extent = 2 x spread

    frusta = {}
    for key, (idx, poses, half) in kept.items():
        local = poses.copy()
        local[:, :3, 3] = 0.0 if all_collapsed else (poses[:, :3, 3] - origin) / unit
        frusta[key] = np.stack([_frustum(T, h, length) for T, h in zip(local, half)]) \
            if len(idx) else np.zeros((0, 8, 3))

    view_set = kept["ref"][1] if "ref" in kept and len(kept["ref"][1]) else kept["pred"][1]
    rots = view_set[:, :3, :3] if len(view_set) else np.eye(3)[None]
    axes = _view_axes(rots)

    # Fit to the canvas (orthographic), with bands for the legend (top) and scale bar (bottom).
    font = cv2.FONT_HERSHEY_SIMPLEX
    fs = max(0.3, min(H, W) / 900.0)
    line_h = int(round(26 * fs)) + 4
    # Legend: (x, line, text, colour) per entry. A further set's entry starts a new line when it
    # would cross the right edge (the first two stay on one line whatever the width).
    entries = [(names[0], colour_pred)] + ([(names[1], colour_ref)] if ref is not None else []) \
        + [style[key][:2] for key in style if key.startswith("other")]
    legend, x, line = [], 6, 0
    for k, (text, colour) in enumerate(entries):
        width = int(24 * fs * 2) + cv2.getTextSize(text, font, fs, 1)[0][0]
        if k >= 2 and x > 6 and x + width > W - 6:
            x, line = 6, line + 1
        legend.append((x, line, text, colour))
        x += width + int(16 * fs * 2)
    top = line_h * (1 + line + (title is not None)) + 4
    bottom = line_h * (1 + len(notes)) + 6
    margin = max(8, W // 25)
    pts = np.concatenate([f.reshape(-1, 3) for f in frusta.values()]) if frusta else np.zeros((0, 3))
    if len(pts) == 0:
        pts = np.zeros((1, 3))
    xy = pts @ axes[:2].T
    lo, hi = xy.min(0), xy.max(0)
    span = np.maximum(hi - lo, 1e-9)
    avail = np.array([W - 2 * margin, max(H - top - bottom - 2 * margin, 8)], dtype=np.float64)
    scale = float(np.min(avail / span))
    mid = (lo + hi) / 2.0
    centre_px = np.array([W / 2.0, top + margin + avail[1] / 2.0])

    def to_px(p3):
        q = (p3 @ axes[:2].T - mid) * scale
        out = np.stack([centre_px[0] + q[..., 0], centre_px[1] - q[..., 1]], -1)
        return np.clip(np.nan_to_num(out), -4 * max(H, W), 4 * max(H, W))

    SHIFT = 4

    def ipt(p):
        return (int(round(p[0] * (1 << SHIFT))), int(round(p[1] * (1 << SHIFT))))

    img = np.full((H, W, 3), 255, dtype=np.uint8)
    thick = 1 if min(H, W) < 400 else 2

    # Correspondence lines camera k <-> reference k.
    if "ref" in frusta and len(kept["ref"][0]) == len(kept["pred"][0]) > 0 \
            and np.array_equal(kept["ref"][0], kept["pred"][0]):
        a, b = to_px(frusta["ref"][:, 0]), to_px(frusta["pred"][:, 0])
        for p, q in zip(a, b):
            cv2.line(img, ipt(p), ipt(q), (170, 170, 170), 1, cv2.LINE_AA, SHIFT)

    # Frustums of all sets, far to near (painter's order).
    items = []
    for key, F in frusta.items():
        colour = style[key][1]
        for k, f in enumerate(F):
            items.append((float(f[0] @ axes[2]), key, kept[key][0][k], f, colour))
    items.sort(key=lambda it: (-it[0], style[it[1]][3]))
    for _, key, index, f, colour in items:
        p = to_px(f)
        tk = thick
        for i in range(1, 5):
            cv2.line(img, ipt(p[0]), ipt(p[i]), colour, tk, cv2.LINE_AA, SHIFT)
            cv2.line(img, ipt(p[i]), ipt(p[1 + i % 4]), colour, tk, cv2.LINE_AA, SHIFT)
        tri = np.array([ipt(q) for q in p[5:8]], dtype=np.int32)
        cv2.fillConvexPoly(img, tri, colour, cv2.LINE_AA, SHIFT)
        cv2.circle(img, ipt(p[0]), (tk + 1) << SHIFT, colour, -1, cv2.LINE_AA, SHIFT)
    if labels:
        for key in sorted(frusta, key=lambda k: style[k][3]):
            _, colour, tags, _ = style[key]
            # Cameras drawn at the same spot (a collapsed set) share one label "0-7" / "1,4".
            groups: dict[tuple[int, int], list] = {}
            for index, f in zip(kept[key][0], frusta[key]):
                c = to_px(f[0])
                label = int(index) if tags is None else int(tags[index])
                groups.setdefault((int(c[0] // 4), int(c[1] // 4)), []).append((label, f, c))
            for members in groups.values():
                _, f, c = members[0]
                text = _index_label([m[0] for m in members])
                (tw, th), _ = cv2.getTextSize(text, font, fs, 1)
                # Beside the centre, on the side away from the frustum's image rectangle.
                away = c - to_px(f[1:5]).mean(0)
                n = np.linalg.norm(away)
                away = away / n if n > 1e-6 else np.array([-1.0, 0.0])
                at = c + away * (6 + 0.6 * max(tw, th)) + np.array([-tw / 2, th / 2])
                org = np.clip(at, [0, top + th], [max(W - tw, 0), H - bottom])
                cv2.putText(img, text, (int(org[0]), int(org[1])), font, fs, colour, 1,
                            cv2.LINE_AA)

    # Legend and title.
    y = line_h
    if title is not None:
        cv2.putText(img, title, (6, y), font, fs, (0, 0, 0), 1, cv2.LINE_AA)
        y += line_h
    for x, line, text, colour in legend:
        yl = y + line * line_h
        cv2.rectangle(img, (x, yl - int(14 * fs * 2) // 2 - 2), (x + int(20 * fs * 2), yl - 2),
                      colour, -1)
        cv2.putText(img, text, (x + int(24 * fs * 2), yl), font, fs, (0, 0, 0), 1, cv2.LINE_AA)

    # Scale bar (scene units) and notes.
    y = H - 6 - line_h * len(notes)
    if not all_collapsed:
        per_px = unit * coord_scale / scale        # scene units per pixel
        bar = _nice_length(0.2 * W * per_px)
        bar_px = bar / per_px
        x0 = margin
        cv2.line(img, (x0, y - 4), (int(x0 + bar_px), y - 4), (0, 0, 0), 2)
        for xe in (x0, int(x0 + bar_px)):
            cv2.line(img, (xe, y - 9), (xe, y + 1), (0, 0, 0), 1)
        cv2.putText(img, f"{bar:g} units", (int(x0 + bar_px) + 8, y), font, fs, (0, 0, 0), 1,
                    cv2.LINE_AA)
    for k, text in enumerate(notes):
        cv2.putText(img, text, (6, H - 6 - line_h * (len(notes) - 1 - k)), font, fs, (120, 0, 0), 1,
                    cv2.LINE_AA)
    return img
