"""The measured parts of the error-against-time benchmark: knobs, scaling, sizing, peak, memory.

Each ``part_*`` returns the JSON-ready section of the results (``results[part]``); the report
(``report``) and the targets (``targets``) read only those sections. ``args`` is the benchmark's
parsed command line (``benchmarks/error_vs_time.py``).
"""
from __future__ import annotations

import json
import os
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from . import child, rows as R
from .machine import TCMALLOC, ort_profile, renderer_flops

# ----------------------------------------------------------------------------------------------
# Timing, metrics, scenes
# ----------------------------------------------------------------------------------------------


def timed(fn, runs: int):
    """-> (median seconds, all seconds, last result) of ``runs`` calls."""
    times, out = [], None
    for _ in range(runs):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), times, out


def psnr(a, b) -> float:
    """PSNR in dB, capped at ``metrics.PSNR_CAP`` (identical images)."""
    from iris_train.metrics import capped_psnr
    return capped_psnr(a, b)


def ssim(a, b) -> float:
    from iris_train.metrics import ssim
    return ssim(a, b)


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


# ----------------------------------------------------------------------------------------------
# Torch anchors
# ----------------------------------------------------------------------------------------------

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


def torch_parity(model, rt, images_list, refs, targets, size: int, exact_outs) -> dict:
    """Where the exact path's distance from torch comes from, per stage (no timing):

    - ``exact_vs_torch64``: the exact ORT path against torch in float64 (encode and render), the
      most exact reference there is;
    - ``torch32_vs_torch64``: torch eager (float32, what the anchor rows run) against the same;
    - ``renderer_vs_torch32``: the ORT renderer given torch's own float32 scene (field maps,
      cameras, focal) and target poses, against torch's render of them: the renderer graph and
      the numpy ray geometry alone;
    - ``encoder_maps_vs_torch32`` / ``encoder_poses_vs_torch32``: the encoder graph's field maps
      and poses against torch's.
    Max abs over every target frame (rgb in [0, 1])."""
    import copy
    import dataclasses
    import torch
    model64 = copy.deepcopy(model).double()
    out = {"exact_vs_torch64": 0.0, "torch32_vs_torch64": 0.0, "renderer_vs_torch32": 0.0,
           "encoder_maps_vs_torch32": 0.0, "encoder_poses_vs_torch32": 0.0}
    k = 0
    with torch.no_grad():
        for images in images_list:
            x = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2) / 255.0
            sc32 = model.encode(x.float())
            sc64 = model64.encode(x.double())
            ort = rt.encode(list(images), cameras="model")
            out["encoder_maps_vs_torch32"] = max(out["encoder_maps_vs_torch32"], float(
                np.abs(ort.field_maps - sc32.field_maps.numpy()).max()))
            out["encoder_poses_vs_torch32"] = max(out["encoder_poses_vs_torch32"], float(
                np.abs(ort.world_from_cam - sc32.world_from_cam.numpy()).max()))
            same = dataclasses.replace(ort, field_maps=sc32.field_maps.numpy().astype(ort.field_maps.dtype),
                                       world_from_cam=sc32.world_from_cam.double().numpy(),
                                       focal=sc32.focal.double().numpy()).subset(refs)
            for t in targets:
                r32, _ = model.render(sc32.subset(refs), sc32.world_from_cam[[t]], size, size)
                r64, _ = model64.render(sc64.subset(refs), sc64.world_from_cam[[t]], size, size)
                r32, r64 = r32[0].double().numpy(), r64[0].numpy()
                pose = sc32.world_from_cam[t].double().numpy()
                same_out = rt.render(same, pose, height=size, width=size, depth=True).image_float
                out["exact_vs_torch64"] = max(out["exact_vs_torch64"], float(np.abs(exact_outs[k] - r64).max()))
                out["torch32_vs_torch64"] = max(out["torch32_vs_torch64"], float(np.abs(r32 - r64).max()))
                out["renderer_vs_torch32"] = max(out["renderer_vs_torch32"],
                                                 float(np.abs(same_out.astype(np.float64) - r32).max()))
                k += 1
    return out


def torch_tcmalloc_anchor(args) -> dict | None:
    """The torch anchor in a subprocess started with tcmalloc preloaded (``child torch-anchor``);
    None when this machine has no tcmalloc."""
    if not Path(TCMALLOC).exists():
        return None
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "torch_tcmalloc.npz"
        cmd = child.command("torch-anchor", checkpoint=Path(args.checkpoint), scenes=args.scenes,
                            runs=args.runs, threads=args.threads, size=args.size, out=out)
        subprocess.run(cmd, env=child.environment(LD_PRELOAD=TCMALLOC), check=True)
        d = np.load(out)
        return {"meds": d["meds"].tolist(), "alls": d["alls"].tolist(), "outs": d["outs"],
                "preload": str(d["preload"])}


# ----------------------------------------------------------------------------------------------
# Parts
# ----------------------------------------------------------------------------------------------

def part_knobs(args, rt, rt_nocull, rt_par, model, log) -> dict:
    """Every knob on the held-out scenes' targets, against the full render and the ground truth.

    ``rt``: the default runtime (culling on); ``rt_nocull``: ``cull=False``; ``rt_par``:
    ``workers=2``; ``model``: the torch ``IrisModel`` (None without torch: no anchors)."""
    from iris_train.data import HELDOUT_SEEDS
    from iris_train.evaluate import split_frames
    scenes = heldout_scenes(args.scenes)
    refs, targets = split_frames(8)
    refs, targets = list(refs), list(targets)
    # Encode every scene once (the Scene cache); targets at their predicted poses.
    encoded = [rt.encode(list(s.images), cameras="model") for s in scenes]
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
            runs = []                                          # every timed run's timings

            def render():
                res = runtime.render(subs[i], pose, depth=True, **kw)
                runs.append(res.timings)
                return res

            med, times, res = timed(render, args.runs)
            meds.append(med)
            alls.append(times)
            outs.append(res.image_float.astype(np.float64))
            works.append(res.work)
            # Per stage, the median over the runs (like the frame time), not the last run's.
            tims.append({k: statistics.median(r[k] for r in runs) for k in runs[0]})
        return meds, alls, outs, works, tims

    rows = []
    log("knobs: full ORT render (exact, cull)")
    full = ort_config(rt, {})
    full_outs = full[2]

    def add(name, group, meds, alls, outs, works=None, tims=None, note=""):
        err = max(float(np.abs(o - f).max()) for o, f in zip(outs, full_outs))
        row = {"name": name, "group": group, "s_per_frame": float(np.mean(meds)),
               "s_per_frame_runs": alls, "max_abs_vs_full": err,
               "psnr_vs_full": float(np.mean([psnr(o, f) for o, f in zip(outs, full_outs)])),
               "psnr_gt": float(np.mean([psnr(np.clip(o, 0, 1), fr[3])
                                         for o, fr in zip(outs, frames)])),
               "ssim_gt": float(np.mean([ssim(np.clip(o, 0, 1), fr[3])
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
            if "pixels" in tot:                       # coarse-to-fine (iris_runtime.adaptive)
                row["refined_fraction"] = tot["refined_rays"] / tot["pixels"]
                row["windowed_fraction"] = tot["windowed_rays"] / max(1, tot["refined_rays"])
                row["kept_sample_fraction"] = (tot["kept_samples"]
                                               / max(1, tot["refined_rays"] * rt.samples))
        rows.append(row)
        log(f"  {name:24s} {row['s_per_frame']:7.3f} s/frame  max|d| {err:.2e}  "
            f"PSNR(full) {row['psnr_vs_full']:6.2f}  PSNR(gt) {row['psnr_gt']:6.2f}")
        return row

    # Anchors.
    if model is not None:
        log("knobs: torch eager (as installed)")
        meds, alls, outs = torch_render_frames(model, [s.images for s in scenes], refs, targets,
                                               args.threads, args.runs, size)
        add(R.TORCH_EAGER, R.ANCHOR, meds, alls, outs, note="IrisModel.render, default allocator")
        if not args.no_tcmalloc:
            log("knobs: torch eager + tcmalloc (subprocess)")
            tc = torch_tcmalloc_anchor(args)
            if tc is not None:
                add(R.TORCH_TCMALLOC, R.ANCHOR, tc["meds"], tc["alls"], list(tc["outs"]),
                    note=f"LD_PRELOAD={tc['preload']}")
    add(R.EXACT, R.EXACT_GROUP, *full, note="default: IrisRuntime(cull=True)")
    log("knobs: exact, data-parallel (workers=2)")
    add(R.EXACT_2_WORKERS, R.EXACT_GROUP, *ort_config(rt_par, {}),
        note=f"IrisRuntime(threads={args.threads}, workers=2): two renderer calls in flight, "
             f"{max(1, args.threads // 2)} intra-op thread(s) each")
    log("knobs: no culling")
    add(R.EXACT_NO_CULLING, R.EXACT_GROUP, *ort_config(rt_nocull, {}),
        note="IrisRuntime(cull=False): every sample, view and ray through the graph")
    # Scene cache: encode the references on every render (one-shot API).
    # (encode + render at the head's cameras, as every row here: the shipped model's default
    # cameras are solved from the photos, which torch's anchor does not do.)
    log("knobs: encode + render per frame (no Scene cache)")
    meds, alls, outs = [], [], []

    def one_shot(imgs, pose, **kw):
        return rt.render(rt.encode(imgs, cameras="model"), pose, **kw)

    one_shot(list(scenes[0].images[refs]), frames[0][2], **ort_kw)
    for i, t, pose, _ in frames:
        imgs = list(scenes[i].images[refs])
        med, times, res = timed(lambda: one_shot(imgs, pose, depth=True, **ort_kw), args.runs)
        meds.append(med)
        alls.append(times)
        outs.append(res.image_float.astype(np.float64))
    add(R.EXACT_NO_SCENE_CACHE, R.EXACT_GROUP, meds, alls, outs,
        note="encoder re-run on the references per render; its scene differs from the "
             "all-frames encoding, so the error is the encoder's view-set dependence, not rounding")
    for knob in R.KNOB_GRID:
        if knob.render_kw.get("precision") == "int8" and "renderer_int8" not in rt.manifest.graphs:
            continue                                  # exported without --quantize int8
        log(f"knobs: {knob.name}")
        add(knob.name, knob.group, *ort_config(rt, knob.render_kw))
    parity = None
    if model is not None:
        log("knobs: parity with torch float32 and float64, per stage")
        parity = torch_parity(model, rt, [s.images for s in scenes], refs, targets, size, full_outs)
        log("  " + ", ".join(f"{k} {v:.1e}" for k, v in parity.items()))
    return {"refs": refs, "targets": targets,
            "scenes": [int(s) for s in HELDOUT_SEEDS[:args.scenes]],
            "frames": len(frames), "rows": rows, "parity": parity}


def part_scaling(args, rt, model, log) -> dict:
    """(V refs, T targets): encode V + T frames, render T targets from V refs; seconds total."""
    from iris_train.data import HELDOUT_SEEDS, SyntheticScenes
    n_frames = max(v + t for v, t in R.SCALING)
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
        row = {"views": V, "targets": T, "paper_gpu_s": R.PAPER_TABLE11.get((V, T))}

        def ort_run(kw):
            sc = rt.encode(list(images), cameras="model")
            t_enc = time.perf_counter()
            sub = sc.subset(list(refs_pos))
            outs = [rt.render(sub, sc.world_from_cam[j], depth=True, **okw, **kw)
                    for j in tgt_pos]
            return sc, outs, t_enc

        results = {}
        for label, kw in R.SCALING_METHODS:
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
            row[f"{label}_psnr_gt"] = float(np.mean([psnr(np.clip(o, 0, 1), g)
                                                     for o, g in zip(results[label], gts)]))
        exact, balanced = results[R.SCALING_EXACT], results[R.SCALING_BALANCED]
        row["balanced_psnr_vs_exact"] = float(np.mean([psnr(b, e)
                                                       for b, e in zip(balanced, exact)]))
        row["balanced_max_abs_vs_exact"] = float(max(np.abs(b - e).max()
                                                     for b, e in zip(balanced, exact)))
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
                np.abs(rgb[k].double().numpy() - exact[k]).max() for k in range(T)))
        row["load_avg_1min"] = os.getloadavg()[0]
        rows.append(row)
        log(f"  ({V:2d},{T}) exact {row['exact_s']:7.2f} s  balanced {row['balanced_s']:7.2f} s  "
            f"torch {row.get('torch_s', float('nan')):7.2f} s  per frame exact "
            f"{row['exact_s_per_frame']:.3f} balanced {row['balanced_s_per_frame']:.3f}  "
            f"PSNR(bal vs exact) {row['balanced_psnr_vs_exact']:.1f}")
    return {"seed": int(HELDOUT_SEEDS[0]), "frames": n_frames, "rows": rows}


def _spread(n_frames: int, refs: int) -> tuple[np.ndarray, int]:
    """``refs`` reference frames spread evenly over ``n_frames`` frames of an orbit, and one
    target frame halfway between two of them -> (reference indices, target index)."""
    idx = np.round(np.linspace(0, n_frames - 1, refs + 1, endpoint=False)).astype(int)
    return idx[np.arange(refs + 1) != 1], int(idx[1])


def _timed_until(fn, runs: int, budget_s: float):
    """-> (median seconds, all seconds, last result) of up to ``runs`` calls, stopping once they
    add up to ``budget_s`` (at least one call)."""
    times, out = [], None
    while len(times) < runs and sum(times) < budget_s:
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), times, out


def part_sizing(args, rt, log) -> dict:
    """What a user sizes a server by (issue 12, part 3): seconds per frame of every preset at
    ``args.sizing_sizes`` from ``args.sizing_views`` reference views, and frames per second of
    every preset over an orbit of ``args.fps_poses`` poses of one encoded scene.

    One held-out scene (seed ``HELDOUT_SEEDS[0]``) with max(views) + 1 frames: per V, V
    references spread over the orbit and one target between two of them, all encoded once
    (encode seconds reported), the target rendered at its predicted pose. Per (preset, V): one
    warm-up render at the smallest size, then per size ``_timed_until`` (``--runs`` runs, at most
    ``rows.SIZING_SECONDS_PER_CONFIG`` seconds). Error: PSNR against the exact render of the
    same (V, size) (no ground truth above the model's 64x64)."""
    from iris_runtime import QUALITY_PRESETS
    from iris_runtime.orbit import orbit_poses
    from iris_train.data import HELDOUT_SEEDS, SyntheticScenes
    presets = ["exact"] + [p for p in QUALITY_PRESETS if p != "exact"]   # the errors' reference
    n_frames = max(max(args.sizing_views), args.fps_views) + 1
    images = SyntheticScenes([HELDOUT_SEEDS[0]], n_views=n_frames)[0].images
    sizes = sorted(args.sizing_sizes)
    rows = []
    for V in args.sizing_views:
        refs, target = _spread(n_frames, V)
        t0 = time.perf_counter()
        scene = rt.encode(list(images[list(refs) + [target]]), cameras="model")
        encode_s = time.perf_counter() - t0
        sub, pose = scene.subset(list(range(V))), scene.world_from_cam[V]
        exact = {}
        for preset in presets:
            rt.render(sub, pose, height=sizes[0], width=sizes[0], quality=preset)   # warm-up
            for size in sizes:
                med, times, res = _timed_until(
                    lambda: rt.render(sub, pose, height=size, width=size, depth=True,
                                      quality=preset), args.runs, R.SIZING_SECONDS_PER_CONFIG)
                out = res.image_float.astype(np.float64)
                exact.setdefault(size, out)               # the first preset is "exact"
                row = {"views": V, "size": size, "preset": preset, "s_per_frame": med,
                       "s_runs": times, "encode_s": encode_s,
                       "psnr_vs_exact": psnr(out, exact[size]),
                       "max_abs_vs_exact": float(np.abs(out - exact[size]).max()),
                       "work": res.work, "load_avg_1min": os.getloadavg()[0]}
                rows.append(row)
                log(f"  sizing V={V:2d} {size:3d}^2 {preset:9s} {med:8.3f} s/frame "
                    f"(x{len(times)})  PSNR vs exact {row['psnr_vs_exact']:6.2f}")
    # Frames per second: many poses of one encoded scene (the Scene cache), one after another.
    refs, _ = _spread(n_frames, args.fps_views)
    t0 = time.perf_counter()
    scene = rt.encode(list(images[list(refs)]), cameras="model")
    encode_s = time.perf_counter() - t0
    poses = orbit_poses(scene.world_from_cam, args.fps_poses, near=rt.near, far=rt.far)
    fps = []
    for preset in presets:
        size = args.fps_size
        rt.render(scene, poses[0], height=size, width=size, quality=preset)       # warm-up
        t0 = time.perf_counter()
        for pose in poses:
            rt.render(scene, pose, height=size, width=size, quality=preset)
        secs = time.perf_counter() - t0
        fps.append({"preset": preset, "views": args.fps_views, "size": size,
                    "poses": len(poses), "seconds": secs, "fps": len(poses) / secs,
                    "encode_s": encode_s, "load_avg_1min": os.getloadavg()[0]})
        log(f"  fps {preset:9s} {len(poses)} poses at {size}^2 from {args.fps_views} views: "
            f"{len(poses) / secs:.2f} frames/s")
    return {"seed": int(HELDOUT_SEEDS[0]), "frames": n_frames, "presets": presets,
            "workers": rt.workers, "threads": rt.threads, "rows": rows, "fps": fps}


def peak_rows(knob_rows: list[dict], peak_gflops: float) -> list[dict]:
    """The renderer graph's FLOP rate against the matmul peak for the ``rows.PEAK_ROWS`` of the
    knobs table, on the graph's own time (the ORT calls; the basis of the issue's figures) and on
    the whole frame's wall time (numpy geometry and Python included, a lower bound).

    With 2 workers the graph time is summed over two one-thread calls in flight, so it is divided
    by the 2 cores they run on: the graph's rate per core times 2. Each call's time is its wall
    time on its worker thread (at least its CPU time), so this is a lower bound too."""
    rows = []
    for r in knob_rows:
        if "renderer_gflop_per_frame" in r and r["name"] in R.PEAK_ROWS:
            workers = 2 if r["name"] == R.EXACT_2_WORKERS else 1
            secs = r["renderer_s_per_frame"] / workers
            gflops = r["renderer_gflop_per_frame"] / secs
            wall = r["renderer_gflop_per_frame"] / r["s_per_frame"]
            rows.append({"name": r["name"], "gflop": r["renderer_gflop_per_frame"],
                         "seconds": secs, "gflops": gflops, "fraction": gflops / peak_gflops,
                         "wall_seconds": r["s_per_frame"], "wall_gflops": wall,
                         "wall_fraction": wall / peak_gflops,
                         "basis": ("renderer graph time / 2 cores (two one-thread calls in "
                                   "flight)" if workers == 2 else "renderer graph time")})
    return rows


def part_peak(matmul: dict, knob_rows: list[dict], rt, threads: int) -> dict:
    """``matmul`` (``matmul_peak()``, measured first, on the quiet machine) with the
    ``peak_rows`` of the knobs table and ORT's per-op profile of the exact path (when the knobs
    ran)."""
    out = {"matmul": matmul, "rows": peak_rows(knob_rows, matmul["gflops"])}
    if knob_rows:
        from iris_train.evaluate import split_frames
        refs, targets = split_frames(8)
        sc = heldout_scenes(1)[0]
        enc = rt.encode(list(sc.images), cameras="model")
        out["profile"] = ort_profile(rt, enc.subset(list(refs)), enc.world_from_cam[targets[0]],
                                     threads)
    return out


def part_memory(args, model_dir, workers: int, log) -> list[dict]:
    """Peak RSS of one render from 16 reference views in a fresh process (``child memory``: no
    torch imported)."""
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
            cmd = child.command("memory", model_dir=Path(model_dir), quality=quality,
                                threads=args.threads, size=size, images=npy, workers=workers)
            proc = subprocess.run(cmd, env=child.environment(), capture_output=True, text=True)
            if proc.returncode != 0:
                raise RuntimeError(f"memory child failed ({' '.join(cmd)}):\n{proc.stderr}")
            row = json.loads(proc.stdout.strip().splitlines()[-1])
            log(f"  peak RSS {row['peak_rss_mb']:.0f} MB, {row['seconds']:.1f} s")
            out.append(row)
    return out
