"""Coarse-to-fine rendering: leave out the pixels and the samples a view does not need
(``RenderSettings.refine`` and ``depth_window``; numpy + OpenCV, no torch).

    rendered = render(settings, march_at, height, width, near=..., far=..., samples=...)

One **coarse pass** marches the view at ``settings.coarse`` x its resolution with every sample
(``march_at(h, w, ...)`` is the render's ray march at another size or on a subset of pixels,
``iris_runtime.raymarch``). Then:

- **Adaptive refinement** (``refine``): the coarse colour and depth are upsampled to the render's
  resolution (``cv2.resize``, ``settings.upsample``; depth linear) and the pixels where that
  cannot be trusted are marched again at full resolution, exactly as without ``refine``. The
  trust of a coarse pixel is the range of the coarse colour (largest over the channels) and of
  the coarse depth (as a fraction of far - near) over its 3 x 3 neighbourhood: upsampling is
  only wrong where the image or the geometry changes within the footprint it interpolates over
  (colour edges, texture, occlusion boundaries). A pixel of the render takes the score of the
  coarse pixel containing its centre, whose 3 x 3 neighbourhood holds the 2 x 2 pixels bilinear
  interpolation reads (bicubic reads 4 x 4, one pixel further on two sides). Pixels scoring
  ``>= refine`` are refined, at most ``refine_budget`` of all (rounded; highest scores first):
  a threshold says what error is tolerated, a budget bounds the time.
- **Depth-guided samples** (``depth_window``): the coarse pass also keeps each ray's weight mode
  (the depth of its largest renderer weight) and the weight within ``depth_window`` bins of it.
  A ray of the render keeps the samples from ``depth_window`` bins before the nearest to
  ``depth_window`` bins after the farthest mode of the 2 x 2 coarse rays it lies between (so a
  depth edge widens the window instead of guessing a side); if one of those coarse rays carried
  less than ``depth_mass`` of its weight inside its window (weights spread along the ray, or no
  valid sample at all), it keeps every sample: exact. The kept samples are marched as the
  renderer's masked samples are (``raymarch``: dropped as if they projected nowhere), so only
  their cost is paid.

Both together share the coarse pass: the refined pixels are marched with their depth windows.
Depth follows the colour: a refined pixel's is its march's, ``sum(weights * z)`` over the
samples it kept; the others' is the coarse depth, upsampled linearly (as ``scale`` does).
What is rendered exactly is the same as without these knobs (float rounding, <= 1e-6: different
pixels share each renderer call): every refined pixel, every pixel of a ``refine=0`` render, and
every ray of a depth-guided render that keeps all its samples.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from . import geometry as G
from .raymarch import MarchResult, MarchStats

__all__ = ["Rendered", "render", "untrusted", "coarse_size", "depth_windows",
           "BYTES_PER_PIXEL"]

f32 = np.float32

#: Most bytes per pixel of the render that ``render`` holds at once, the fine pass's rgb and
#: depth included (the exact path holds 16 there): the upsampled coarse pass, the trust score,
#: the refined pixels' indices and, with ``depth_window``, every pixel's window and their order
#: (tests/test_adaptive.py measures it with tracemalloc; ``limits.MAX_OUTPUT_PIXELS``).
BYTES_PER_PIXEL = 80


@dataclass(frozen=True, eq=False)
class Rendered:
    """A coarse-to-fine render of H x W pixels.

    rgb:    float32 [H*W, 3]   row-major (refined pixels marched, the others upsampled)
    depth:  float32 [H*W]
    stats:  ``MarchStats`` of both passes (summed)
    work:   ``coarse_rays`` (rays of the coarse pass), ``refined_rays`` (pixels marched at the
            render's resolution), ``windowed_rays`` (of those, the rays marched on a depth
            window rather than every sample), ``kept_samples`` (samples those rays kept, summed;
            every sample counts for the others), ``pixels`` (H*W)
    coarse_s: wall seconds of the coarse pass, the trust scores and the windows
    """
    rgb: np.ndarray
    depth: np.ndarray
    stats: MarchStats
    work: dict
    coarse_s: float


def coarse_size(height: int, width: int, coarse: float) -> tuple[int, int]:
    """(h, w) of the coarse pass: ``round(height * coarse) x round(width * coarse)``, >= 1."""
    return max(1, int(round(height * coarse))), max(1, int(round(width * coarse)))


def _centre_index(n_out: int, n_in: int) -> np.ndarray:
    """For each of ``n_out`` pixels along an axis, the one of ``n_in`` containing its centre."""
    return np.minimum((np.arange(n_out) + 0.5) * n_in // n_out, n_in - 1).astype(np.int64)


def _bilinear_floor(n_out: int, n_in: int) -> np.ndarray:
    """For each of ``n_out`` pixels along an axis, ``floor`` of its position among ``n_in``
    (pixel centres aligned), in [-1, n_in - 1]: linear interpolation (``cv2.resize``
    INTER_LINEAR) reads the input pixels ``floor`` and ``floor + 1``, clamped to the edges."""
    x = (np.arange(n_out) + 0.5) * (n_in / n_out) - 0.5
    return np.clip(np.floor(x), -1, n_in - 1).astype(np.int64)


def _over_pairs(a: np.ndarray, reduce) -> np.ndarray:
    """``a`` [h, w] -> [h + 1, w + 1]: entry (i, j) is ``reduce`` over the 2 x 2 pixels that
    linear interpolation reads for a floor position (i - 1, j - 1) (``_bilinear_floor``),
    edge-clamped."""
    p = np.pad(a, 1, mode="edge")
    return reduce(reduce(p[:-1, :-1], p[1:, :-1]), reduce(p[:-1, 1:], p[1:, 1:]))


def untrusted(rgb: np.ndarray, depth: np.ndarray, height: int, width: int,
              depth_range: float) -> np.ndarray:
    """How far the coarse pass can be from the truth at each pixel of the render.

    ``rgb`` float32 [h, w, 3], ``depth`` float32 [h, w] (the coarse pass) -> float32
    [height, width]: the range (max - min) of the coarse colour, largest over the channels, and
    of the coarse depth / ``depth_range``, whichever is larger, over the 3 x 3 coarse
    neighbourhood of the coarse pixel containing the pixel's centre.
    """
    import cv2
    k = np.ones((3, 3), np.uint8)           # border: OpenCV's morphology ignores outside pixels
    colour = (cv2.dilate(rgb, k) - cv2.erode(rgb, k)).max(axis=2)
    geometry = (cv2.dilate(depth, k) - cv2.erode(depth, k)) / f32(depth_range)
    score = np.maximum(colour, geometry)
    h, w = depth.shape
    return score[_centre_index(height, h)[:, None], _centre_index(width, w)[None, :]]


def depth_windows(mode: np.ndarray, mass: np.ndarray, height: int, width: int,
                  z_bins: np.ndarray, window: int, min_mass: float) -> np.ndarray:
    """Per pixel of the render, the samples ``[lo, hi)`` of ``z_bins`` it keeps.

    ``mode``, ``mass`` float32 [h, w]: the coarse rays' weight modes and their weight within
    ``window`` bins of it (``raymarch.MarchResult``). ``z_bins`` float32 [S] (equal bins).
    -> int64 [height * width, 2], row-major: from ``window`` bins before the smallest to
    ``window`` bins after the largest mode of the 2 x 2 coarse rays the pixel lies between;
    ``[0, S)`` where one of them has ``mass < min_mass`` or no weight at all (no valid sample).
    Computed per 2 x 2 block of coarse rays, then looked up per pixel (16 bytes per pixel).
    """
    S = len(z_bins)
    dz = (float(z_bins[-1]) - float(z_bins[0])) / max(1, S - 1)
    least = _over_pairs(mass, np.minimum)
    trusted = (least >= min_mass) & (least > 0)          # 0: a coarse ray that saw nothing
    # Modes are bin centres: half a bin of slack makes the rounding of the bounds irrelevant.
    lo = np.searchsorted(z_bins, _over_pairs(mode, np.minimum) - (window + 0.5) * dz, "left")
    hi = np.searchsorted(z_bins, _over_pairs(mode, np.maximum) + (window + 0.5) * dz, "right")
    blocks = np.stack([np.where(trusted, lo, 0),
                       np.where(trusted, np.clip(hi, lo + 1, S), S)], axis=-1)   # [h+1, w+1, 2]
    h, w = mode.shape
    rows, cols = _bilinear_floor(height, h) + 1, _bilinear_floor(width, w) + 1
    return blocks[rows[:, None], cols[None, :]].reshape(height * width, 2).astype(np.int64,
                                                                               copy=False)


def render(settings, march_at: Callable[..., MarchResult], height: int, width: int, *,
           near: float, far: float, samples: int,
           progress: Callable[[int, int], None] | None = None) -> Rendered:
    """The coarse-to-fine render of ``height`` x ``width`` pixels (``settings``: a
    ``RenderSettings`` with ``refine`` or ``depth_window`` set).

    ``march_at(h, w, pixel_index=None, sample_window=None, mode_radius=None, progress=None)``:
    the render's ray march at ``h`` x ``w`` pixels (its intrinsics scaled to that size) on the
    given subset (``raymarch.MarchPlan``). ``progress(rays_done, rays_total)``: over both passes;
    the total is the coarse rays plus every pixel until the coarse pass has chosen the pixels,
    then the rays actually marched.
    """
    import cv2
    t0 = time.perf_counter()
    n = height * width
    h, w = coarse_size(height, width, settings.coarse)
    guided = settings.depth_window is not None
    dz = (far - near) / samples
    # Modes are bin centres, so anything within window + 1/2 bins is within window bins.
    radius = (settings.depth_window + 0.5) * dz if guided else None
    coarse = march_at(h, w, mode_radius=radius,
                      progress=None if progress is None else lambda d, _: progress(d, h * w + n))
    stats = MarchStats()
    stats.add(coarse.stats)
    rgb_c, depth_c = coarse.rgb.reshape(h, w, 3), coarse.depth.reshape(h, w)
    if settings.refine is None:                # depth-guided only: march every pixel (None)
        pixels, rgb, depth = None, np.empty((n, 3), f32), np.empty(n, f32)
    else:
        interp = cv2.INTER_CUBIC if settings.upsample == "cubic" else cv2.INTER_LINEAR
        rgb = np.clip(cv2.resize(rgb_c, (width, height), interpolation=interp), 0.0, 1.0)
        depth = cv2.resize(depth_c, (width, height), interpolation=cv2.INTER_LINEAR)
        rgb, depth = rgb.reshape(n, 3), depth.reshape(n)
        score = untrusted(rgb_c, depth_c, height, width, far - near).reshape(n)
        pixels = np.flatnonzero(score >= settings.refine)
        budget = int(settings.refine_budget * n + 0.5)    # rounded: 0.12 of 4096 is 492
        if len(pixels) > budget:                       # the least trusted first, ties by index
            pixels = np.sort(np.argsort(-score, kind="stable")[:budget])
    windows = None
    if guided:
        z_bins = G.sample_depths(near, far, samples, 1, dtype=f32)[0]      # the march's depths
        windows = depth_windows(coarse.mode.reshape(h, w), coarse.mass.reshape(h, w), height,
                                width, z_bins, settings.depth_window, settings.depth_mass)
        if pixels is not None:
            windows = windows[pixels]
        # Rays of equal window length side by side: a block traces its longest window.
        order = np.argsort(windows[:, 1] - windows[:, 0], kind="stable")
        pixels, windows = (order if pixels is None else pixels[order]), windows[order]
    coarse_s = time.perf_counter() - t0
    if len(pixels):
        fine = march_at(height, width, pixel_index=pixels, sample_window=windows,
                        progress=None if progress is None else
                        lambda d, t: progress(h * w + d, h * w + t))
        stats.add(fine.stats)
        rgb[pixels] = fine.rgb
        depth[pixels] = fine.depth
    elif progress is not None:
        progress(h * w, h * w)
    kept = samples * len(pixels) if windows is None else int((windows[:, 1] - windows[:, 0]).sum())
    work = {"coarse_rays": h * w, "refined_rays": int(len(pixels)),
            "windowed_rays": 0 if windows is None else int(
                ((windows[:, 1] - windows[:, 0]) < samples).sum()),
            "kept_samples": kept, "pixels": n}
    return Rendered(rgb, depth, stats, work, coarse_s)
