"""Row and group names of the error-against-time tables, and the grids the rows come from.

The names are the keys the report, the targets and the committed results
(benchmarks/results/error_vs_time.{json,md}) share, so they are spelled once, here.
"""
from __future__ import annotations

from typing import NamedTuple

# Groups (the plot's legend; the table's second column).
ANCHOR = "anchor"
EXACT_GROUP = "exact"
TOPK_POINT_GROUP = "top-k per point"
TOPK_RAY_GROUP = "top-k per ray"
SAMPLES_GROUP = "samples"
INT8_GROUP = "int8"
RESOLUTION_GROUP = "resolution"
REFINE_GROUP = "adaptive refinement"
DEPTH_GROUP = "depth-guided samples"
PRESET_GROUP = "preset"

# Anchors: torch eager, the reference the speed targets are measured against.
TORCH_EAGER = "torch eager"
TORCH_TCMALLOC = "torch eager + tcmalloc"

# The exact path: same output as the full render, different ways of getting it. EXACT is the full
# render every error is taken against (culling on; "no culling" is the same render without
# skipping).
EXACT = "exact (cull)"
EXACT_2_WORKERS = "exact, 2 workers"
EXACT_NO_CULLING = "exact, no culling"
EXACT_NO_SCENE_CACHE = "exact, no Scene cache"

# Knobs that trade error for time.
TOPK_POINT_2 = "top-k point k=2"
TOPK_POINT_4 = "top-k point k=4"
TOPK_RAY_2 = "top-k ray k=2"
TOPK_RAY_4 = "top-k ray k=4"
SAMPLES_48 = "samples 48"
SAMPLES_32 = "samples 32"
SAMPLES_16 = "samples 16"
INT8 = "int8"
SCALE_HALF_LINEAR = "scale 1/2 linear"
SCALE_HALF_CUBIC = "scale 1/2 cubic"
SCALE_QUARTER_LINEAR = "scale 1/4 linear"
SCALE_QUARTER_CUBIC = "scale 1/4 cubic"
# Coarse-to-fine (iris_runtime.adaptive): a quarter-resolution coarse pass, then the pixels
# refined exactly / the samples kept around the coarse weight mode.
REFINE_EVERY = "refine 1/4, every pixel"
REFINE_BUDGET_10 = "refine 1/4, budget 10%"
REFINE_BUDGET_20 = "refine 1/4, budget 20%"
REFINE_THRESHOLD_02 = "refine 1/4, threshold 0.2"
DEPTH_WINDOW_8 = "depth window 8"
DEPTH_WINDOW_16_MASS_05 = "depth window 16, mass 0.5"
PRESET_BALANCED = "preset balanced"
PRESET_FAST = "preset fast"
PRESET_ADAPTIVE = "preset adaptive"


class Knob(NamedTuple):
    """One row of the knob grid: ``IrisRuntime.render(scene, pose, **render_kw)``."""
    name: str
    group: str
    render_kw: dict


#: The knob grid, in table order, after the anchors and the exact rows.
KNOB_GRID = (
    Knob(TOPK_POINT_2, TOPK_POINT_GROUP, {"top_k": 2, "top_k_by": "point"}),
    Knob(TOPK_POINT_4, TOPK_POINT_GROUP, {"top_k": 4, "top_k_by": "point"}),
    Knob(TOPK_RAY_2, TOPK_RAY_GROUP, {"top_k": 2, "top_k_by": "ray"}),
    Knob(TOPK_RAY_4, TOPK_RAY_GROUP, {"top_k": 4, "top_k_by": "ray"}),
    Knob(SAMPLES_48, SAMPLES_GROUP, {"samples": 48}),
    Knob(SAMPLES_32, SAMPLES_GROUP, {"samples": 32}),
    Knob(SAMPLES_16, SAMPLES_GROUP, {"samples": 16}),
    Knob(INT8, INT8_GROUP, {"precision": "int8"}),
    Knob(SCALE_HALF_LINEAR, RESOLUTION_GROUP, {"scale": 0.5, "upsample": "linear"}),
    Knob(SCALE_HALF_CUBIC, RESOLUTION_GROUP, {"scale": 0.5, "upsample": "cubic"}),
    Knob(SCALE_QUARTER_LINEAR, RESOLUTION_GROUP, {"scale": 0.25, "upsample": "linear"}),
    Knob(SCALE_QUARTER_CUBIC, RESOLUTION_GROUP, {"scale": 0.25, "upsample": "cubic"}),
    Knob(REFINE_EVERY, REFINE_GROUP, {"coarse": 0.25, "refine": 0.0}),
    Knob(REFINE_BUDGET_10, REFINE_GROUP, {"coarse": 0.25, "refine": 0.0, "refine_budget": 0.1,
                                          "upsample": "cubic"}),
    Knob(REFINE_BUDGET_20, REFINE_GROUP, {"coarse": 0.25, "refine": 0.0, "refine_budget": 0.2,
                                          "upsample": "cubic"}),
    Knob(REFINE_THRESHOLD_02, REFINE_GROUP, {"coarse": 0.25, "refine": 0.2, "upsample": "cubic"}),
    Knob(DEPTH_WINDOW_8, DEPTH_GROUP, {"coarse": 0.25, "depth_window": 8}),
    Knob(DEPTH_WINDOW_16_MASS_05, DEPTH_GROUP, {"coarse": 0.25, "depth_window": 16,
                                                "depth_mass": 0.5}),
    Knob(PRESET_BALANCED, PRESET_GROUP, {"quality": "balanced"}),
    Knob(PRESET_FAST, PRESET_GROUP, {"quality": "fast"}),
    Knob(PRESET_ADAPTIVE, PRESET_GROUP, {"quality": "adaptive"}),
)

#: Rows whose renders are coarse-to-fine: the report lists the fraction of pixels they refined
#: and of samples they kept (``RenderResult.work``).
COARSE_TO_FINE_GROUPS = (REFINE_GROUP, DEPTH_GROUP)

#: The two exact configurations; the faster one runs the scaling and memory parts and is the one
#: the speed targets are checked on (same output; both measured in the knobs table).
EXACT_CONFIGS = (EXACT, EXACT_2_WORKERS)

#: Rows of the throughput-against-peak table (those with renderer graph FLOPs worth comparing).
PEAK_ROWS = (EXACT, EXACT_2_WORKERS, EXACT_NO_CULLING, TOPK_RAY_4, SAMPLES_32, INT8,
             PRESET_BALANCED)

#: Scaling part: the methods timed per (views, targets), as (label, render keywords). The labels
#: prefix the row's JSON keys (``exact_s``, ``balanced_s_per_frame``, ...).
SCALING_EXACT = "exact"
SCALING_BALANCED = "balanced"
SCALING_METHODS = ((SCALING_EXACT, {}), (SCALING_BALANCED, {"quality": "balanced"}))

#: Server sizing (issue 12, part 3): seconds per frame of every preset at these output sizes from
#: these numbers of reference views, and frames per second over an orbit of ``SIZING_FPS_POSES``
#: poses of one encoded scene of ``SIZING_FPS_VIEWS`` views at ``SIZING_FPS_SIZE``.
SIZING_SIZES = (64, 128, 256)
SIZING_VIEWS = (4, 8, 16)
SIZING_FPS_VIEWS = 8
SIZING_FPS_SIZE = 64
SIZING_FPS_POSES = 24
#: A (preset, views, size) is timed ``--runs`` times, but no more once its runs add up to this
#: many seconds (a 256^2 exact frame from 16 views is one long run of many renderer calls).
SIZING_SECONDS_PER_CONFIG = 10.0

#: Scaling grid, like the paper's Table 11: (reference views, targets).
SCALING = ((4, 1), (8, 2), (12, 4), (16, 8), (32, 8))
#: The IRIS column of the paper's Table 11 (GPU seconds, a much larger model): context only.
PAPER_TABLE11 = {(4, 1): 2.74, (8, 2): 7.92, (12, 4): 20.75, (16, 8): 49.24}
