"""Error against run time: every speed/quality knob of IrisRuntime.render, two anchors, one run.

    python benchmarks/error_vs_time.py                       # models/iris-tiny-rgb.pt, all parts
                                                             # (~12 min on 2 cores, with export)
    python benchmarks/error_vs_time.py --checkpoint runs/tiny/last.pt --scenes 1 --parts knobs

Parts (everything in one process; the tcmalloc torch anchor and the 512x512 memory measurement
in subprocesses):

- knobs:   held-out scenes (``iris_train.data.HELDOUT_SEEDS``, 8 frames, targets
           ``evaluate.TARGET_FRAMES``, the others references; all frames encoded, targets rendered
           from ``Scene.subset(refs)`` at their predicted poses). Every knob against the torch
           eager reference (``IrisModel.render``, as installed and with tcmalloc preloaded) and
           the full ORT runtime. Seconds per target frame (median of ``--runs`` timed renders after
           one warm-up render per configuration), max abs difference and PSNR against the full
           render (ORT, exact), PSNR/SSIM against the ground truth.
- scaling: like the paper's Table 11: (reference views, targets) = (4, 1) ... (32, 8), seconds for
           encode + render of all targets: torch eager, the exact ORT path, the balanced preset.
- peak:    float32 matmul peak of this machine (numpy, 4096^3) against the renderer graph's
           analytic FLOPs per second (FLOPs counted from the shapes of every renderer call).
- memory:  peak RSS of a 512x512 render from 16 reference views (a fresh subprocess).

Results: ``--out`` (default benchmarks/results/): error_vs_time.json, error_vs_time.md,
error_vs_time.png.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

TCMALLOC = "/usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4"
PAPER_TABLE11 = {(4, 1): 2.74, (8, 2): 7.92, (12, 4): 20.75, (16, 8): 49.24}
SCALING = ((4, 1), (8, 2), (12, 4), (16, 8), (32, 8))

#: The knob grid: (name, group, render keywords). "full" is the reference every error is taken
#: against (the exact path with culling on; "no culling" is the same render without skipping).
KNOBS = [
    ("exact (cull)", "exact", {}),
    ("top-k point k=2", "top-k per point", {"top_k": 2, "top_k_by": "point"}),
    ("top-k point k=4", "top-k per point", {"top_k": 4, "top_k_by": "point"}),
    ("top-k ray k=2", "top-k per ray", {"top_k": 2, "top_k_by": "ray"}),
    ("top-k ray k=4", "top-k per ray", {"top_k": 4, "top_k_by": "ray"}),
    ("samples 48", "samples", {"samples": 48}),
    ("samples 32", "samples", {"samples": 32}),
    ("samples 16", "samples", {"samples": 16}),
    ("int8", "int8", {"precision": "int8"}),
    ("scale 1/2 linear", "resolution", {"scale": 0.5, "upsample": "linear"}),
    ("scale 1/2 cubic", "resolution", {"scale": 0.5, "upsample": "cubic"}),
    ("scale 1/4 linear", "resolution", {"scale": 0.25, "upsample": "linear"}),
    ("preset balanced", "preset", {"quality": "balanced"}),
    ("preset fast", "preset", {"quality": "fast"}),
]


# ----------------------------------------------------------------------------------------------
# Facts, timing, FLOPs
# ----------------------------------------------------------------------------------------------

def machine_facts(threads: int) -> dict:
    import onnxruntime as ort
    cpu = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    facts = {"date_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()), "cpu": cpu,
             "logical_cpus": os.cpu_count(), "usable_cpus": len(os.sched_getaffinity(0)),
             "threads": threads, "onnxruntime": ort.__version__, "numpy": np.__version__,
             "python": platform.python_version(), "load_avg_start": os.getloadavg(),
             "tcmalloc": TCMALLOC if Path(TCMALLOC).exists() else None}
    try:
        import torch
        facts["torch"] = torch.__version__
    except ImportError:
        facts["torch"] = None
    return facts


def matmul_peak(n: int = 4096, runs: int = 3) -> dict:
    """float32 GFLOP/s of one large numpy matmul (median of ``runs`` after a warm-up)."""
    rng = np.random.default_rng(0)
    a = rng.standard_normal((n, n), dtype=np.float32)
    b = rng.standard_normal((n, n), dtype=np.float32)
    a @ b
    times = []
    for _ in range(runs):
        t = time.perf_counter()
        a @ b
        times.append(time.perf_counter() - t)
    med = statistics.median(times)
    return {"n": n, "seconds": times, "gflops": 2 * n ** 3 / med / 1e9}


def renderer_flops(cfg: dict, work: dict) -> float:
    """Multiply-add FLOPs (2 per MAC) of the renderer graph for the calls summarised in ``work``
    (``RenderResult.work``). Matmul-like work only (sampling matmul, linear layers, attention
    products); norms, activations and softmax are left out (a few % at these widths)."""
    W = cfg["field_width"]
    C = W * (1 + 2 * cfg["view_blocks"])
    hw = (cfg["image_height"] // cfg["patch_size"]) * (cfg["image_width"] // cfg["patch_size"])
    P = 3 * (1 + 2 * cfg["pos_freqs"]) + 3 * (1 + 2 * cfg["dir_freqs"])
    hidden = int(W * cfg["mlp_ratio"])
    Bv, Br = cfg["view_blocks"], cfg["ray_blocks"]
    mlp = 4 * W * hidden
    per_point_view = 2 * hw * C + Bv * (2 * 4 * 2 * W + 4 * W)      # dense sampling, cue->kv, logits+sum
    per_point = Bv * (4 * W * W + mlp) + Br * (2 * P * W + 8 * W * W + mlp)
    per_ray_pair = Br * 4 * W                                       # QK^T and AV
    per_ray = 2 * (W * W + 3 * W)
    return (per_point_view * work["point_views"] + per_point * work["points"]
            + per_ray_pair * work["ray_pairs"] + per_ray * work["rays"])


def timed(fn, runs: int):
    """-> (median seconds, all seconds, last result) of ``runs`` calls."""
    times, out = [], None
    for _ in range(runs):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), times, out


def _psnr(a, b) -> float:
    from iris_train.metrics import psnr
    return min(psnr(a, b), 100.0)


def _ssim(a, b) -> float:
    from iris_train.metrics import ssim
    return ssim(a, b)


def _sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


# ----------------------------------------------------------------------------------------------
# Scenes and anchors
# ----------------------------------------------------------------------------------------------

def heldout_scenes(n: int, n_views: int = 8):
    from iris_train.data import HELDOUT_SEEDS, SyntheticScenes
    ds = SyntheticScenes(list(HELDOUT_SEEDS)[:n], n_views=n_views)
    return [ds[i] for i in range(n)]


def gt_image(image: np.ndarray, size: int) -> np.ndarray:
    """Ground truth as float [0, 1] at ``size`` x ``size`` (area-resized when smaller)."""
    import cv2
    if image.shape[:2] != (size, size):
        image = cv2.resize(image, (size, size), interpolation=cv2.INTER_AREA)
    return image.astype(np.float64) / 255.0


def torch_render_frames(model, images_list, refs, targets, threads: int, runs: int,
                        size: int | None = None):
    """Torch eager anchor: per scene, encode all frames once, then time ``IrisModel.render`` of
    each target from the references -> (per-frame medians, per-frame runs, outputs)."""
    import torch
    torch.set_num_threads(threads)
    meds, alls, outs = [], [], []
    with torch.no_grad():
        for images in images_list:
            x = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float() / 255.0
            scene = model.encode(x)
            sub = scene.subset(refs)
            H = W = size or images.shape[1]
            if not outs:                                        # warm-up
                model.render(sub, scene.world_from_cam[targets[:1]], H, W)
            for t in targets:
                pose = scene.world_from_cam[[t]]
                med, times, out = timed(lambda: model.render(sub, pose, H, W), runs)
                meds.append(med)
                alls.append(times)
                outs.append(out[0][0].double().numpy())
    return meds, alls, outs


def _torch_child(args) -> None:
    """Subprocess body of the tcmalloc anchor: same scenes, timings + outputs to an npz."""
    from iris_train.evaluate import split_frames
    from iris_train.model import load_model
    model = load_model(args.checkpoint)
    scenes = heldout_scenes(args.scenes)
    refs, targets = split_frames(8)
    meds, alls, outs = torch_render_frames(model, [s.images for s in scenes], list(refs),
                                           list(targets), args.threads, args.runs, args.size)
    np.savez(args.torch_child, meds=np.array(meds), alls=np.array(alls), outs=np.stack(outs),
             preload=np.array(os.environ.get("LD_PRELOAD", "")))


def torch_tcmalloc_anchor(args) -> dict | None:
    if not Path(TCMALLOC).exists():
        return None
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "torch_tcmalloc.npz"
        env = dict(os.environ, LD_PRELOAD=TCMALLOC)
        cmd = [sys.executable, str(Path(__file__).resolve()), "--checkpoint", str(args.checkpoint),
               "--scenes", str(args.scenes), "--runs", str(args.runs), "--threads",
               str(args.threads), "--size", str(args.size), "--torch-child", str(out)]
        subprocess.run(cmd, env=env, check=True)
        d = np.load(out)
        return {"meds": d["meds"].tolist(), "alls": d["alls"].tolist(), "outs": d["outs"],
                "preload": str(d["preload"])}


# ----------------------------------------------------------------------------------------------
# Parts
# ----------------------------------------------------------------------------------------------

def part_knobs(args, rt, rt_nocull, rt_par, model, log) -> dict:
    from iris_train.evaluate import split_frames
    scenes = heldout_scenes(args.scenes)
    refs, targets = split_frames(8)
    refs, targets = list(refs), list(targets)
    # Encode every scene once (the Scene cache); targets at their predicted poses.
    encoded = [rt.encode(list(s.images)) for s in scenes]
    frames = []                            # (scene index, target frame, pose, gt float image)
    size = args.size
    for i, (s, sc) in enumerate(zip(scenes, encoded)):
        for t in targets:
            frames.append((i, t, sc.world_from_cam[t], gt_image(s.images[t], size)))
    ort_kw = {"height": size, "width": size}
    subs = [sc.subset(refs) for sc in encoded]

    def ort_config(runtime, kw):
        kw = {**ort_kw, **kw}
        runtime.render(subs[0], frames[0][2], depth=True, **kw)             # warm-up
        meds, alls, outs, works, tims = [], [], [], [], []
        for i, t, pose, _ in frames:
            med, times, res = timed(lambda: runtime.render(subs[i], pose, depth=True, **kw),
                                    args.runs)
            meds.append(med)
            alls.append(times)
            outs.append(res.image_float.astype(np.float64))
            works.append(res.work)
            tims.append(res.timings)
        return meds, alls, outs, works, tims

    rows = []
    log("knobs: full ORT render (exact, cull)")
    full = ort_config(rt, {})
    full_outs = full[2]

    def add(name, group, meds, alls, outs, works=None, tims=None, note=""):
        err = max(float(np.abs(o - f).max()) for o, f in zip(outs, full_outs))
        row = {"name": name, "group": group, "s_per_frame": float(np.mean(meds)),
               "s_per_frame_runs": alls, "max_abs_vs_full": err,
               "psnr_vs_full": float(np.mean([_psnr(o, f) for o, f in zip(outs, full_outs)])),
               "psnr_gt": float(np.mean([_psnr(np.clip(o, 0, 1), fr[3])
                                         for o, fr in zip(outs, frames)])),
               "ssim_gt": float(np.mean([_ssim(np.clip(o, 0, 1), fr[3])
                                         for o, fr in zip(outs, frames)])),
               "note": note, "load_avg_1min": os.getloadavg()[0]}
        if works:
            tot = {k: sum(w[k] for w in works) for k in works[0]}
            row["work_per_frame"] = {k: v / len(works) for k, v in tot.items()}
            ort_s = float(np.mean([t["renderer"] for t in tims]))
            row["renderer_s_per_frame"] = ort_s
            row["numpy_s_per_frame"] = float(np.mean([t["rays"] for t in tims]))
            row["renderer_gflop_per_frame"] = renderer_flops(rt.manifest.config,
                                                             row["work_per_frame"]) / 1e9
        rows.append(row)
        log(f"  {name:24s} {row['s_per_frame']:7.3f} s/frame  max|d| {err:.2e}  "
            f"PSNR(full) {row['psnr_vs_full']:6.2f}  PSNR(gt) {row['psnr_gt']:6.2f}")
        return row

    # Anchors.
    if model is not None:
        log("knobs: torch eager (as installed)")
        meds, alls, outs = torch_render_frames(model, [s.images for s in scenes], refs, targets,
                                               args.threads, args.runs, size)
        add("torch eager", "anchor", meds, alls, outs, note="IrisModel.render, default allocator")
        if not args.no_tcmalloc:
            log("knobs: torch eager + tcmalloc (subprocess)")
            tc = torch_tcmalloc_anchor(args)
            if tc is not None:
                add("torch eager + tcmalloc", "anchor", tc["meds"], tc["alls"], list(tc["outs"]),
                    note=f"LD_PRELOAD={tc['preload']}")
    add("exact (cull)", "exact", *full, note="default: IrisRuntime(cull=True)")
    log("knobs: exact, data-parallel (workers=2)")
    add("exact, 2 workers", "exact", *ort_config(rt_par, {}),
        note=f"IrisRuntime(threads={args.threads}, workers=2): two renderer calls in flight, "
             f"{max(1, args.threads // 2)} intra-op thread(s) each")
    log("knobs: no culling")
    add("exact, no culling", "exact", *ort_config(rt_nocull, {}),
        note="IrisRuntime(cull=False): every sample, view and ray through the graph")
    # Scene cache: encode the references on every render (one-shot API).
    log("knobs: one-shot render(images, pose) (no Scene cache)")
    meds, alls, outs = [], [], []
    rt.render(list(scenes[0].images[refs]), frames[0][2], **ort_kw)
    for i, t, pose, _ in frames:
        imgs = list(scenes[i].images[refs])
        med, times, res = timed(lambda: rt.render(imgs, pose, depth=True, **ort_kw), args.runs)
        meds.append(med)
        alls.append(times)
        outs.append(res.image_float.astype(np.float64))
    add("exact, no Scene cache", "exact", meds, alls, outs,
        note="encoder re-run on the references per render; its scene differs from the "
             "all-frames encoding, so the error is the encoder's view-set dependence, not rounding")
    for name, group, kw in KNOBS[1:]:
        if kw.get("precision") == "int8" and "renderer_int8" not in rt.manifest.graphs:
            continue
        log(f"knobs: {name}")
        add(name, group, *ort_config(rt, kw))
    return {"refs": refs, "targets": targets, "scenes": [int(s) for s in
            __import__("iris_train.data", fromlist=["HELDOUT_SEEDS"]).HELDOUT_SEEDS[:args.scenes]],
            "frames": len(frames), "rows": rows}


def part_scaling(args, rt, model, log) -> dict:
    """(V refs, T targets): encode V + T frames, render T targets from V refs; seconds total."""
    from iris_train.data import HELDOUT_SEEDS, SyntheticScenes
    n_frames = max(v + t for v, t in SCALING)
    scene_data = SyntheticScenes([HELDOUT_SEEDS[0]], n_views=n_frames)[0]
    rows = []
    for V, T in args.scaling:
        # References evenly spread over the orbit; targets between them.
        idx = np.round(np.linspace(0, n_frames - 1, V + T, endpoint=False)).astype(int)
        order = np.argsort(np.arange(V + T) % ((V + T) // T) == 1, kind="stable")
        refs_pos, tgt_pos = order[:V], order[V:]
        images = scene_data.images[idx]
        size = args.scaling_size
        gts = [gt_image(images[j], size) for j in tgt_pos]
        okw = {"height": size, "width": size}
        row = {"views": V, "targets": T, "paper_gpu_s": PAPER_TABLE11.get((V, T))}

        def ort_run(kw):
            sc = rt.encode(list(images))
            t_enc = time.perf_counter()
            sub = sc.subset(list(refs_pos))
            outs = [rt.render(sub, sc.world_from_cam[j], depth=True, **okw, **kw)
                    for j in tgt_pos]
            return sc, outs, t_enc

        results = {}
        for label, kw in (("exact", {}), ("balanced", {"quality": "balanced"})):
            if not rows:                                           # warm-up, once per method
                ort_run(kw)
            times, enc_times, frame_times = [], [], []
            for _ in range(args.runs):
                t0 = time.perf_counter()
                sc, outs, t_enc = ort_run(kw)
                t1 = time.perf_counter()
                times.append(t1 - t0)
                enc_times.append(t_enc - t0)
                frame_times.append((t1 - t_enc) / T)
            results[label] = [o.image_float.astype(np.float64) for o in outs]
            row[f"{label}_s"] = statistics.median(times)
            row[f"{label}_s_runs"] = times
            row[f"{label}_encode_s"] = statistics.median(enc_times)
            row[f"{label}_s_per_frame"] = statistics.median(frame_times)
            row[f"{label}_psnr_gt"] = float(np.mean([_psnr(np.clip(o, 0, 1), g)
                                                     for o, g in zip(results[label], gts)]))
        row["balanced_psnr_vs_exact"] = float(np.mean([_psnr(b, e) for b, e in
                                                       zip(results["balanced"], results["exact"])]))
        row["balanced_max_abs_vs_exact"] = float(max(np.abs(b - e).max() for b, e in
                                                     zip(results["balanced"], results["exact"])))
        if model is not None:
            import torch
            torch.set_num_threads(args.threads)
            x = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float() / 255.0
            H = W = size

            def torch_run():
                with torch.no_grad():
                    sc = model.encode(x)
                    t_enc = time.perf_counter()
                    rgb, _ = model.render(sc.subset(list(refs_pos)),
                                          sc.world_from_cam[list(tgt_pos)], H, W)
                return rgb, t_enc

            if not rows:
                torch_run()                                        # warm-up, once
            times, frame_times = [], []
            for _ in range(args.runs):
                t0 = time.perf_counter()
                rgb, t_enc = torch_run()
                t1 = time.perf_counter()
                times.append(t1 - t0)
                frame_times.append((t1 - t_enc) / T)
            row["torch_s"] = statistics.median(times)
            row["torch_s_runs"] = times
            row["torch_s_per_frame"] = statistics.median(frame_times)
            row["torch_max_abs_vs_exact"] = float(max(
                np.abs(rgb[k].double().numpy() - results["exact"][k]).max() for k in range(T)))
        row["load_avg_1min"] = os.getloadavg()[0]
        rows.append(row)
        log(f"  ({V:2d},{T}) exact {row['exact_s']:7.2f} s  balanced {row['balanced_s']:7.2f} s  "
            f"torch {row.get('torch_s', float('nan')):7.2f} s  per frame exact "
            f"{row['exact_s_per_frame']:.3f} balanced {row['balanced_s_per_frame']:.3f}  "
            f"PSNR(bal vs exact) {row['balanced_psnr_vs_exact']:.1f}")
    return {"seed": int(HELDOUT_SEEDS[0]), "frames": n_frames, "rows": rows}


_MEMORY_CHILD = r"""
import json, sys, time
import numpy as np
sys.path.insert(0, sys.argv[1])
from iris_runtime import IrisRuntime
model_dir, quality, threads, size = sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5])
workers = int(sys.argv[7])

def hwm_mb():
    # VmHWM: peak RSS of this process image (ru_maxrss would carry the parent's peak over exec).
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0

images = np.load(sys.argv[6])                      # 16 reference frames, uint8 [16, H, W, 3]
rt = IrisRuntime(model_dir, threads=threads, workers=workers)
before = hwm_mb()
scene = rt.encode(list(images))
after_encode = hwm_mb()
pose = scene.world_from_cam[1].copy(); pose[:3, 3] += [0.01, 0.0, 0.0]
t = time.perf_counter()
res = rt.render(scene, pose, height=size, width=size, depth=True, quality=quality)
secs = time.perf_counter() - t
peak = hwm_mb()
print(json.dumps({"quality": quality, "views": 16, "size": [size, size], "seconds": secs,
                  "workers": workers,
                  "rss_before_mb": before, "rss_after_encode_mb": after_encode,
                  "peak_rss_mb": peak, "work": res.work,
                  "finite": bool(np.isfinite(res.image_float).all())}))
"""


def part_memory(args, model_dir, workers: int, log) -> list[dict]:
    """Peak RSS of one render from 16 reference views in a fresh process (no torch imported)."""
    from iris_train.data import HELDOUT_SEEDS, SyntheticScenes
    images = SyntheticScenes([HELDOUT_SEEDS[0]], n_views=40)[0].images[::40 // 16][:16]
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        npy = Path(tmp) / "refs.npy"
        np.save(npy, images)
        for spec in args.memory_quality:
            quality, _, size = spec.partition("@")
            size = int(size) if size else args.memory_size
            log(f"memory: {size}^2 from 16 views, quality={quality} (subprocess)")
            proc = subprocess.run([sys.executable, "-c", _MEMORY_CHILD, str(REPO), str(model_dir),
                                   quality, str(args.threads), str(size), str(npy),
                                   str(workers)], capture_output=True, text=True, check=True)
            row = json.loads(proc.stdout.strip().splitlines()[-1])
            log(f"  peak RSS {row['peak_rss_mb']:.0f} MB, {row['seconds']:.1f} s")
            out.append(row)
    return out


# ----------------------------------------------------------------------------------------------
# Report
# ----------------------------------------------------------------------------------------------

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
        exact = next(r for r in k["rows"] if r["name"] == "exact (cull)")["s_per_frame"]
        for r in k["rows"]:
            L.append(f"| {r['name']} | {r['group']} | {r['s_per_frame']:.3f} | "
                     f"{exact / r['s_per_frame']:.2f}x | {r['max_abs_vs_full']:.1e} | "
                     f"{r['psnr_vs_full']:.2f} | {r['psnr_gt']:.2f} | {r['ssim_gt']:.4f} | "
                     f"{r.get('renderer_s_per_frame', float('nan')):.3f} | "
                     f"{r.get('numpy_s_per_frame', float('nan')):.3f} | "
                     f"{r.get('renderer_gflop_per_frame', float('nan')):.2f} |")
        L += ["", "Notes: " + "; ".join(f"{r['name']}: {r['note']}" for r in k["rows"]
                                        if r.get("note")), ""]
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
    if "peak" in results:
        p = results["peak"]
        L += ["## Renderer throughput against the matmul peak", "",
              f"numpy float32 matmul {p['matmul']['n']}^3: {p['matmul']['gflops']:.1f} GFLOP/s "
              f"(median of {len(p['matmul']['seconds'])}).", "",
              "| path | renderer GFLOP/frame | seconds/frame | basis | GFLOP/s | % of peak |",
              "|---|---|---|---|---|---|"]
        for r in p["rows"]:
            L.append(f"| {r['name']} | {r['gflop']:.2f} | {r['seconds']:.3f} | {r['basis']} | "
                     f"{r['gflops']:.1f} | {100 * r['fraction']:.0f}% |")
        if p.get("profile"):
            L += ["", f"ORT per-op profile of the exact path ({p['profile']['note']}):", "",
                  "| op type | share of node time |", "|---|---|"]
            for op, share in p["profile"]["shares"][:12]:
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


def ort_profile(rt, scene, pose, threads: int) -> dict:
    """Per-op-type share of ORT node time for one exact render (ORT's built-in profiler)."""
    import onnxruntime as ort
    from iris_runtime.manifest import read_graph_bytes
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.enable_profiling = True
    with tempfile.TemporaryDirectory() as tmp:
        opts.profile_file_prefix = str(Path(tmp) / "prof")
        sess = ort.InferenceSession(read_graph_bytes(rt.manifest.graphs["renderer"]), opts,
                                    providers=["CPUExecutionProvider"])
        saved = rt._sessions.get("renderer")
        rt._sessions["renderer"] = sess
        try:
            rt.render(scene, pose)
        finally:
            if saved is not None:
                rt._sessions["renderer"] = saved
            else:
                rt._sessions.pop("renderer")
        prof = sess.end_profiling()
        events = json.loads(Path(prof).read_text())
    by_op: dict[str, float] = {}
    for e in events:
        if e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time"):
            op = e.get("args", {}).get("op_name", "?")
            by_op[op] = by_op.get(op, 0.0) + e.get("dur", 0)
    total = sum(by_op.values()) or 1.0
    shares = sorted(((op, d / total) for op, d in by_op.items()), key=lambda x: -x[1])
    return {"shares": shares, "note": "one 64x64 frame, first held-out scene"}


def _graph_limits(results: dict) -> str:
    """What limits the exact path, from the run's own profile and FLOP counts."""
    prof = dict(results.get("peak", {}).get("profile", {}).get("shares", []))
    if not prof:
        return ""
    mm = sum(prof.get(k, 0.0) for k in ("MatMul", "FusedMatMul", "Gemm", "MatMulInteger"))
    ew = sum(prof.get(k, 0.0) for k in ("Where", "Transpose", "Mul", "Add", "Split", "Sub",
                                        "Div", "ReduceSum", "Expand", "Concat", "Reshape"))
    rows = {r["name"]: r for r in results.get("knobs", {}).get("rows", [])}
    txt = (f"ORT per-op profile of the exact path: matmul-class ops (MatMul, FusedMatMul, Gemm) "
           f"{100 * mm:.0f}% of node time, element-wise and layout ops (Where, Transpose, Mul, "
           f"Add, Split, ...) {100 * ew:.0f}% (Where {100 * prof.get('Where', 0):.0f}%: masking; "
           f"Transpose {100 * prof.get('Transpose', 0):.0f}%: view-major inputs to point-major "
           "field and per-head layouts); the matmuls are thin (model width 64)")
    ex, tc = rows.get("exact (cull)"), rows.get("torch eager + tcmalloc")
    if ex and tc and ex.get("renderer_gflop_per_frame"):
        g = ex["renderer_gflop_per_frame"]
        txt += (f". Same {g:.0f} GFLOP per frame: torch + tcmalloc {g / tc['s_per_frame']:.0f} "
                f"GFLOP/s (whole frame), the ORT graph {g / ex['renderer_s_per_frame']:.0f} "
                "GFLOP/s (graph time)")
    nc = rows.get("exact, no culling")
    if ex and nc and ex.get("work_per_frame") and nc.get("work_per_frame"):
        kept = ex["work_per_frame"]["points"] / max(1, nc["work_per_frame"]["points"])
        txt += (f". Exact skipping cannot help here: culling keeps {100 * kept:.0f}% of the "
                "samples (every sample of these scenes projects into some reference view)")
    return txt


def evaluate_targets(results: dict) -> list[dict]:
    out = []
    limits = _graph_limits(results)
    rows = {r["name"]: r for r in results.get("knobs", {}).get("rows", [])}
    exacts = [rows[n] for n in ("exact (cull)", "exact, 2 workers") if n in rows]
    ex = min(exacts, key=lambda r: r["s_per_frame"]) if exacts else None
    if ex and "torch eager" in rows:
        ratio = rows["torch eager"]["s_per_frame"] / ex["s_per_frame"]
        out.append({"target": "exact path >= 3x faster than torch eager as installed",
                    "met": ratio >= 3.0, "measured": f"{ratio:.2f}x ({ex['name']}: "
                    f"{ex['s_per_frame']:.3f} s vs {rows['torch eager']['s_per_frame']:.3f} s "
                    "per frame)", "why": "torch's default allocator makes its time vary from run "
                    "to run (page faults on the 4096-ray chunks); on the ORT side: " + limits})
    if ex and "torch eager + tcmalloc" in rows:
        tc = rows["torch eager + tcmalloc"]
        ratio = tc["s_per_frame"] / ex["s_per_frame"]
        out.append({"target": "exact path >= 1.5x faster than torch eager with tcmalloc",
                    "met": ratio >= 1.5, "measured": f"{ratio:.2f}x ({tc['s_per_frame']:.3f} s "
                    "per frame)", "why": limits})
    if ex and "torch eager" in rows:
        err = rows["torch eager"]["max_abs_vs_full"]
        out.append({"target": "identical output to torch (<= 1e-4)", "met": err <= 1e-4,
                    "measured": f"max abs {err:.1e} (rgb, all frames)"})
    if "no culling" in " ".join(rows):
        err = rows["exact, no culling"]["max_abs_vs_full"]
        out.append({"target": "exact knobs unchanged within 1e-6", "met": err <= 1e-6,
                    "measured": f"culling vs none: max abs {err:.1e}"})
    sc = {(r["views"], r["targets"]): r for r in results.get("scaling", {}).get("rows", [])}
    v4 = next((r for (v, _), r in sc.items() if v == 4), None)
    v16 = next((r for (v, _), r in sc.items() if v == 16), None)
    if v4 and v16:
        g = v16["balanced_s_per_frame"] / v4["balanced_s_per_frame"]
        out.append({"target": "balanced: time per target frame 4 -> 16 views grows <= 1.5x",
                    "met": g <= 1.5, "measured": f"{g:.2f}x (exact path: "
                    f"{v16['exact_s_per_frame'] / v4['exact_s_per_frame']:.2f}x)"})
        in_range = [r for (v, _), r in sc.items() if 4 <= v <= 16]
        worst = min(r["balanced_psnr_gt"] - r["exact_psnr_gt"] for r in in_range)
        beyond = "; ".join(f"V={v}: {r['balanced_psnr_gt'] - r['exact_psnr_gt']:+.3f} dB"
                           for (v, _), r in sc.items() if v > 16)
        out.append({"target": "balanced, 4 to 16 views: at most 0.1 dB PSNR (gt) below the full "
                              "render", "met": worst >= -0.1,
                    "measured": f"worst difference {worst:+.3f} dB; PSNR vs full >= "
                    f"{min(r['balanced_psnr_vs_exact'] for r in in_range):.1f} dB"
                    + (f" (beyond the range, {beyond})" if beyond else "")})
    if "peak" in results:
        name = ex["name"] if ex else "exact (cull)"
        r = next(r for r in results["peak"]["rows"] if r["name"] == name)
        out.append({"target": "renderer graph >= 50% of float32 matmul peak",
                    "met": r["fraction"] >= 0.5, "measured": f"{100 * r['fraction']:.0f}% "
                    f"({r['gflops']:.1f} of {results['peak']['matmul']['gflops']:.1f} GFLOP/s)",
                    "why": limits})
    for r in results.get("memory", []):
        out.append({"target": f"peak RSS {r['size'][0]}x{r['size'][1]} from 16 views <= 1.5 GB "
                              f"({r['quality']})",
                    "met": r["peak_rss_mb"] <= 1536, "measured": f"{r['peak_rss_mb']:.0f} MB"})
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", type=Path, default=REPO / "models" / "iris-tiny-rgb.pt")
    ap.add_argument("--model-dir", type=Path, help="an iris-export output of the checkpoint "
                    "(default: export it, with --quantize int8, to a temporary directory)")
    ap.add_argument("--scenes", type=int, default=1)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--threads", type=int, default=len(os.sched_getaffinity(0)))
    ap.add_argument("--parts", default="knobs,scaling,peak,memory")
    ap.add_argument("--scaling", default=",".join(f"{v}x{t}" for v, t in SCALING),
                    help="(views)x(targets) list")
    ap.add_argument("--size", type=int, default=64, help="knobs: target frame size (64: the "
                    "model's; smaller only for quick checks, ground truth area-resized)")
    ap.add_argument("--scaling-size", type=int, default=24, help="scaling: target frame size")
    ap.add_argument("--memory-size", type=int, default=512)
    ap.add_argument("--memory-quality", default="balanced,exact@128",
                    help="quality[@size] list (size default --memory-size)")
    ap.add_argument("--no-tcmalloc", action="store_true")
    ap.add_argument("--note", default="", help="a note on the model (e.g. which checkpoint)")
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results")
    ap.add_argument("--torch-child", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    args.scaling = [tuple(int(x) for x in s.split("x")) for s in args.scaling.split(",") if s]
    args.memory_quality = [q for q in args.memory_quality.split(",") if q]
    if args.torch_child:
        _torch_child(args)
        return 0
    parts = set(args.parts.split(","))
    t_start = time.perf_counter()

    def log(msg):
        print(f"[{time.perf_counter() - t_start:7.1f} s] {msg}", flush=True)

    from iris_runtime import IrisRuntime
    results: dict = {"machine": machine_facts(args.threads),
                     "args": {k: (str(v) if isinstance(v, Path) else v)
                              for k, v in vars(args).items()}}
    results["model"] = {"checkpoint": str(args.checkpoint), "sha256": _sha256(args.checkpoint),
                        "note": args.note}
    tmp = None
    model_dir = args.model_dir
    if model_dir is None:
        from export.pipeline import export_model
        tmp = tempfile.TemporaryDirectory()
        model_dir = Path(tmp.name) / "model"
        log(f"exporting {args.checkpoint} (with int8)")
        export_model(args.checkpoint, model_dir, quantize="int8", force=True, quick=True,
                     progress=False, threads=args.threads)
    rt = IrisRuntime(model_dir, threads=args.threads)
    rt_nocull = IrisRuntime(model_dir, threads=args.threads, cull=False)
    rt_par = IrisRuntime(model_dir, threads=args.threads, workers=2)
    model = None
    try:
        from iris_train.model import load_model, read_checkpoint
        model = load_model(args.checkpoint)
        results["model"]["step"] = read_checkpoint(args.checkpoint).get("step")
    except ImportError:
        log("torch not installed: no torch anchor")
    if "peak" in parts:
        log("peak: numpy matmul 4096^3")
        results["peak"] = {"matmul": matmul_peak()}
        log(f"  {results['peak']['matmul']['gflops']:.1f} GFLOP/s")
    if "knobs" in parts:
        results["knobs"] = part_knobs(args, rt, rt_nocull, rt_par, model, log)
    # The faster exact configuration (1 worker x threads, or 2 workers) runs the remaining parts
    # (same output; measured in the knobs table).
    workers = 1
    if "knobs" in results:
        rows = {r["name"]: r for r in results["knobs"]["rows"]}
        if rows["exact, 2 workers"]["s_per_frame"] < rows["exact (cull)"]["s_per_frame"]:
            workers = 2
    results["workers_used"] = workers
    rt_best = rt_par if workers == 2 else rt
    if "scaling" in parts:
        log(f"scaling (workers={workers})")
        results["scaling"] = part_scaling(args, rt_best, model, log)
    if "peak" in parts:
        peak = results["peak"]["matmul"]["gflops"]
        rows = []
        for r in results.get("knobs", {}).get("rows", []):
            if "renderer_gflop_per_frame" in r and r["name"] in (
                    "exact (cull)", "exact, 2 workers", "exact, no culling", "top-k ray k=4",
                    "samples 32", "int8", "preset balanced"):
                # Graph-only seconds are summed over threads with workers > 1: use the frame's
                # wall time there (it includes the numpy geometry, so it is a lower bound).
                par = r["name"] == "exact, 2 workers"
                secs = r["s_per_frame"] if par else r["renderer_s_per_frame"]
                gflops = r["renderer_gflop_per_frame"] / secs
                rows.append({"name": r["name"], "gflop": r["renderer_gflop_per_frame"],
                             "seconds": secs, "gflops": gflops, "fraction": gflops / peak,
                             "wall_gflops": r["renderer_gflop_per_frame"] / r["s_per_frame"],
                             "basis": "frame wall time" if par else "renderer graph time"})
        results["peak"]["rows"] = rows
        if "knobs" in results:
            from iris_train.evaluate import split_frames
            refs, targets = split_frames(8)
            sc = heldout_scenes(1)[0]
            enc = rt.encode(list(sc.images))
            results["peak"]["profile"] = ort_profile(rt, enc.subset(list(refs)),
                                                     enc.world_from_cam[targets[0]], args.threads)
    if "memory" in parts:
        results["memory"] = part_memory(args, model_dir, workers, log)
    results["targets"] = evaluate_targets(results)
    results["seconds_total"] = time.perf_counter() - t_start
    results["machine"]["load_avg_end"] = os.getloadavg()
    args.out.mkdir(parents=True, exist_ok=True)
    for r in results.get("knobs", {}).get("rows", []):
        r["s_per_frame_runs"] = [[round(x, 4) for x in runs] for runs in r["s_per_frame_runs"]]
    (args.out / "error_vs_time.json").write_text(json.dumps(results, indent=1, default=float))
    (args.out / "error_vs_time.md").write_text(markdown(results))
    if "knobs" in results:
        plot(results, args.out / "error_vs_time.png")
    log(f"wrote {args.out}/error_vs_time.{{json,md,png}}")
    print(markdown(results))
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())
