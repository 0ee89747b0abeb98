"""The benchmark's targets (speed against torch, exactness, view scaling, matmul peak, memory),
checked against one run's results; each missed target says what limits it, from the run itself.
"""
from __future__ import annotations

from . import rows as R
from .machine import node_shares

#: Exact path against torch eager as installed / with tcmalloc: at least this many times faster.
SPEEDUP_VS_TORCH = 3.0
SPEEDUP_VS_TORCH_TCMALLOC = 1.5
#: Max abs difference of the exact path from torch (rgb), and of the exact knobs from each other.
MAX_ABS_VS_TORCH = 1e-4
#: Issue 12's bar: within this of torch (``measure.torch_parity``).
MAX_ABS_VS_TORCH_STRICT = 1e-5
MAX_ABS_EXACT_KNOBS = 1e-6
#: Balanced preset, 4 -> 16 reference views: time per target frame grows at most this much, and
#: its ground-truth PSNR stays within this many dB of the full render's.
BALANCED_GROWTH_4_TO_16 = 1.5
BALANCED_MAX_PSNR_DROP_DB = 0.1
#: Adaptive preset (issue 12, part 2): at least this many times faster than the exact path
#: (``rows.EXACT``: the same runtime configuration as every knob row) at most this many dB below
#: the full render's ground-truth PSNR.
ADAPTIVE_SPEEDUP = 4.0
ADAPTIVE_MAX_PSNR_DROP_DB = 0.1
#: Renderer graph FLOP rate against the float32 matmul peak (this benchmark's own target, and
#: issue 12's bar), on the graph's own time (``measure.peak_rows``).
PEAK_FRACTION = 0.5
PEAK_FRACTION_ISSUE = 0.4
#: Peak RSS of one render from 16 reference views.
PEAK_RSS_MB = 1536

_ELEMENTWISE_OPS = ("Where", "Transpose", "Mul", "Add", "Split", "Sub", "Div", "ReduceSum",
                    "Expand", "Concat", "Reshape")
_MATMUL_OPS = ("MatMul", "FusedMatMul", "Gemm", "MatMulInteger")


def _e(x: float) -> str:
    """1e-4, not 1e-04."""
    return f"{x:.0e}".replace("e-0", "e-")


def graph_limits(results: dict) -> str:
    """What limits the exact path, from the run's own profile and FLOP counts."""
    prof = dict(node_shares(results.get("peak", {}).get("profile", {}).get("shares", [])))
    if not prof:
        return ""
    mm = sum(prof.get(k, 0.0) for k in _MATMUL_OPS)
    ew = sum(prof.get(k, 0.0) for k in _ELEMENTWISE_OPS)
    rows = {r["name"]: r for r in results.get("knobs", {}).get("rows", [])}
    txt = (f"ORT per-op profile of the exact path: matmul-class ops (MatMul, FusedMatMul, Gemm) "
           f"{100 * mm:.0f}% of node time, element-wise and layout ops (Where, Transpose, Mul, "
           f"Add, Split, ...) {100 * ew:.0f}% (Where {100 * prof.get('Where', 0):.0f}%: masking; "
           f"Transpose {100 * prof.get('Transpose', 0):.0f}%: view-major inputs to point-major "
           "field and per-head layouts); the matmuls are thin (model width 64)")
    ex, tc = rows.get(R.EXACT), rows.get(R.TORCH_TCMALLOC)
    if ex and tc and ex.get("renderer_gflop_per_frame"):
        g = ex["renderer_gflop_per_frame"]
        txt += (f". Same {g:.0f} GFLOP per frame: torch + tcmalloc {g / tc['s_per_frame']:.0f} "
                f"GFLOP/s (whole frame), the ORT graph {g / ex['renderer_s_per_frame']:.0f} "
                "GFLOP/s (graph time)")
    nc = rows.get(R.EXACT_NO_CULLING)
    if ex and nc and ex.get("work_per_frame") and nc.get("work_per_frame"):
        kept = ex["work_per_frame"]["points"] / max(1, nc["work_per_frame"]["points"])
        txt += (f". Exact skipping cannot help here: culling keeps {100 * kept:.0f}% of the "
                "samples (every sample of these scenes projects into some reference view)")
    return txt


def fastest_exact(results: dict) -> dict | None:
    """The faster of the exact configurations (``rows.EXACT_CONFIGS``) in the knobs table."""
    rows = {r["name"]: r for r in results.get("knobs", {}).get("rows", [])}
    exacts = [rows[n] for n in R.EXACT_CONFIGS if n in rows]
    return min(exacts, key=lambda r: r["s_per_frame"]) if exacts else None


def evaluate_targets(results: dict) -> list[dict]:
    """-> [{"target", "met", "measured", "why"?}] for every target the run's parts can check."""
    out = []
    limits = graph_limits(results)
    rows = {r["name"]: r for r in results.get("knobs", {}).get("rows", [])}
    ex = fastest_exact(results)
    torch = rows.get(R.TORCH_EAGER)
    if ex and torch:
        ratio = torch["s_per_frame"] / ex["s_per_frame"]
        out.append({"target": f"exact path >= {SPEEDUP_VS_TORCH:g}x faster than torch eager as "
                              "installed",
                    "met": ratio >= SPEEDUP_VS_TORCH, "measured": f"{ratio:.2f}x ({ex['name']}: "
                    f"{ex['s_per_frame']:.3f} s vs {torch['s_per_frame']:.3f} s "
                    "per frame)", "why": "torch's default allocator makes its time vary from run "
                    "to run (page faults on the 4096-ray chunks); on the ORT side: " + limits})
    tc = rows.get(R.TORCH_TCMALLOC)
    if ex and tc:
        ratio = tc["s_per_frame"] / ex["s_per_frame"]
        out.append({"target": f"exact path >= {SPEEDUP_VS_TORCH_TCMALLOC:g}x faster than torch "
                              "eager with tcmalloc",
                    "met": ratio >= SPEEDUP_VS_TORCH_TCMALLOC, "measured": f"{ratio:.2f}x "
                    f"({tc['s_per_frame']:.3f} s per frame)", "why": limits})
    if ex and torch:
        err = torch["max_abs_vs_full"]
        out.append({"target": f"identical output to torch (<= {_e(MAX_ABS_VS_TORCH)})",
                    "met": err <= MAX_ABS_VS_TORCH,
                    "measured": f"max abs {err:.1e} (rgb, all frames)"})
    parity = results.get("knobs", {}).get("parity")
    if ex and torch:
        # Issue 12's bar, literally: the exact path within 1e-5 of torch eager (float32), end to
        # end. The per-stage figures say where a miss comes from: the renderer on torch's own
        # inputs, and both float32 paths against float64 (float32 rounding of the cameras moves
        # the render on either side).
        err = torch["max_abs_vs_full"]
        measured = f"torch eager vs exact {err:.1e}"
        if parity:
            measured += (f"; renderer on torch's own scene and poses {parity['renderer_vs_torch32']:.1e}; "
                         f"against torch float64: exact {parity['exact_vs_torch64']:.1e}, torch "
                         f"float32 {parity['torch32_vs_torch64']:.1e}; encoder maps / poses vs "
                         f"torch {parity['encoder_maps_vs_torch32']:.1e} / "
                         f"{parity['encoder_poses_vs_torch32']:.1e}")
        out.append({"target": f"output within {_e(MAX_ABS_VS_TORCH_STRICT)} of torch eager",
                    "met": err <= MAX_ABS_VS_TORCH_STRICT, "measured": measured,
                    "why": "float32 rounding of the encoder's cameras (~1e-7) moves samples near a "
                           "reference image's edge: a jump with a hard validity mask, a slope with "
                           "the fade of I/O spec 4 (benchmarks/pose_sensitivity.py); the renderer "
                           "given torch's own inputs is the implementation difference"})
    nc = rows.get(R.EXACT_NO_CULLING)
    if nc:
        err = nc["max_abs_vs_full"]
        measured = f"culling vs none: max abs {err:.1e}"
        every = rows.get(R.REFINE_EVERY)          # refine=0: every pixel marched again, exactly
        if every:
            measured += f"; refine every pixel vs full: max abs {every['max_abs_vs_full']:.1e}"
            err = max(err, every["max_abs_vs_full"])
        out.append({"target": f"exact knobs unchanged within {_e(MAX_ABS_EXACT_KNOBS)}",
                    "met": err <= MAX_ABS_EXACT_KNOBS, "measured": measured})
    ad, exact = rows.get(R.PRESET_ADAPTIVE), rows.get(R.EXACT)
    if ad and exact:
        ratio = exact["s_per_frame"] / ad["s_per_frame"]
        drop = ad["psnr_gt"] - exact["psnr_gt"]
        out.append({"target": f"adaptive preset >= {ADAPTIVE_SPEEDUP:g}x faster than the exact "
                              f"path at <= {ADAPTIVE_MAX_PSNR_DROP_DB:g} dB ground-truth PSNR loss",
                    "met": ratio >= ADAPTIVE_SPEEDUP and drop >= -ADAPTIVE_MAX_PSNR_DROP_DB,
                    "measured": f"{ratio:.2f}x ({ad['s_per_frame']:.3f} vs "
                                f"{exact['s_per_frame']:.3f} s per frame), PSNR gt {drop:+.3f} dB "
                                f"(PSNR vs full {ad['psnr_vs_full']:.2f} dB, "
                                f"{100 * ad.get('refined_fraction', float('nan')):.0f}% of the "
                                "pixels refined)",
                    "why": "the coarse pass marches 1/16 of the pixels and a refined pixel costs "
                           "what it costs in the exact path, so the refined fraction decides, "
                           "plus the overhead of the coarse pass's few, small renderer calls"})
    sc = {(r["views"], r["targets"]): r for r in results.get("scaling", {}).get("rows", [])}
    v4 = next((r for (v, _), r in sc.items() if v == 4), None)
    v16 = next((r for (v, _), r in sc.items() if v == 16), None)
    if v4 and v16:
        g = v16["balanced_s_per_frame"] / v4["balanced_s_per_frame"]
        out.append({"target": "balanced: time per target frame 4 -> 16 views grows <= "
                              f"{BALANCED_GROWTH_4_TO_16:g}x",
                    "met": g <= BALANCED_GROWTH_4_TO_16, "measured": f"{g:.2f}x (exact path: "
                    f"{v16['exact_s_per_frame'] / v4['exact_s_per_frame']:.2f}x)"})
        in_range = [r for (v, _), r in sc.items() if 4 <= v <= 16]
        worst = min(r["balanced_psnr_gt"] - r["exact_psnr_gt"] for r in in_range)
        beyond = "; ".join(f"V={v}: {r['balanced_psnr_gt'] - r['exact_psnr_gt']:+.3f} dB"
                           for (v, _), r in sc.items() if v > 16)
        out.append({"target": f"balanced, 4 to 16 views: at most {BALANCED_MAX_PSNR_DROP_DB:g} "
                              "dB PSNR (gt) below the full render",
                    "met": worst >= -BALANCED_MAX_PSNR_DROP_DB,
                    "measured": f"worst difference {worst:+.3f} dB; PSNR vs full >= "
                    f"{min(r['balanced_psnr_vs_exact'] for r in in_range):.1f} dB"
                    + (f" (beyond the range, {beyond})" if beyond else "")})
    if "peak" in results:
        name = ex["name"] if ex else R.EXACT
        r = next((r for r in results["peak"]["rows"] if r["name"] == name), None)
        if r is not None:                   # None: the knobs part did not run
            peak = results["peak"]["matmul"]["gflops"]
            measured = (f"{100 * r['fraction']:.1f}% ({name}: {r['gflops']:.1f} of {peak:.1f} "
                        f"GFLOP/s, {r['basis']})")
            if "wall_fraction" in r:
                measured += (f"; over the whole frame's wall time {100 * r['wall_fraction']:.1f}% "
                             f"({r['wall_gflops']:.1f} GFLOP/s)")
            for frac in (PEAK_FRACTION_ISSUE, PEAK_FRACTION):
                out.append({"target": f"renderer graph >= {100 * frac:.0f}% of float32 matmul "
                                      "peak", "met": r["fraction"] >= frac, "measured": measured,
                            "why": limits})
    for r in results.get("memory", []):
        out.append({"target": f"peak RSS {r['size'][0]}x{r['size'][1]} from 16 views <= "
                              f"{PEAK_RSS_MB / 1024:g} GB ({r['quality']})",
                    "met": r["peak_rss_mb"] <= PEAK_RSS_MB,
                    "measured": f"{r['peak_rss_mb']:.0f} MB"})
    return out
