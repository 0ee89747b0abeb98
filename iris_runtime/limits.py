"""Request limits and the memory model of ``IrisRuntime`` (numbers: docs/PERFORMANCE.md,
"Runtime limits and chunking").

Every limit is checked before anything is allocated; exceeding one raises ``InputError`` naming
the argument. ``IrisRuntime`` exposes them as ``max_views``, ``default_chunk_rays`` and
``check_output_size``.
"""
from __future__ import annotations

from .errors import InputError
from .validation import check_integer

__all__ = ["RENDER_BUDGET", "MAX_CHUNK_RAYS", "MAX_OUTPUT_PIXELS", "MAX_ENCODER_TOKENS",
           "MAX_CHUNK_SAMPLES", "MAX_LOCATE_CALLS", "MAX_POSE_DISTANCE", "render_memory_bound",
           "default_chunk_rays", "max_views", "output_size", "check_output_size",
           "check_chunk_rays", "chunk_rays_for"]

#: Rays x samples x views per renderer call by default: ``default_chunk_rays`` gives
#: ``min(MAX_CHUNK_RAYS, RENDER_BUDGET // (S * V))`` rays (256 for 1-2 views, 128 for 4, 64 for 8
#: at S = 64). Bigger chunks are not faster per ray, while ONNX Runtime's peak memory grows
#: linearly with the chunk (``render_memory_bound``); this budget keeps a call near 0.1-0.35 GB.
RENDER_BUDGET = 32 * 1024
MAX_CHUNK_RAYS = 256
#: Output pixels per render (4096 x 4096). The output is assembled whole: float32 rgb + depth, the
#: uint8 image and the clipping temporaries take ~31 bytes per pixel, 0.5 GB at this limit; a
#: coarse-to-fine render (``refine``, ``depth_window``) up to ``adaptive.BYTES_PER_PIXEL`` - 16
#: more while it chooses what to march, ~1.6 GB at this limit. Larger views: render tiles with
#: ``intrinsics``.
MAX_OUTPUT_PIXELS = 4096 * 4096
#: Encoder tokens per ``encode`` call: views x (patches per view + 1 camera token). Cross-view
#: attention memory grows with the square of the tokens; 4160 tokens (64 views of the tiny model,
#: 16 of the paper preset) stay under ~0.7 GB. ``max_views`` is this limit in views of a model.
MAX_ENCODER_TOKENS = 4160
#: Rays x samples x views per renderer call when ``chunk_rays`` is given explicitly (8 x the default
#: budget): ONNX Runtime's peak grows linearly with it (``render_memory_bound``), ~1 GB here.
MAX_CHUNK_SAMPLES = 8 * RENDER_BUDGET
#: Farthest target camera centre from the references' mean centre, in units of their spread
#: (at least 1 model unit): the scene lies within the depth range [near, far] <= 1 of the
#: references, so a camera this far sees none of it (and its rays' float32 arithmetic would
#: overflow long before a translation of 1e300). ``render`` refuses a pose beyond it.
MAX_POSE_DISTANCE = 1000.0
#: Encoder calls one ``locate`` may make: photos per call are ``max_views`` minus the scene's
#: references (at least 1), so one call locates up to this many batches (bounded work per request).
MAX_LOCATE_CALLS = 64


def render_memory_bound(num_views: int, chunk_rays: int, samples: int = 64,
                        concurrent: int = 1) -> int:
    """Documented bound (bytes) of the memory that ``concurrent`` renders in flight add to a warm
    runtime: per renderer call (1.2 + 0.1 V) MB per ray at S = 64 samples (measured, see
    docs/PERFORMANCE.md), scaled by S / 64 and rounded up to 1.5 + 0.15 V, plus 64 MB of numpy
    geometry and allocator slack per call. The 8-thread load test of tests/test_stability.py
    checks it."""
    per_ray = (1.5 + 0.15 * num_views) * 2 ** 20 * samples / 64
    return int(concurrent * (chunk_rays * per_ray + 64 * 2 ** 20))


def default_chunk_rays(num_views: int, samples: int) -> int:
    """Rays per renderer call: R * S * V near ``RENDER_BUDGET``, at most ``MAX_CHUNK_RAYS``."""
    return min(MAX_CHUNK_RAYS, max(1, RENDER_BUDGET // (samples * max(1, num_views))))


def max_views(image_size: tuple[int, int], patch_size) -> int:
    """Most images one ``encode`` accepts: ``MAX_ENCODER_TOKENS // (patches per view + 1)``
    (``patch_size`` as the manifest's config holds it; not a positive int: 8)."""
    H, W = image_size
    p = patch_size if isinstance(patch_size, int) and not isinstance(patch_size, bool) \
        and patch_size > 0 else 8
    return MAX_ENCODER_TOKENS // ((H // p) * (W // p) + 1)


def output_size(image_size: tuple[int, int], height=None, width=None) -> tuple[int, int]:
    """The (height, width) a render of a model of resolution ``image_size`` produces (None: the
    model's, or the model's aspect for one given side), or ``InputError`` for non-positive /
    non-integer sizes; no limit on the pixels (``check_output_size`` adds it). A caller with a
    lower limit of its own (iris-serve's ``--max-output-pixels``) states that one."""
    Hm, Wm = image_size
    height = check_integer(height, "height", allow_none=True)
    width = check_integer(width, "width", allow_none=True)
    if height is None and width is None:
        return Hm, Wm
    if height is None:
        return max(1, round(width * Hm / Wm)), int(width)
    if width is None:
        return int(height), max(1, round(height * Wm / Hm))
    return int(height), int(width)


def check_output_size(image_size: tuple[int, int], height=None, width=None) -> tuple[int, int]:
    """``output_size``, or ``InputError`` also for more than ``MAX_OUTPUT_PIXELS`` pixels.
    Allocates nothing."""
    h, w = output_size(image_size, height, width)
    if h * w > MAX_OUTPUT_PIXELS:
        raise InputError(f"height, width: {h}x{w} = {h * w} output pixels exceeds "
                         f"MAX_OUTPUT_PIXELS = {MAX_OUTPUT_PIXELS} (the output is held in "
                         f"memory whole, ~31 bytes per pixel); render tiles with intrinsics")
    return h, w


def chunk_rays_for(chunk_rays, *, pixels: int, samples: int, num_views: int,
                   views_per_call: int) -> int:
    """Rays per renderer call of a render of ``pixels`` pixels, ``samples`` samples per ray and
    ``num_views`` reference views: ``chunk_rays`` checked (``check_chunk_rays``), or when None
    ``default_chunk_rays`` of the views a call feeds per point (``views_per_call``: fewer than
    ``num_views`` when the calls shrink to a top-k of them)."""
    if chunk_rays is None:
        return default_chunk_rays(views_per_call, samples)
    return check_chunk_rays(chunk_rays, pixels, samples, num_views)


def check_chunk_rays(chunk_rays, pixels: int, samples: int, num_views: int,
                     name: str = "chunk_rays") -> int:
    """An explicit ``chunk_rays`` as an int, or ``InputError`` naming ``name`` when it is not a
    positive integer or when ``min(chunk_rays, pixels) * samples * num_views`` exceeds
    ``MAX_CHUNK_SAMPLES``."""
    chunk_rays = check_integer(chunk_rays, name)
    if min(chunk_rays, pixels) * samples * num_views > MAX_CHUNK_SAMPLES:
        raise InputError(f"{name}: {chunk_rays} rays x {samples} samples x "
                         f"{num_views} views per renderer call exceeds "
                         f"MAX_CHUNK_SAMPLES = {MAX_CHUNK_SAMPLES} (memory grows with it); "
                         f"use at most {max(1, MAX_CHUNK_SAMPLES // (samples * num_views))}")
    return chunk_rays
