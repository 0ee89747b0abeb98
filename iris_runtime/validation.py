"""The one validation layer at IRIS's public boundary: cameras and images (numpy only).

Three checks, each with one documented tolerance, used by every public entry (``IrisRuntime``,
the camera readers and writers of ``camera_io``, ``images.load_image``, ``iris-render``); code
behind them trusts what they return and checks nothing again.

- ``check_world_from_cam``: a rigid camera-to-world pose ``[4, 4]`` (or ``[N, 4, 4]``), to
  ``RIGID_ATOL``. ``snap_world_from_cam`` is its one relaxation, for readers of *text* camera
  files only (see "Rigidity policy").
- ``check_intrinsics``: pinhole ``K [3, 3]`` (or one per view), structure to ``INTRINSICS_ATOL``.
- ``check_images``: a numpy image array (shape, dtype, finite; float values in [0, 1] to
  ``FLOAT_IMAGE_ATOL``).

Every failure is a typed error (``InputError`` for cameras, ``ImageError`` for images) whose
message starts with the argument's name and says what was expected and what was found.
``check_integer`` is the one check of a count (sizes, samples, views, threads, frames) for every
caller, with the caller's error type.

Rigidity policy
---------------
One strict check, ``RIGID_ATOL = 1e-4`` on ``max(|R^T R - I|, |det R - 1|, |last row - [0, 0, 0, 1]|)``.
It accepts every pose IRIS itself makes or passes on (the encoder's float32 poses are rigid to
~1e-7, float64 compositions to ~1e-15, poses written with >= 5 decimals to ~1e-5) and rejects
every pose that is really something else: a scale by 1.001 (error 2e-3), a shear, a mirror
(det -1, error 2), a projective last row. The check never changes its input (it returns it as
float64), so a pose that passes renders bit for bit as given.

Camera files written by other tools carry rounded numbers: a rotation printed with 3 or 4 decimals
is orthonormal only to ~1e-3. So the readers of text camera files (``camera_io``'s
``transforms.json`` reader, ``iris-render --pose`` JSON) call ``snap_world_from_cam``: a matrix
that passes the strict check is returned as is (IRIS's own files round-trip bit for bit); one
rigid only to ``SNAP_ATOL = 1e-3`` is replaced by the nearest rigid transform (rotation block by
``nearest_rotation``, the translation kept, last row set to [0, 0, 0, 1]); beyond, the same
``InputError`` as the strict check. That is the only place a pose is changed, and everything it
returns passes the strict check. COLMAP's quaternions need neither: a normalised quaternion is a
rotation by construction.
"""
from __future__ import annotations

import numpy as np

from .errors import ImageError, InputError

__all__ = ["RIGID_ATOL", "SNAP_ATOL", "INTRINSICS_ATOL", "FLOAT_IMAGE_ATOL", "rigidity_error",
           "nearest_rotation", "check_world_from_cam", "snap_world_from_cam", "check_intrinsics",
           "check_images", "check_integer"]

#: The one tolerance of a rigid ``world_from_cam``: max of |R^T R - I|, |det R - 1| and
#: |last row - [0, 0, 0, 1]| (see the module docstring for why 1e-4).
RIGID_ATOL = 1e-4
#: Readers of text camera files only: a pose rigid to this (3-4 printed decimals) is snapped to the
#: nearest rigid transform by ``snap_world_from_cam``; nothing else relaxes ``RIGID_ATOL``.
SNAP_ATOL = 1e-3
#: The fixed entries of a pinhole K (K[0, 1] = K[1, 0] = K[2, 0] = K[2, 1] = 0, K[2, 2] = 1) must
#: hold to this, absolute. They are exact in any K built entry by entry, scaled or cropped (what
#: IRIS and calibration files give); 1e-9 still forgives float64 round-off of a decomposed
#: projection matrix (~1e-16 |K|). A larger skew or a projective last row is another camera model,
#: which the renderer does not implement.
INTRINSICS_ATOL = 1e-9
#: Float images hold values in [0, 1]; values beyond by at most this (float32 rounding of a
#: computation, ~8 ulp at 1) are clipped, anything further raises ``ImageError``.
FLOAT_IMAGE_ATOL = 1e-6


# ----------------------------------------------------------------------------------------------
# world_from_cam
# ----------------------------------------------------------------------------------------------

def rigidity_error(T: np.ndarray) -> np.ndarray:
    """``max(|R^T R - I|, |det R - 1|, |T[3] - [0, 0, 0, 1]|)`` of finite ``T [..., 4, 4]`` ->
    ``[...]`` float64 (0 for an exact rigid transform, 2 for a mirror, >= 1 when singular)."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    # Entries near the float64 limit overflow R^T R and det R: such a matrix is as far from
    # rigid as can be, so inf (never NaN, which no comparison would refuse) and no warning.
    with np.errstate(over="ignore", invalid="ignore"):
        ortho = np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3)).max(axis=(-2, -1))
        det = np.abs(np.linalg.det(R) - 1.0)
        bottom = np.abs(T[..., 3, :] - [0.0, 0.0, 0.0, 1.0]).max(axis=-1)
        err = np.maximum(np.maximum(ortho, det), bottom)
    return np.where(np.isnan(err), np.inf, err)


def nearest_rotation(M: np.ndarray) -> np.ndarray:
    """The rotation closest to ``M [..., 3, 3]`` in Frobenius norm: ``U D V^T`` of the SVD
    ``M = U S V^T`` with ``D = diag(1, 1, sign det(U V^T))`` (det +1 also for a mirrored ``M``;
    finite for any finite ``M``). ``geometry.nearest_rotation`` is this function."""
    U, _, Vt = np.linalg.svd(M)
    d = np.sign(np.linalg.det(U @ Vt))
    d = np.where(d == 0, 1.0, d)
    U = U.copy()
    U[..., :, 2] *= d[..., None]
    return U @ Vt


def _pose_array(value, name: str, batch: bool) -> np.ndarray:
    """``value`` as float64 ``[4, 4]`` (``batch``: ``[N, 4, 4]``, N >= 1), finite, else InputError."""
    try:
        T = np.asarray(value)
    except Exception:                          # ragged nested lists and other non-arrays
        T = np.asarray(None, dtype=object)
    if T.dtype == object or not (np.issubdtype(T.dtype, np.floating)
                                 or np.issubdtype(T.dtype, np.integer)):
        what = "an array of 4x4 world_from_cam matrices" if batch else "a 4x4 world_from_cam matrix"
        raise InputError(f"{name}: expected {what} of numbers, got {type(value).__name__} of "
                         f"dtype {T.dtype}")
    if batch and (T.ndim != 3 or T.shape[1:] != (4, 4) or T.shape[0] == 0):
        raise InputError(f"{name}: expected an array of shape [V, 4, 4] with V >= 1, got shape "
                         f"{T.shape}")
    if not batch and T.shape != (4, 4):
        raise InputError(f"{name}: expected a 4x4 world_from_cam matrix, got shape {T.shape}")
    T = T.astype(np.float64)
    finite = np.isfinite(T).all(axis=(-2, -1))
    if not np.all(finite):
        where = f"{name}[{int(np.argmin(finite))}]" if batch else name
        raise InputError(f"{where}: contains NaN or inf")
    return T


def _not_rigid(T: np.ndarray, name: str, atol: float) -> InputError:
    """The error for one finite ``T [4, 4]`` whose rigidity error exceeds ``atol``: what is wrong."""
    R = T[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):      # huge entries: det inf or NaN
        det = float(np.linalg.det(R))
        err = float(np.abs(R.T @ R - np.eye(3)).max())
    if abs(det) <= atol:
        why = f"its rotation block is singular (det {det:.2g})"
    elif det < 0:
        why = f"it is mirrored (det {det:.3g} < 0): a reflection is not a camera pose"
    elif np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > atol:
        why = f"its last row is {T[3].tolist()}, expected [0, 0, 0, 1]"
    else:
        why = f"its rotation block is not orthonormal (max |R^T R - I| = {err:.2g}, det {det:.4g})"
    return InputError(f"{name}: expected a rigid camera-to-world transform (orthonormal rotation "
                      f"with det +1, last row [0, 0, 0, 1], to within {atol:g}), but {why}")


def check_world_from_cam(value, name: str = "pose", *, batch: bool = False) -> np.ndarray:
    """``value`` as a float64 rigid ``world_from_cam`` ``[4, 4]`` (``batch=True``: ``[N, 4, 4]``
    with N >= 1), or ``InputError`` naming ``name`` (``name[i]`` for view i of a batch) and what is
    wrong: not numeric, shape, NaN/inf, singular, mirrored (det < 0), not orthonormal, last row not
    [0, 0, 0, 1]; tolerance ``RIGID_ATOL``. The values are returned unchanged (a float64 copy)."""
    T = _pose_array(value, name, batch)
    err = rigidity_error(T)
    bad = np.flatnonzero(np.atleast_1d(err > RIGID_ATOL))
    if bad.size:
        i = int(bad[0])
        raise _not_rigid(T[i] if batch else T, f"{name}[{i}]" if batch else name, RIGID_ATOL)
    return T


def snap_world_from_cam(value, name: str) -> np.ndarray:
    """For readers of text camera files only: ``value [4, 4]`` (numbers from a file) as a rigid
    float64 ``world_from_cam``. Rigid to ``RIGID_ATOL``: returned unchanged. Rigid to
    ``SNAP_ATOL`` (rounded decimals): the nearest rigid transform (rotation ``nearest_rotation(R)``,
    translation kept, last row [0, 0, 0, 1]). Otherwise ``InputError``."""
    T = _pose_array(value, name, batch=False)
    err = float(rigidity_error(T))
    if err <= RIGID_ATOL:
        return T
    if err > SNAP_ATOL:
        raise _not_rigid(T, name, SNAP_ATOL)
    T[:3, :3] = nearest_rotation(T[:3, :3])
    T[3] = [0.0, 0.0, 0.0, 1.0]
    return T


# ----------------------------------------------------------------------------------------------
# Intrinsics
# ----------------------------------------------------------------------------------------------

def check_intrinsics(value, name: str = "intrinsics", height: int | None = None,
                     width: int | None = None, *, views: int | None = None) -> np.ndarray:
    """``value`` as float64 pinhole intrinsics ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels
    (fx, fy > 0, finite; the fixed entries to ``INTRINSICS_ATOL``), or ``InputError`` naming
    ``name``. ``height, width``: the image K refers to (named in the message only: the principal
    point may lie anywhere, e.g. for tiles). ``views=V``: a shared ``[3, 3]`` or per-view
    ``[V, 3, 3]``, returned as ``[V, 3, 3]``. Values are returned unchanged."""
    try:
        K = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name}: expected a 3x3 matrix of numbers, got "
                         f"{type(value).__name__}") from None
    per_view = views is not None and K.shape != (3, 3)
    if views is not None:
        if K.shape == (3, 3):
            K = np.broadcast_to(K, (views, 3, 3)).copy()
        if K.shape != (views, 3, 3):
            raise InputError(f"{name}: expected shape [3, 3] or [{views}, 3, 3], got {K.shape}")
    elif K.shape != (3, 3):
        raise InputError(f"{name}: expected a finite 3x3 matrix, got shape {K.shape}")
    Ks = K.reshape(-1, 3, 3)
    finite = np.isfinite(Ks).all(axis=(1, 2))
    if not np.all(finite):
        where = f"{name}[{int(np.argmin(finite))}]" if per_view else name
        raise InputError(f"{where}: expected a finite 3x3 matrix, got NaN or inf")
    fixed = np.stack([Ks[:, 0, 1], Ks[:, 1, 0], Ks[:, 2, 0], Ks[:, 2, 1], Ks[:, 2, 2] - 1.0], -1)
    bad = (Ks[:, 0, 0] <= 0) | (Ks[:, 1, 1] <= 0) | (np.abs(fixed) > INTRINSICS_ATOL).any(-1)
    if np.any(bad):
        i = int(np.argmax(bad))
        where = f"{name}[{i}]" if per_view else name
        image = f"a {height}x{width} image" if height and width else "the image"
        raise InputError(f"{where}: expected pinhole [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in "
                         f"pixels of {image} with fx, fy > 0 (no skew), got {Ks[i].tolist()}")
    return K


# ----------------------------------------------------------------------------------------------
# Images
# ----------------------------------------------------------------------------------------------

def _range_hint(lo: float, hi: float) -> str:
    if hi > 255.0 + FLOAT_IMAGE_ATOL:
        return ("looks like 16-bit values (0..65535): divide by 65535, or pass the uint16 array "
                "itself")
    if hi > 2.0:
        return "looks like 0..255 values: divide by 255, or pass a uint8 array"
    if lo < -0.5:
        return "looks like values in [-1, 1] (a normalised tensor): pass (image + 1) / 2"
    return ("if the excess is an overshoot of resampling or filtering, clip it first: "
            "np.clip(image, 0, 1)")


def check_images(value, name: str = "image", *, batch: bool = False) -> np.ndarray:
    """``value`` checked as a numpy image array and returned unchanged, or ``ImageError`` naming
    ``name``.

    One image (default): shape ``[H, W]``, ``[H, W, 1]``, ``[H, W, 3]`` or ``[H, W, 4]``, H, W >= 1.
    ``batch=True``: channels-first RGB ``[N, 3, H, W]``, N, H, W >= 1 (the encoder's layout).
    dtype uint8, uint16 or float; float values finite and in [0, 1] to ``FLOAT_IMAGE_ATOL``
    (the error says how to fix 0..255, 0..65535 and [-1, 1] data).
    """
    if not isinstance(value, np.ndarray):
        raise ImageError(f"{name}: expected a numpy array, got {type(value).__name__}")
    a = value
    if batch:
        if a.ndim != 4 or a.shape[1] != 3 or 0 in a.shape:
            raise ImageError(f"{name}: expected an array of shape [N, 3, H, W] with N, H, W >= 1, "
                             f"got shape {tuple(a.shape)}")
    else:
        if not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (1, 3, 4))):
            raise ImageError(
                f"{name}: expected an array of shape [H, W], [H, W, 1], [H, W, 3] or [H, W, 4], "
                f"got shape {tuple(a.shape)}")
        if a.shape[0] == 0 or a.shape[1] == 0:
            raise ImageError(f"{name}: image is empty (shape {tuple(a.shape)})")
    if a.dtype in (np.uint8, np.uint16):
        return a
    if not np.issubdtype(a.dtype, np.floating):
        raise ImageError(
            f"{name}: expected dtype uint8, uint16 or float (values in [0, 1]), got {a.dtype}")
    if not np.all(np.isfinite(a)):
        raise ImageError(f"{name}: float image contains NaN or inf")
    lo, hi = float(a.min()), float(a.max())
    if lo < -FLOAT_IMAGE_ATOL or hi > 1.0 + FLOAT_IMAGE_ATOL:
        raise ImageError(f"{name}: float image values must lie in [0, 1], got [{lo:.4g}, "
                         f"{hi:.4g}]; {_range_hint(lo, hi)}")
    return a


# ----------------------------------------------------------------------------------------------
# Counts
# ----------------------------------------------------------------------------------------------

def check_integer(value, name: str, *, minimum: int = 1, allow_none: bool = False,
                  error: type[Exception] = InputError) -> int | None:
    """``value`` as a Python int ``>= minimum`` (numpy integers accepted, bools refused), or
    ``error`` naming ``name``: "expected a positive integer" (``minimum`` 1), "a non-negative
    integer" (0), "an integer >= minimum" otherwise, "or None" with ``allow_none`` (None is then
    returned as is)."""
    if value is None and allow_none:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) \
            or value < minimum:
        what = {1: "a positive integer", 0: "a non-negative integer"}.get(
            minimum, f"an integer >= {minimum}")
        raise error(f"{name}: expected {what}{' or None' if allow_none else ''}, got {value!r}")
    return int(value)
