"""Photometric variation of the capture kinds: what a real camera does to the rendered light.

Applied per scene and view, deterministically from the seed, to uint8 RGB images of any size
(the parameters are drawn once per scene and view, independent of the size; sizes are given as
fractions of the image): grey scenes (real sets such as ViSP's are grey), exposure / gain and
white-balance changes between views, vignetting, a slight blur (defocus), sensor noise
(signal-dependent + read noise) and JPEG compression. ``render_scene(..., clean=True)`` and
``SyntheticScenes(..., clean=True)`` skip it, so depth and evaluation stay exact.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from iris_runtime.errors import InputError

#: Share of capture scenes rendered fully grey.
GREY_SHARE = 0.25


@dataclass(frozen=True)
class ViewPhotometry:
    """One view's parameters (see ``draw``)."""

    gain: float                     # exposure x gain, multiplies linear intensity
    white: tuple[float, float, float]   # per-channel white-balance factors
    gamma: float                    # tone curve exponent applied after the gain
    vignette: float                 # intensity loss at the image corner (0 = none)
    blur: float                     # Gaussian sigma as a fraction of the image height
    noise: float                    # read-noise sigma in levels of 255 at 256 px height
    shot: float                     # signal-dependent noise factor
    jpeg: int                       # JPEG quality, 0 = not compressed


def draw(seed: int, n_views: int) -> tuple[bool, list[ViewPhotometry]]:
    """``(grey, per-view parameters)`` of scene ``seed``: a scene-level camera (grey or colour,
    noise level, blur, vignetting, compression) with per-view exposure and white-balance drift."""
    rng = np.random.default_rng([int(seed), 0x9407])
    grey = bool(rng.random() < GREY_SHARE)
    base_gain = float(np.exp(rng.normal(0, 0.2)))
    gain_drift = rng.uniform(0.0, 0.15)
    white = rng.normal(0, 0.04, size=3) if not grey else np.zeros(3)
    gamma = float(rng.uniform(0.85, 1.15))
    vignette = float(rng.uniform(0.0, 0.4)) if rng.random() < 0.7 else 0.0
    blur = float(rng.uniform(0.0, 0.004))
    noise = float(rng.uniform(0.0, 6.0))
    shot = float(rng.uniform(0.0, 0.6))
    jpeg = int(rng.integers(40, 96)) if rng.random() < 0.6 else 0
    views = []
    for _ in range(n_views):
        g = base_gain * float(np.exp(rng.normal(0, gain_drift)))
        w = np.exp(white + rng.normal(0, 0.01, size=3))
        views.append(ViewPhotometry(g, tuple(float(x) for x in w), gamma, vignette,
                                    blur * float(rng.uniform(0.7, 1.3)), noise, shot, jpeg))
    return grey, views


def _apply_view(img: np.ndarray, p: ViewPhotometry, grey: bool, rng: np.random.Generator) -> np.ndarray:
    h, w = img.shape[:2]
    x = img.astype(np.float32) / 255.0
    sigma = p.blur * h
    if sigma > 0.3:
        x = cv2.GaussianBlur(x, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT)
    x = x * (p.gain * np.asarray(p.white, np.float32))
    if p.vignette > 0:
        jj, ii = np.meshgrid((np.arange(w) + 0.5) / w - 0.5, (np.arange(h) + 0.5) / h - 0.5)
        r2 = (jj ** 2 + ii ** 2) / 0.5
        x = x * (1.0 - p.vignette * r2 ** 1.5).astype(np.float32)[..., None]
    x = np.clip(x, 0.0, 1.0) ** p.gamma
    if grey:
        x = np.repeat((x @ np.array([0.299, 0.587, 0.114], np.float32))[..., None], 3, axis=2)
    # Noise scaled so that a 4x area downsample of a 256 image has the 64 image's level.
    scale = (256.0 / h)
    read = p.noise / 255.0 / scale
    std = np.sqrt(read ** 2 + (p.shot / 255.0) ** 2 * x * 255.0 / scale ** 2)
    n = rng.standard_normal(x.shape[:2] if grey else x.shape).astype(np.float32)
    x = x + std * (n[..., None] if grey else n)
    out = np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8)
    if p.jpeg:
        ok, buf = cv2.imencode(".jpg", out[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, p.jpeg])
        out = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]
        if grey:
            out = np.repeat(out[..., :1], 3, axis=2)
    return np.ascontiguousarray(out)


def apply(images: np.ndarray, seed: int) -> np.ndarray:
    """``images`` uint8 ``[V, H, W, 3]`` of scene ``seed`` -> the same with the scene's camera
    effects (a new array; deterministic per seed, view and size)."""
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] != 3 or images.dtype != np.uint8:
        raise InputError(f"images: expected uint8 [V, H, W, 3], got {images.dtype} {images.shape}")
    grey, views = draw(seed, images.shape[0])
    out = np.empty_like(images)
    for v, p in enumerate(views):
        rng = np.random.default_rng([int(seed), 0x9408, v, images.shape[1], images.shape[2]])
        out[v] = _apply_view(images[v], p, grey, rng)
    return out
