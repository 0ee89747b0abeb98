"""Speed/quality knobs of ``IrisRuntime.render`` and the named presets (``quality=``).

Exact work-skipping (output unchanged up to float rounding, <= 1e-6) is always on: the encoder's
output is cached in a ``Scene``; per chunk of rays the runtime drops the samples that project
validly into no reference view, the views into which no sample of the chunk projects and the
rays without any valid sample (``IrisRuntime(cull=True)``, the default; the renderer masks all of
them out of every attention, pool and weight, so dropping them is exact).

Lossy knobs, opt-in (``RenderSettings`` fields, also accepted as ``render`` keywords):

- ``top_k``: keep, per sample point, only the ``top_k`` valid reference views whose direction
  from the point is closest to the target ray's (largest cue dot t.s), masking the others.
  ``top_k_by="point"`` is that rule literally; with a model exported with ``renderer_views``
  (``io_spec.RENDERER_VIEWS``, the default "fast" graphs) the renderer is fed only the kept
  (view, point) pairs and runs its field on ``top_k`` view slots per point (same values as
  masking; older exports mask the other views). ``top_k_by="ray"`` keeps, per ray, the ``top_k`` views most
  often chosen by its points (ties: larger summed t.s) and groups rays with the same views into
  one renderer call, so every call sees at most ``top_k`` views whatever the scene's count.
- ``samples``: samples per ray (bin centres of ``samples`` equal bins in [near, far]; the model
  was trained with the manifest's count, 64).
- ``scale``: render at ``round(H * scale) x round(W * scale)`` pixels and resize to H x W with
  OpenCV (``upsample``: "linear" or "cubic"; depth always linear).
- ``refine``: adaptive refinement (``iris_runtime.adaptive``). A coarse pass renders the view at
  ``coarse`` x its resolution and is upsampled (``upsample``); the pixels where it cannot be
  trusted (its colour, or its depth as a fraction of far - near, varies by at least ``refine``
  within the 3 x 3 coarse neighbourhood they are interpolated from; at most ``refine_budget`` of
  the pixels, the least trusted first) are rendered again exactly: each equals that pixel of the
  render without ``refine`` (float rounding, <= 1e-6). ``refine=0`` renders every pixel again.
- ``depth_window``: depth-guided samples (``iris_runtime.adaptive``). The coarse pass also finds
  each ray's soft-depth mode (its largest renderer weight); a ray of the render keeps only the
  samples within ``depth_window`` bins of the modes of the coarse rays it lies between, unless
  one of those carried less than ``depth_mass`` of its weight inside its window: then it keeps
  every sample (exact). With ``refine`` as well, one coarse pass serves both and the refined
  pixels are depth-guided.
- ``precision``: "int8" runs the dynamically quantised renderer (``iris-export --quantize int8``).
  The one knob with a runtime-wide default: ``IrisRuntime(precision=...)``; ``RenderSettings``
  (and ``render(precision=...)``, which overrides that field) chooses per call. Both are checked
  against ``PRECISIONS``, and ``IrisRuntime`` maps a precision to its graph in one place.

The presets' settings are ``QUALITY_PRESETS``; their measured error and speed are in
docs/PERFORMANCE.md (numbers from benchmarks/error_vs_time.py, results in benchmarks/results/).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .validation import check_integer

__all__ = ["RenderSettings", "QUALITY_PRESETS", "TWO_SCALE_PRESETS", "TOP_K_BY", "UPSAMPLERS", "PRECISIONS",
           "resolve_settings", "top_k_mask", "ray_view_sets", "group_rays"]

TOP_K_BY = ("point", "ray")
UPSAMPLERS = ("linear", "cubic")
#: Renderer graph (manifest ``graphs`` key) per precision: "int8" is the dynamically quantised
#: variant iris-export writes with --quantize int8 (its error vs torch is in the manifest's
#: validation report). Dynamic quantisation scales activations per call, so int8 results depend
#: slightly on how rays are chunked.
PRECISIONS = {"float32": "renderer", "int8": "renderer_int8"}


@dataclass(frozen=True)
class RenderSettings:
    """How to trade error for time in one render (``None``: the model's / runtime's default).

    samples:   samples per ray (None: the manifest's, 64 for the shipped model)
    top_k:     views kept per point (None: all valid views)
    top_k_by:  "point" (choose per sample point) or "ray" (per ray; lets calls shrink to top_k views)
    scale:     render resolution relative to the output (1.0: full; 0.5: half, then upsampled)
    upsample:  "linear" or "cubic" (cv2.resize interpolation for scale < 1, and of the coarse
               pass of ``refine``)
    precision: "float32" or "int8" (None: the runtime's ``precision``)
    coarse:    resolution of the coarse pass of ``refine`` / ``depth_window``, relative to the
               render's (0.25: a quarter of the rows and of the columns)
    refine:    re-render exactly the pixels whose coarse neighbourhood varies by at least this
               (colour in [0, 1], depth in units of far - near; 0: every pixel); None: off
    refine_budget: at most this fraction of the pixels re-rendered (the least trusted first)
    depth_window:  keep the samples within this many bins of the coarse soft-depth mode (0: the
               mode's bin alone); None: every sample
    depth_mass:    ... unless the coarse rays carried less than this fraction of their weight in
               their windows: every sample then (the exact fallback of spread-out rays)
    field_scale:   two scales (explicit-colour models, ``iris_runtime.detail``), for outputs
               larger than the model's resolution: march the field at this fraction of the
               output's rows and columns and take the colour of every output pixel from the
               photos through the coarse rays' geometry (``scale`` then does not apply). An
               output no larger than the model's resolution is marched as without it (its
               colours are the model-resolution images: the photos have nothing finer to give
               it). In a preset it applies to explicit-colour models only; asked for by name
               on another model it is an ``InputError``. None: off
    colour_samples: with ``field_scale``, depth bins of each coarse ray the colour is read at
               (its heaviest, rescaled to its total weight)
    depth_search:  with ``field_scale``, how many depth bins each of those samples may move,
               along the output pixel's own ray, to where the views' colours agree best
               (``iris_runtime.detail.search_depth``); 0: off
    """
    samples: int | None = None
    top_k: int | None = None
    top_k_by: str = "ray"
    scale: float = 1.0
    upsample: str = "linear"
    precision: str | None = None
    coarse: float = 0.25
    refine: float | None = None
    refine_budget: float = 1.0
    depth_window: int | None = None
    depth_mass: float = 0.9
    field_scale: float | None = None
    colour_samples: int = 8
    depth_search: int = 0

    def __post_init__(self):
        for name in ("samples", "top_k"):
            check_integer(getattr(self, name), name, allow_none=True)
        if self.top_k_by not in TOP_K_BY:
            raise InputError(f"top_k_by: expected one of {list(TOP_K_BY)}, got {self.top_k_by!r}")
        if self.upsample not in UPSAMPLERS:
            raise InputError(f"upsample: expected one of {list(UPSAMPLERS)}, got {self.upsample!r}")
        for name in ("scale", "coarse", "refine_budget"):
            _check_fraction(name, getattr(self, name), "in (0, 1]", lambda x: 0.0 < x <= 1.0)
        _check_fraction("depth_mass", self.depth_mass, "in [0, 1]", lambda x: 0.0 <= x <= 1.0)
        if self.refine is not None:
            _check_fraction("refine", self.refine, ">= 0 or None", lambda x: x >= 0.0)
        check_integer(self.depth_window, "depth_window", minimum=0, allow_none=True)
        if self.field_scale is not None:
            _check_fraction("field_scale", self.field_scale, "in (0, 1] or None",
                            lambda x: 0.0 < x <= 1.0)
            if self.refine is not None or self.depth_window is not None:
                raise InputError("field_scale: two scales replace refine and depth_window's "
                                 "coarse-to-fine march; set refine and depth_window to None")
        check_integer(self.colour_samples, "colour_samples", minimum=1)
        check_integer(self.depth_search, "depth_search", minimum=0)
        if self.depth_search and self.field_scale is None:
            raise InputError("depth_search: moves the colour samples of two scales; set "
                             "field_scale too, or depth_search to 0")
        if self.precision is not None and (not isinstance(self.precision, str)
                                           or self.precision not in PRECISIONS):
            raise InputError(f"precision: expected one of {list(PRECISIONS)} or None, got "
                             f"{self.precision!r}")


    def two_scales(self, size: tuple[int, int], model_size: tuple[int, int]) -> bool:
        """Whether a render of ``size`` pixels takes two scales: ``field_scale`` is set and the
        output is larger than ``model_size`` on a side. Two scales compose the colour at the
        output's size (``scale`` then does not apply: the field's grid is ``field_scale``'s)."""
        return self.field_scale is not None and (size[0] > model_size[0]
                                                 or size[1] > model_size[1])

    def march_size(self, height: int, width: int) -> tuple[int, int]:
        """The pixels a render of ``height`` x ``width`` marches before its resize: ``scale`` x
        each side, rounded, at least 1 (never more than the output: ``scale`` is in (0, 1])."""
        if self.scale == 1.0:
            return height, width
        return max(1, int(round(height * self.scale))), max(1, int(round(width * self.scale)))


def _check_fraction(name: str, x, expected: str, ok) -> None:
    """``InputError`` naming ``name`` unless ``x`` is a finite real number with ``ok(x)``."""
    if isinstance(x, bool) or not isinstance(x, (int, float, np.integer, np.floating)) \
            or not np.isfinite(x) or not ok(x):
        raise InputError(f"{name}: expected a number {expected}, got {x!r}")


#: Named presets, chosen from the measured error/time table (docs/PERFORMANCE.md, "Choosing speed
#: against quality"; benchmarks/results/error_vs_time.md):
#:
#: - "auto":     the default of explicit-colour models: the full render up to the model's
#:               resolution; above it two scales (``field_scale``): the field marched at an
#:               eighth of the output's rows and columns, each pixel's colour from the photos
#:               through the 8 heaviest depth bins of the coarse rays around it (error and
#:               time against the full render at 128, 256 and 512: benchmarks/two_scale.py,
#:               docs/PERFORMANCE.md "Two scales"), each of those samples moved up to 4 bins
#:               to where the photos agree (``depth_search``; "Depth from the photos").
#: - "exact":    the full render (at every size: the field marched at every output pixel).
#: - "balanced": 64 -> 32 samples and at most 8 views per ray: about half the time of the full
#:               render at an error far below the model's own (ground-truth PSNR unchanged), and a
#:               time per frame that grows much slower than the full render's with the views.
#: - "fast":     16 samples, 2 views per ray, half resolution + bicubic upsampling: over an order
#:               of magnitude faster, at a visible but small error against the full render;
#:               above the model's resolution two scales instead: the field at a quarter of
#:               the output, the colour at the output's size through 4 depth windows.
#: - "adaptive": a quarter-resolution coarse pass, bicubic upsampling, and the 12 % least trusted
#:               pixels (colour or depth range >= 0.1 over their coarse neighbourhood) rendered
#:               again exactly: a coarse pass costs 1/16 of the full render and the budget
#:               bounds the rest, so about 1/5 of the full render's renderer work, aimed at
#:               >= 4x the speed for <= 0.1 dB of ground-truth PSNR. The budget, not the
#:               threshold, decides on textured views; a plain view refines less. No
#:               ``depth_window``: the shipped model's weights are spread along its rays (the
#:               fallback would keep every sample), see docs/PERFORMANCE.md.
QUALITY_PRESETS: dict[str, RenderSettings] = {
    "auto": RenderSettings(field_scale=0.125, colour_samples=8, depth_search=4),
    "exact": RenderSettings(),
    "balanced": RenderSettings(samples=32, top_k=8, top_k_by="ray"),
    "fast": RenderSettings(samples=16, top_k=2, top_k_by="ray", scale=0.5, upsample="cubic",
                           field_scale=0.125, colour_samples=4),
    "adaptive": RenderSettings(upsample="cubic", coarse=0.25, refine=0.1, refine_budget=0.12),
}


#: The presets that take two scales (``field_scale``) on explicit-colour models; on other
#: models they render without it ("auto" is then "exact").
TWO_SCALE_PRESETS = tuple(k for k, v in QUALITY_PRESETS.items() if v.field_scale is not None)


def resolve_settings(quality: str | RenderSettings | None = None, default: str = "exact",
                     **overrides) -> RenderSettings:
    """The settings of preset ``quality`` (None: preset ``default``) with the non-None
    ``overrides``; ``refine`` or ``depth_window`` among them replace the preset's two scales
    (``field_scale``) unless that is given too."""
    if quality is None:
        base = QUALITY_PRESETS[default]
    elif isinstance(quality, RenderSettings):
        base = quality
    elif isinstance(quality, str) and quality in QUALITY_PRESETS:
        base = QUALITY_PRESETS[quality]
    else:
        raise InputError(f"quality: expected one of {list(QUALITY_PRESETS)} or a RenderSettings, "
                         f"got {quality!r}")
    changes = {k: v for k, v in overrides.items() if v is not None}
    unknown = set(changes) - {f.name for f in dataclasses.fields(RenderSettings)}
    if unknown:
        raise InputError(f"unknown render settings {sorted(unknown)}")
    if (("refine" in changes or "depth_window" in changes) and "field_scale" not in changes
            and base.field_scale is not None):
        # The coarse-to-fine march asked for replaces the preset's two scales.
        changes["field_scale"] = None
        changes.setdefault("depth_search", 0)
    return dataclasses.replace(base, **changes) if changes else base


# ----------------------------------------------------------------------------------------------
# View selection (numpy; view axis first, as the runtime's projection produces it). The score is
# the geometric cue's last entry t.s (``geometry.geometric_cue``), which the ray march computes for
# the renderer anyway (``iris_runtime.raymarch.trace_block``).
# ----------------------------------------------------------------------------------------------


def top_k_mask(valid: np.ndarray, score: np.ndarray, k: int) -> np.ndarray:
    """Per point, the ``k`` valid views of largest ``score``.

    ``valid`` bool [V, ...], ``score`` float [V, ...] -> bool [V, ...] (a subset of ``valid``;
    points with fewer than k valid views keep them all). Ties go to the lower view index.
    """
    V = valid.shape[0]
    if k >= V:
        return valid.copy()
    s = np.where(valid, score, -np.inf)
    # Stable descending order: sort -s (ties keep view order); only the first k matter.
    idx = np.argsort(-s, axis=0, kind="stable")[:k]
    chosen = np.zeros(valid.shape, dtype=bool)
    np.put_along_axis(chosen, idx, True, axis=0)
    return chosen & valid


def ray_view_sets(valid: np.ndarray, score: np.ndarray, k: int) -> np.ndarray:
    """Per ray, the ``k`` views most often among its points' ``top_k_mask`` choices.

    ``valid``, ``score`` [V, R, S] -> bool [V, R]. Ties between views chosen equally often go to
    the larger summed score of those choices (score in [-1, 1], the cue's t.s), then to the lower
    index. Views chosen by no point of the ray are never kept.
    """
    V, R, S = valid.shape
    if k >= V:
        return valid.any(axis=2)
    point = top_k_mask(valid, score, k)
    count = point.sum(axis=2).astype(np.float64)                             # [V, R]
    tie = np.where(point, score.astype(np.float64) + 1.0, 0.0).sum(axis=2) / (2.0 * S + 1.0)
    return top_k_mask(count > 0, count + tie, k)


def group_rays(sets: np.ndarray, max_views: int, max_rays: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Split rays into renderer calls by their view sets.

    ``sets`` bool [V, R] (the views each ray keeps) -> ``[(rays, views), ...]``: index arrays of
    the rays of one call and the union of their views. Rays with the same set go together; whole
    sets are merged greedily while the union stays within ``max_views`` views, and calls hold at
    most ``max_rays`` rays. Every ray appears in exactly one call.
    """
    V, R = sets.shape
    if R == 0:
        return []
    keys, inverse = np.unique(sets.T, axis=0, return_inverse=True)           # [G, V], [R]
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(keys) + 1))
    # Largest sets first so that their subsets merge into them.
    sizes = keys.sum(axis=1)
    calls: list[tuple[np.ndarray, np.ndarray]] = []
    cur_rays: list[np.ndarray] = []
    cur_union = np.zeros(V, dtype=bool)
    cur_n = 0

    def flush():
        nonlocal cur_rays, cur_union, cur_n
        if cur_rays:
            calls.append((np.sort(np.concatenate(cur_rays)), np.flatnonzero(cur_union)))
        cur_rays, cur_union, cur_n = [], np.zeros(V, dtype=bool), 0

    for g in sorted(range(len(keys)), key=lambda g: (-int(sizes[g]), keys[g].tobytes())):
        rays = order[bounds[g]:bounds[g + 1]]
        union = cur_union | keys[g]
        if cur_rays and int(union.sum()) > max_views:
            flush()
            union = keys[g].copy()
        cur_union = union
        while len(rays):
            room = max_rays - cur_n
            if room <= 0:
                flush()
                cur_union = keys[g].copy()
                room = max_rays
            cur_rays.append(rays[:room])
            cur_n += len(rays[:room])
            rays = rays[room:]
    flush()
    return calls
