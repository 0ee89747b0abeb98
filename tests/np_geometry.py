"""Numpy twins of ``iris_train.geometry`` functions that the runtime itself does not need (moved
here from ``iris_runtime.geometry``): the runtime builds its pixel centres per block of rays
(``iris_runtime.raymarch.trace_block``), composes no poses, and gets rotations from the encoder
graph (6D -> matrix inside ONNX). The tests keep them as float64 references: twins of the torch
functions (tests/test_geometry.py), checks of the exported encoder's rotations and of the float32
fallbacks (tests/test_stability.py), probe poses (tests/test_export.py).
"""
from __future__ import annotations

import numpy as np


def pixel_centres(height: int, width: int, dtype=np.float64) -> np.ndarray:
    """Pixel centres ``[H*W, 2]`` as (u, v) = (j + 0.5, i + 0.5), row-major."""
    v, u = np.meshgrid(np.arange(height, dtype=dtype) + 0.5, np.arange(width, dtype=dtype) + 0.5,
                       indexing="ij")
    return np.stack([u.ravel(), v.ravel()], axis=-1)


def compose(a_from_b: np.ndarray, b_from_c: np.ndarray) -> np.ndarray:
    """``a_from_c = a_from_b @ b_from_c`` (named so the frames chain visibly)."""
    return a_from_b @ b_from_c


def rotation_from_6d(a: np.ndarray) -> np.ndarray:
    """6D rotation ``[..., 6]`` (two columns a1, a2) to a rotation matrix ``[..., 3, 3]``.

    Gram-Schmidt: b1 = a1/|a1|, b2 = unit(a2 - (b1.a2) b1), b3 = b1 x b2; columns [b1, b2, b3].
    Degenerate inputs stay finite and orthonormal with det +1: where |a1| is below ``tol`` times
    the input's scale, b1 falls back to x; where a2's part orthogonal to b1 is below it (a2 zero or
    parallel to a1), b2 falls back to the coordinate axis least aligned with b1. A second
    Gram-Schmidt pass keeps b2 orthogonal to b1 to rounding even when a2 is nearly parallel.
    """
    dtype = a.dtype
    tiny = np.finfo(dtype).tiny
    tol = 64 * np.finfo(dtype).eps
    a1, a2 = a[..., 0:3], a[..., 3:6]
    scale = np.maximum(np.abs(a).max(axis=-1, keepdims=True), tiny)
    a1, a2 = a1 / scale, a2 / scale          # scale-free: 1e-30 and 1e30 inputs behave alike
    n1 = np.linalg.norm(a1, axis=-1, keepdims=True)
    b1 = np.where(n1 > tol, a1 / np.maximum(n1, tiny), np.array([1.0, 0.0, 0.0], dtype=dtype))
    eye = np.eye(3, dtype=dtype)
    fallback = eye[np.argmin(np.abs(b1), axis=-1)]
    a2p = a2 - (b1 * a2).sum(-1, keepdims=True) * b1
    n2 = np.linalg.norm(a2p, axis=-1, keepdims=True)
    a2p = np.where(n2 > tol, a2p, fallback - (b1 * fallback).sum(-1, keepdims=True) * b1)
    b2 = a2p - (b1 * a2p).sum(-1, keepdims=True) * b1
    b2 = b2 / np.maximum(np.linalg.norm(b2, axis=-1, keepdims=True), tiny)
    b3 = np.cross(b1, b2)
    return np.stack([b1, b2, b3], axis=-1)
