"""The results files of the error-against-time benchmark: JSON, markdown table, plot.

The markdown layout is quoted by docs/PERFORMANCE.md (the committed
benchmarks/results/error_vs_time.md): change its rows and columns only together with them.
"""
from __future__ import annotations

import json
from pathlib import Path

from iris_runtime.fileio import atomic_write_text

from . import rows as R
from .machine import CONTAINER_OPS, node_shares

#: The files a run writes into ``--out``.
JSON_NAME, MARKDOWN_NAME, PLOT_NAME = "error_vs_time.json", "error_vs_time.md", "error_vs_time.png"


def write(results: dict, out: Path) -> str:
    """Write the JSON, the markdown and (with the knobs part) the plot into ``out``; -> the
    markdown. Per-run seconds in the JSON are rounded to 0.1 ms (noise is far larger)."""
    out.mkdir(parents=True, exist_ok=True)
    for r in results.get("knobs", {}).get("rows", []):
        r["s_per_frame_runs"] = [[round(x, 4) for x in runs] for runs in r["s_per_frame_runs"]]
    text = markdown(results)
    atomic_write_text(out / JSON_NAME, json.dumps(results, indent=1, default=float))
    atomic_write_text(out / MARKDOWN_NAME, text)
    if "knobs" in results:
        plot(results, out / PLOT_NAME)
    return text


def plot(results: dict, path: Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = results["knobs"]["rows"]
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.2))
    groups = sorted({r["group"] for r in rows})
    markers = dict(zip(groups, "osD^v<>ph*"))
    colors = {g: f"C{i}" for i, g in enumerate(groups)}
    for ax, key, label in ((axes[0], "psnr_vs_full", "PSNR against the full render (dB, capped 100)"),
                           (axes[1], "psnr_gt", "PSNR against ground truth (dB)")):
        for r in rows:
            ax.scatter(r["s_per_frame"], r[key], marker=markers[r["group"]], s=50,
                       color=colors[r["group"]], label=r["group"])
            ax.annotate(r["name"], (r["s_per_frame"], r[key]), fontsize=7,
                        xytext=(4, 2), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_xlabel(f"seconds per {results['args']['size']}^2 target frame (log)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    uniq = dict(zip(labels, handles))
    axes[0].legend(uniq.values(), uniq.keys(), fontsize=7, loc="lower left")
    m = results["machine"]
    fig.suptitle(f"IRIS runtime: error against time ({m['cpu']}, {m['usable_cpus']} cores, "
                 f"{m['threads']} threads, onnxruntime {m['onnxruntime']})", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def coarse_to_fine(rows: list[dict], exact_s: float) -> list[str]:
    """The work of the coarse-to-fine rows (``RenderSettings.refine`` / ``depth_window``; speed-up
    against ``exact_s`` seconds per frame): no lines when the run had none (runs before them)."""
    rows = [r for r in rows if "refined_fraction" in r]
    if not rows:
        return []
    L = ["Coarse-to-fine rows (`iris_runtime.adaptive`): a coarse pass at 1/4 of the rows and "
         "columns, then the pixels marched again at full resolution (refined, exactly) and, "
         "of those, the rays marched on a depth window around the coarse weight mode (the "
         "others keep every sample: the exact fallback).", "",
         "| knob | pixels refined | rays windowed | samples kept (refined rays) | speed-up vs "
         "exact | PSNR vs full | PSNR gt |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        L.append(f"| {r['name']} | {100 * r['refined_fraction']:.1f}% | "
                 f"{100 * r['windowed_fraction']:.1f}% | {100 * r['kept_sample_fraction']:.1f}% | "
                 f"{exact_s / r['s_per_frame']:.2f}x | {r['psnr_vs_full']:.2f} | "
                 f"{r['psnr_gt']:.2f} |")
    return L + [""]


def sizing(s: dict, runs: int) -> list[str]:
    """The server-sizing section: seconds per frame per (preset, views, size), frames/s."""
    sizes = sorted({r["size"] for r in s["rows"]})
    views = sorted({r["views"] for r in s["rows"]})
    at = {(r["preset"], r["views"], r["size"]): r for r in s["rows"]}
    L = ["## Server sizing: seconds per frame and frames per second", "",
         f"One held-out scene (seed {s['seed']}, {s['frames']} frames); per number of reference "
         "views V, V frames spread over the orbit are encoded with a target between two of them, "
         "rendered at its predicted pose at each size (square). Seconds per frame: median of up "
         f"to {runs} renders after a warm-up (fewer for long frames); the runtime as the scaling "
         f"part runs it (workers={s['workers']}, threads={s['threads']}). PSNR: against the "
         "exact render of the same views and size. Encoding is per scene, not per frame.", "",
         "| preset | V | encode s | " + " | ".join(f"{z}^2 s/frame" for z in sizes) + " | "
         + " | ".join(f"{z}^2 PSNR vs exact" for z in sizes) + " |",
         "|---|---|---|" + "---|" * (2 * len(sizes))]
    for preset in s["presets"]:
        for v in views:
            rs = [at.get((preset, v, z)) for z in sizes]
            enc = next((r["encode_s"] for r in rs if r), float("nan"))
            L.append(f"| {preset} | {v} | {enc:.2f} | "
                     + " | ".join("-" if r is None else f"{r['s_per_frame']:.3f}" for r in rs)
                     + " | " + " | ".join("-" if r is None else f"{r['psnr_vs_exact']:.2f}"
                                          for r in rs) + " |")
    if s.get("fps"):
        f0 = s["fps"][0]
        L += ["", f"Frames per second: one scene of {f0['views']} reference views encoded once "
              f"({f0['encode_s']:.2f} s), then {f0['poses']} poses of an orbit around its cameras "
              f"(`iris_runtime.orbit`) rendered one after another at {f0['size']}^2.", "",
              "| preset | frames/s | seconds for the orbit |", "|---|---|---|"]
        for f in s["fps"]:
            L.append(f"| {f['preset']} | {f['fps']:.2f} | {f['seconds']:.2f} |")
    return L + [""]


def markdown(results: dict) -> str:
    m = results["machine"]
    L = ["# Error against run time (benchmarks/error_vs_time.py)", "",
         f"- date (UTC): {m['date_utc']}; model: `{results['model']['checkpoint']}` "
         f"(sha256 {results['model']['sha256'][:12]}..., training step "
         f"{results['model'].get('step')}{'; ' + results['model']['note'] if results['model'].get('note') else ''})",
         f"- machine: {m['cpu']}; {m['logical_cpus']} logical CPUs, {m['usable_cpus']} usable; "
         f"threads {m['threads']} (ORT intra-op and torch); onnxruntime {m['onnxruntime']}, "
         f"numpy {m['numpy']}, torch {m['torch']}, python {m['python']}; load average at start "
         f"{', '.join(f'{x:.2f}' for x in m['load_avg_start'])}, at the end "
         f"{', '.join(f'{x:.2f}' for x in m.get('load_avg_end', ()))} (2 cores: a 1-minute load "
         "well above 2 means another job shared the machine; per-row loads are in the JSON)",
         f"- timings: median of {results['args']['runs']} timed runs after a warm-up, all in one "
         f"process run (tcmalloc anchor and memory in subprocesses); {results['args']['scenes']} "
         f"held-out scenes x 3 targets, {results['args']['size']}x{results['args']['size']} "
         "frames (the model's resolution is 64x64).", ""]
    if "knobs" in results:
        k = results["knobs"]
        L += ["## Knobs", "",
              f"Held-out seeds {k['scenes']}, references {k['refs']}, targets {k['targets']} "
              f"({k['frames']} frames). Errors against the full ORT render (exact path); "
              "ground-truth PSNR/SSIM of the rendered target. s/frame: seconds per target frame "
              "(mean over frames of each frame's median). ORT/numpy: renderer graph / numpy "
              "geometry seconds per frame; GFLOP: analytic renderer FLOPs per frame.", "",
              "| knob | group | s/frame | speed-up vs exact | max abs vs full | PSNR vs full | "
              "PSNR gt | SSIM gt | ORT s | numpy s | GFLOP |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
        exact = next(r for r in k["rows"] if r["name"] == R.EXACT)["s_per_frame"]
        for r in k["rows"]:
            L.append(f"| {r['name']} | {r['group']} | {r['s_per_frame']:.3f} | "
                     f"{exact / r['s_per_frame']:.2f}x | {r['max_abs_vs_full']:.1e} | "
                     f"{r['psnr_vs_full']:.2f} | {r['psnr_gt']:.2f} | {r['ssim_gt']:.4f} | "
                     f"{r.get('renderer_s_per_frame', float('nan')):.3f} | "
                     f"{r.get('numpy_s_per_frame', float('nan')):.3f} | "
                     f"{r.get('renderer_gflop_per_frame', float('nan')):.2f} |")
        L += ["", "Notes: " + "; ".join(f"{r['name']}: {r['note']}" for r in k["rows"]
                                        if r.get("note")), ""]
        L += coarse_to_fine(k["rows"], exact)
    if "scaling" in results:
        s = results["scaling"]
        L += ["## Scaling (paper Table 11 shape)", "",
              f"One held-out scene (seed {s['seed']}, {s['frames']} frames); per (V, T): encode "
              f"all V + T frames, render the T targets ({results['args']['scaling_size']}^2) "
              "from the V references; seconds "
              "for the whole forward pass (median of runs). Paper: IRIS column of Table 11, "
              "forward pass only, on a GPU, with a much larger model (256x256) — quoted for "
              "context, not comparable.", "",
              "| (V, T) | torch eager s | ORT exact s | ORT balanced s | exact s/frame | "
              "balanced s/frame | balanced PSNR vs exact | PSNR gt exact / balanced | "
              "torch max abs vs exact | paper GPU s |", "|---|---|---|---|---|---|---|---|---|---|"]
        for r in s["rows"]:
            paper = f"{r['paper_gpu_s']:.2f}" if r["paper_gpu_s"] else "-"
            L.append(f"| ({r['views']}, {r['targets']}) | {r.get('torch_s', float('nan')):.2f} | "
                     f"{r['exact_s']:.2f} | {r['balanced_s']:.2f} | {r['exact_s_per_frame']:.3f} | "
                     f"{r['balanced_s_per_frame']:.3f} | {r['balanced_psnr_vs_exact']:.1f} | "
                     f"{r['exact_psnr_gt']:.2f} / {r['balanced_psnr_gt']:.2f} | "
                     f"{r.get('torch_max_abs_vs_exact', float('nan')):.1e} | {paper} |")
        L.append("")
    if "sizing" in results:
        L += sizing(results["sizing"], results["args"]["runs"])
    if "peak" in results:
        p = results["peak"]
        L += ["## Renderer throughput against the matmul peak", "",
              f"numpy float32 matmul {p['matmul']['n']}^3: {p['matmul']['gflops']:.1f} GFLOP/s "
              f"(median of {len(p['matmul']['seconds'])})"
              + (f"; the fastest of {len(p['matmul']['measurements'])} measurements, before and "
                 f"after the knobs part: "
                 + ", ".join(f"{g:.1f}" for g in p['matmul']['measurements'])
                 if len(p['matmul'].get('measurements', [])) > 1 else "") + ".", "",
              "Graph: FLOPs over the renderer graph's own time (the ORT calls); frame: over the "
              "whole frame's wall time (numpy geometry and Python included).", "",
              "| path | renderer GFLOP/frame | graph s/frame | basis | graph GFLOP/s | graph % of "
              "peak | frame s | frame GFLOP/s | frame % of peak |",
              "|---|---|---|---|---|---|---|---|---|"]
        for r in p["rows"]:
            wall = ((f"{r['wall_seconds']:.3f} | {r['wall_gflops']:.1f} | "
                     f"{100 * r['wall_fraction']:.0f}%") if "wall_fraction" in r else "- | - | -")
            L.append(f"| {r['name']} | {r['gflop']:.2f} | {r['seconds']:.3f} | {r['basis']} | "
                     f"{r['gflops']:.1f} | {100 * r['fraction']:.0f}% | {wall} |")
        if p.get("profile"):
            L += ["", f"ORT per-op profile of the exact path ({p['profile']['note']}; each node "
                  f"counted once: {', '.join(CONTAINER_OPS)} left out, their subgraphs' nodes are "
                  "under their own op types):", "",
                  "| op type | share of node time |", "|---|---|"]
            for op, share in node_shares(p["profile"]["shares"])[:12]:
                L.append(f"| {op} | {100 * share:.1f}% |")
        L.append("")
    if "memory" in results:
        L += ["## Memory: one render from 16 reference views (fresh process, no torch)", "",
              "Peak RSS of the whole process (runtime, sessions, encode of 16 views, render). "
              "Renderer memory is bounded per call (chunk_rays), not per image: the exact path "
              "is measured at a smaller size to keep the run short, its calls are the same.", "",
              "| quality | size | peak RSS MB | after encode MB | seconds | renderer calls |",
              "|---|---|---|---|---|---|"]
        for r in results["memory"]:
            L.append(f"| {r['quality']} | {r['size'][0]}x{r['size'][1]} | {r['peak_rss_mb']:.0f} | "
                     f"{r['rss_after_encode_mb']:.0f} | {r['seconds']:.1f} | {r['work']['calls']} |")
        L.append("")
    if "targets" in results:
        L += ["## Targets", ""]
        for t in results["targets"]:
            L.append(f"- **{'met' if t['met'] else 'MISSED'}** — {t['target']}: {t['measured']}"
                     + (f". Limits: {t['why']}." if t.get("why") and not t["met"] else ""))
        L.append("")
    return "\n".join(L)
