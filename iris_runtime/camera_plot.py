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

``align_similarity``, ``apply_similarity`` and ``align_poses`` (Umeyama's similarity between
camera centres, which moves predicted poses into the true frame: pose-free predictions have their
own frame and scale) are ``iris_runtime.camera_align``'s, importable from here too.

``draw_cameras``' steps: the sets checked (``_camera_sets``), their finite cameras
(``_finite_cameras``), a frame centred on them in units of their spread (``_frame``), their
frustums (``_frusta``), the canvas fitted to those (``_fit``), then the drawing (``_draw_*``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import cv2
import numpy as np

from .camera_align import align_poses, align_similarity, apply_similarity
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
    # A zero, subnormal or non-finite focal divides to inf or NaN (or overflows): intended, since
    # every camera whose extents are not finite and ordered gets the default ones below (`bad`).
    if f.shape == (2,):
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
            h = 0.5 / f
        out = np.array([[-h[0], h[0]], [-h[1], h[1]]])
        out = np.broadcast_to(out, (n, 2, 2)).copy()
    elif f.shape == (3, 3) or (f.ndim == 3 and f.shape[1:] == (3, 3) and f.shape[0] == n):
        Ks = np.broadcast_to(f, (n, 3, 3))
        fx, fy, cx, cy = Ks[:, 0, 0], Ks[:, 1, 1], Ks[:, 0, 2], Ks[:, 1, 2]
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
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
    sets, style = _camera_sets(world_from_cam, focal, reference, reference_focal, colours, names,
                               others)
    notes: list[str] = []
    kept, coord_scale = _finite_cameras(sets, notes)
    origin, unit, all_collapsed = _frame(kept, style, names, notes)
    frusta = _frusta(kept, origin, unit, all_collapsed)

    view_set = kept["ref"][1] if "ref" in kept and len(kept["ref"][1]) else kept["pred"][1]
    rots = view_set[:, :3, :3] if len(view_set) else np.eye(3)[None]
    # The legend: the two sets' entries, then the further sets'.
    entries = [style["pred"][:2]] + ([style["ref"][:2]] if "ref" in kept else []) \
        + [style[key][:2] for key in style if key.startswith("other")]
    canvas, legend = _fit(H, W, frusta, _view_axes(rots), entries, title, len(notes))

    img = np.full((H, W, 3), 255, dtype=np.uint8)
    _draw_correspondences(img, canvas, kept, frusta)
    _draw_frusta(img, canvas, kept, frusta, style)
    if labels:
        _draw_labels(img, canvas, kept, frusta, style)
    _draw_legend(img, canvas, legend, title)
    _draw_scale_bar_and_notes(img, canvas, notes, None if all_collapsed else unit * coord_scale)
    return img


# -- the sets, their cameras and their frame ---------------------------------------------------
def _camera_sets(world_from_cam, focal, reference, reference_focal, colours, names, others):
    """``draw_cameras``' sets checked -> ``(sets, style)``: ``sets`` a list of ``(key,
    world_from_cam [n, 4, 4], half extents [n, 2, 2])``, the reference ("ref") first, then the
    further sets ("other0", ...), then the cameras ("pred"); ``style[key]``: (legend name,
    colour, labels or None, drawing rank: reference under the others under pred)."""
    pred = _check_cameras(world_from_cam, "world_from_cam")
    ref = None if reference is None else _check_cameras(reference, "reference")
    colour_pred, colour_ref = (tuple(int(c) for c in col) for col in
                               (colours if colours is not None else (PRED_COLOUR, TRUE_COLOUR)))
    sets = [("pred", pred, _half_extents(focal, len(pred), "focal"))]
    if ref is not None:
        sets.insert(0, ("ref", ref, _half_extents(focal if reference_focal is None else
                                                  reference_focal, len(ref), "reference_focal")))
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
    return sets, style


def _finite_cameras(sets, notes: list[str]) -> tuple[dict, float]:
    """Each set's finite cameras -> ``(kept, coord_scale)``: ``kept[key] = (their indices, poses
    [n, 4, 4] with the nearest rotations and the centres divided by coord_scale, half extents
    [n, 2, 2])``; a note for the cameras left out."""
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
    return kept, coord_scale


def _frame(kept: dict, style: dict, names, notes: list[str]) -> tuple[np.ndarray, float, bool]:
    """Normalised coordinates: centred on all cameras, in units of their spread -> ``(origin [3],
    unit, all_collapsed)``; notes for cameras all at one point and for a set collapsed next to
    the reference."""
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
    for key in [k for k in kept if k != "ref"] if "ref" in kept and not all_collapsed else ():
        if len(kept[key][0]) > 1 and len(kept["ref"][0]) > 1:
            sp, sr = _spread(kept[key][1][:, :3, 3]), _spread(kept["ref"][1][:, :3, 3])
            if sr > 0 and sp < _PRED_COLLAPSE_FRACTION * sr:
                notes.append(f"{style[key][0]} cameras collapsed (spread {100 * sp / sr:.2g} % "
                             f"of {names[1]})")
    return origin, unit, all_collapsed


def _frusta(kept: dict, origin: np.ndarray, unit: float, all_collapsed: bool) -> dict:
    """Each set's frustums ``[n, 8, 3]`` (``_frustum``) in the normalised coordinates."""
    length = 1.0 if all_collapsed else 2.0 * _FRUSTUM_FRACTION     # extent = 2 x spread
    frusta = {}
    for key, (idx, poses, half) in kept.items():
        local = poses.copy()
        local[:, :3, 3] = 0.0 if all_collapsed else (poses[:, :3, 3] - origin) / unit
        frusta[key] = np.stack([_frustum(T, h, length) for T, h in zip(local, half)]) \
            if len(idx) else np.zeros((0, 8, 3))
    return frusta


# -- the canvas ---------------------------------------------------------------------------------
_SHIFT = 4                      # OpenCV's fractional bits of the points drawn
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def _ipt(p) -> tuple[int, int]:
    return (int(round(p[0] * (1 << _SHIFT))), int(round(p[1] * (1 << _SHIFT))))


@dataclass(frozen=True)
class _Canvas:
    """Where things go in an H x W picture: text size ``fs`` and line height, the bands of the
    legend (``top``) and of the scale bar and notes (``bottom``), and the orthographic fit of the
    frustums (``axes``: screen right, up, into the picture; ``mid``, ``scale``, ``centre_px``)."""
    H: int
    W: int
    fs: float
    line_h: int
    top: int
    bottom: int
    margin: int
    axes: np.ndarray
    mid: np.ndarray
    scale: float
    centre_px: np.ndarray

    def to_px(self, p3):
        """Points ``[..., 3]`` -> pixels ``[..., 2]`` (clipped, finite)."""
        H, W = self.H, self.W
        q = (p3 @ self.axes[:2].T - self.mid) * self.scale
        out = np.stack([self.centre_px[0] + q[..., 0], self.centre_px[1] - q[..., 1]], -1)
        return np.clip(np.nan_to_num(out), -4 * max(H, W), 4 * max(H, W))


def _fit(H: int, W: int, frusta: dict, axes: np.ndarray, entries, title, n_notes: int):
    """The canvas fitted to the frustums (orthographic), with bands for the legend (top) and the
    scale bar and notes (bottom) -> ``(canvas, legend)``, ``legend`` a list of ``(x, line, text,
    colour)``. A further set's entry starts a new line when it would cross the right edge (the
    first two stay on one line whatever the width)."""
    font = _FONT
    fs = max(0.3, min(H, W) / 900.0)
    line_h = int(round(26 * fs)) + 4
    legend, x, line = [], 6, 0
    for k, (text, colour) in enumerate(entries):
        width = int(24 * fs * 2) + cv2.getTextSize(text, font, fs, 1)[0][0]
        if k >= 2 and x > 6 and x + width > W - 6:
            x, line = 6, line + 1
        legend.append((x, line, text, colour))
        x += width + int(16 * fs * 2)
    top = line_h * (1 + line + (title is not None)) + 4
    bottom = line_h * (1 + n_notes) + 6
    margin = max(8, W // 25)
    pts = np.concatenate([f.reshape(-1, 3) for f in frusta.values()]) if frusta else np.zeros((0, 3))
    if len(pts) == 0:
        pts = np.zeros((1, 3))
    xy = pts @ axes[:2].T
    lo, hi = xy.min(0), xy.max(0)
    span = np.maximum(hi - lo, 1e-9)
    avail = np.array([W - 2 * margin, max(H - top - bottom - 2 * margin, 8)], dtype=np.float64)
    scale = float(np.min(avail / span))
    centre_px = np.array([W / 2.0, top + margin + avail[1] / 2.0])
    return _Canvas(H, W, fs, line_h, top, bottom, margin, axes, (lo + hi) / 2.0, scale,
                   centre_px), legend


# -- drawing ------------------------------------------------------------------------------------
def _draw_correspondences(img: np.ndarray, canvas: _Canvas, kept: dict, frusta: dict) -> None:
    """Thin grey lines joining camera k and reference k (when both sets keep the same cameras)."""
    if "ref" in frusta and len(kept["ref"][0]) == len(kept["pred"][0]) > 0 \
            and np.array_equal(kept["ref"][0], kept["pred"][0]):
        a, b = canvas.to_px(frusta["ref"][:, 0]), canvas.to_px(frusta["pred"][:, 0])
        for p, q in zip(a, b):
            cv2.line(img, _ipt(p), _ipt(q), (170, 170, 170), 1, cv2.LINE_AA, _SHIFT)


def _draw_frusta(img: np.ndarray, canvas: _Canvas, kept: dict, frusta: dict,
                 style: dict) -> None:
    """Frustums of all sets, far to near (painter's order; at one depth, by the sets' rank)."""
    thick = 1 if min(canvas.H, canvas.W) < 400 else 2
    items = []
    for key, F in frusta.items():
        colour = style[key][1]
        for k, f in enumerate(F):
            items.append((float(f[0] @ canvas.axes[2]), key, kept[key][0][k], f, colour))
    items.sort(key=lambda it: (-it[0], style[it[1]][3]))
    for _, key, index, f, colour in items:
        p = canvas.to_px(f)
        tk = thick
        for i in range(1, 5):
            cv2.line(img, _ipt(p[0]), _ipt(p[i]), colour, tk, cv2.LINE_AA, _SHIFT)
            cv2.line(img, _ipt(p[i]), _ipt(p[1 + i % 4]), colour, tk, cv2.LINE_AA, _SHIFT)
        tri = np.array([_ipt(q) for q in p[5:8]], dtype=np.int32)
        cv2.fillConvexPoly(img, tri, colour, cv2.LINE_AA, _SHIFT)
        cv2.circle(img, _ipt(p[0]), (tk + 1) << _SHIFT, colour, -1, cv2.LINE_AA, _SHIFT)


def _draw_labels(img: np.ndarray, canvas: _Canvas, kept: dict, frusta: dict, style: dict) -> None:
    """Each camera's index (or its set's label) beside its centre."""
    font, fs, to_px = _FONT, canvas.fs, canvas.to_px
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
            org = np.clip(at, [0, canvas.top + th], [max(canvas.W - tw, 0),
                                                     canvas.H - canvas.bottom])
            cv2.putText(img, text, (int(org[0]), int(org[1])), font, fs, colour, 1,
                        cv2.LINE_AA)


def _draw_legend(img: np.ndarray, canvas: _Canvas, legend, title) -> None:
    """The title (one line) and the legend's entries below it."""
    font, fs, line_h = _FONT, canvas.fs, canvas.line_h
    y = line_h
    if title is not None:
        cv2.putText(img, title, (6, y), font, fs, (0, 0, 0), 1, cv2.LINE_AA)
        y += line_h
    for x, line, text, colour in legend:
        yl = y + line * line_h
        cv2.rectangle(img, (x, yl - int(14 * fs * 2) // 2 - 2), (x + int(20 * fs * 2), yl - 2),
                      colour, -1)
        cv2.putText(img, text, (x + int(24 * fs * 2), yl), font, fs, (0, 0, 0), 1, cv2.LINE_AA)


def _draw_scale_bar_and_notes(img: np.ndarray, canvas: _Canvas, notes: list[str],
                              unit: float | None) -> None:
    """A scale bar in scene units (``unit``: the scene units of one normalised unit; None: no
    scale, the cameras are all at one point) and the notes under it."""
    font, fs, line_h, H = _FONT, canvas.fs, canvas.line_h, canvas.H
    y = H - 6 - line_h * len(notes)
    if unit is not None:
        per_px = unit / canvas.scale               # scene units per pixel
        bar = _nice_length(0.2 * canvas.W * per_px)
        bar_px = bar / per_px
        x0 = canvas.margin
        cv2.line(img, (x0, y - 4), (int(x0 + bar_px), y - 4), (0, 0, 0), 2)
        for xe in (x0, int(x0 + bar_px)):
            cv2.line(img, (xe, y - 9), (xe, y + 1), (0, 0, 0), 1)
        cv2.putText(img, f"{bar:g} units", (int(x0 + bar_px) + 8, y), font, fs, (0, 0, 0), 1,
                    cv2.LINE_AA)
    for k, text in enumerate(notes):
        cv2.putText(img, text, (6, H - 6 - line_h * (len(notes) - 1 - k)), font, fs, (120, 0, 0), 1,
                    cv2.LINE_AA)
