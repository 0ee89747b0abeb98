"""Two scales against the exact march: error and run time at output sizes above the model's.

    python benchmarks/two_scale.py out/model --json benchmarks/results/two_scale.json
    python benchmarks/two_scale.py out/model --sets synthetic:heldout --scenes 2 --sizes 128
                                                  # a quick look, not the recorded run
    python benchmarks/two_scale.py out/model --sets --json speed.json   # the speed bars only

For every scene of every set: the references (frames 0 2 3 5 7, the protocol of ``iris-eval``)
are encoded at their own resolution with the model's default cameras, the first target (frame
1) is located against them and rendered at each output size N by every configuration below. A
row gives, per configuration and size, the median seconds per frame (one thread, after a
warm-up render of the scene), the PSNR against the exact march of the same size (the reference
of the lossy steps: the same model, cameras and colours), and the PSNR / SSIM against the
target photo brought to N (centre crop, area resize) where the photo is at least N on its short
side. ``upsampled`` is the model-resolution exact render, bicubic to N (what every size was
before colours came from the photos).

Configurations: the presets (``auto``, ``fast``), ``auto`` without its depth search
(``depth_search=0``), and field_scale x colour_samples variants around ``auto`` (its search
included). The speed section times the castle's first scene with all 8 photos encoded at
their size: the default render at 256 and ``fast`` at 256 against ``exact`` at the model's size
(the ratios the issue's bars are stated in), in wall seconds and in the process's CPU seconds
(one thread: the same on a quiet machine; the CPU ratio holds on a busy one).

Sets: ``synthetic:heldout`` (the 16 held-out scenes, cached at 256x256:
``python -m iris_train.data --heldout --render-size 256 256``), ``DIR`` a folder of scene
folders of photos (the real sets of ``scripts/real_sets.py``).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from benchmarks.evt.measure import timed  # noqa: E402
from iris_runtime import IrisRuntime  # noqa: E402
from iris_runtime.fileio import atomic_write_json  # noqa: E402
from iris_runtime.images import load_image  # noqa: E402

REFERENCES = (0, 2, 3, 5, 7)
TARGET = 1
#: (name, render keywords): the presets, the default without its search, and variants of the
#: default's two scales (render keywords override the default preset's settings).
CONFIGS = (
    ("auto", dict(quality="auto")),
    ("auto, no search", dict(quality="auto", depth_search=0)),
    ("fast", dict(quality="fast")),
    ("fs1/4 M8", dict(field_scale=0.25, colour_samples=8)),
    ("fs1/8 M4", dict(field_scale=0.125, colour_samples=4)),
    ("fs1/8 M16", dict(field_scale=0.125, colour_samples=16)),
    ("fs1/16 M8", dict(field_scale=0.0625, colour_samples=8)),
)


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return float("inf") if mse == 0 else -10.0 * np.log10(mse)


def _ssim(a: np.ndarray, b: np.ndarray) -> float:
    from skimage.metrics import structural_similarity
    return float(structural_similarity(a, b, channel_axis=2, data_range=1.0))


def _to_size(photo: np.ndarray, n: int) -> np.ndarray:
    """Centre crop to square, area resize to n x n, float in [0, 1]."""
    h, w = photo.shape[:2]
    s = min(h, w)
    crop = photo[(h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s]
    return cv2.resize(crop, (n, n), interpolation=cv2.INTER_AREA).astype(np.float32) / 255.0


def load_set(name: str, limit: int | None) -> list[tuple[str, list[np.ndarray]]]:
    """(scene name, 8 photos uint8 at their own size) of a set."""
    if name == "synthetic:heldout":
        from iris_train.data import HELDOUT_SEEDS, SyntheticScenes
        seeds = list(HELDOUT_SEEDS)[:limit]
        scenes = SyntheticScenes(seeds, size=(256, 256), render_size=(256, 256))
        return [(str(s), list(scenes.get_seed(s).images)) for s in seeds]
    root = Path(name)
    out = []
    for folder in sorted(p for p in root.iterdir() if p.is_dir())[:limit]:
        files = sorted(f for f in folder.iterdir() if f.suffix.lower() in (".png", ".jpg"))
        out.append((folder.name, [load_image(str(f)) for f in files[:8]]))
    return out


def _timed(fn, runs: int):
    """(last result, median seconds) of ``runs`` calls (``evt.measure.timed``)."""
    median, _, out = timed(fn, runs)
    return out, median


def measure_scene(rt: IrisRuntime, photos: list[np.ndarray], sizes: list[int], runs: int,
                  exact_up_to: int) -> dict:
    refs = [photos[i] for i in REFERENCES]
    scene = rt.encode(refs)
    pose = rt.locate(scene, photos[TARGET])
    rt.render(scene, pose)                                        # warm-up (sessions, levels)
    short = min(photos[TARGET].shape[:2])
    model, t_model = _timed(lambda: rt.render(scene, pose, quality="exact"), runs)
    rows = {}
    for n in sizes:
        gt = _to_size(photos[TARGET], n) if short >= n else None
        row = {}
        if n <= exact_up_to:
            exact, t = _timed(lambda: rt.render(scene, pose, height=n, width=n,
                                                quality="exact", depth=True), 1)
            exact = exact.image_float
            row["exact"] = {"s": t}
        else:
            exact = None
        up = np.clip(cv2.resize(model.astype(np.float32) / 255.0, (n, n),
                                interpolation=cv2.INTER_CUBIC), 0, 1)
        row["upsampled"] = {"s": t_model}
        results = {"upsampled": up, "exact": exact}
        for name, kw in CONFIGS:
            rt.render(scene, pose, height=n, width=n, **kw)       # the size's levels made once
            r, t = _timed(lambda: rt.render(scene, pose, height=n, width=n, depth=True, **kw),
                          runs)
            results[name] = r.image_float
            row[name] = {"s": t}
        for name, image in results.items():
            if image is None:
                continue
            q = np.rint(np.clip(image, 0, 1) * 255) / 255
            if exact is not None and name != "exact":
                row[name]["psnr_vs_exact"] = _psnr(q, np.rint(exact * 255) / 255)
            if gt is not None:
                row[name]["psnr"] = _psnr(q, gt)
                row[name]["ssim"] = _ssim(q.astype(np.float32), gt)
        rows[str(n)] = row
    return {"model_s": t_model, "sizes": rows, "photo_size": list(photos[0].shape[:2])}


def _cpu_timed(fn, runs: int) -> tuple[float, float]:
    """(median wall seconds, median CPU seconds of this process) of ``runs`` calls. With one
    thread the CPU time is the wall time of a quiet machine; on a busy one it still is the work
    done, so the ratios below stay meaningful when the wall clock is not."""
    wall, cpu = [], []
    for _ in range(runs):
        t, c = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return float(np.median(wall)), float(np.median(cpu))


def speed(rt: IrisRuntime, photos: list[np.ndarray], runs: int) -> dict:
    """The bars' ratios on one scene of 8 photos at their size, in wall and in CPU seconds."""
    scene = rt.encode(photos)
    pose = scene.world_from_cam[1]
    out = {}
    for name, kw in (("exact_model_size", dict(quality="exact")),
                     ("default_256", dict(height=256, width=256)),
                     ("fast_256", dict(height=256, width=256, quality="fast"))):
        rt.render(scene, pose, **kw)                              # warm-up (sessions, levels)
        out[name + "_s"], out[name + "_cpu_s"] = _cpu_timed(lambda: rt.render(scene, pose, **kw),
                                                            runs)
    for name in ("default_256", "fast_256"):
        out[name + "_ratio"] = out[name + "_s"] / out["exact_model_size_s"]
        out[name + "_cpu_ratio"] = out[name + "_cpu_s"] / out["exact_model_size_cpu_s"]
    out["default_quality"] = rt.default_quality
    return out


def summarise(sets: dict) -> dict:
    """Per set, size and configuration: the means over scenes."""
    out = {}
    for set_name, scenes in sets.items():
        per = {}
        for scene in scenes.values():
            for n, row in scene["sizes"].items():
                for name, m in row.items():
                    for k, v in m.items():
                        per.setdefault(n, {}).setdefault(name, {}).setdefault(k, []).append(v)
        out[set_name] = {n: {name: {k: float(np.mean(v)) for k, v in m.items()}
                             for name, m in row.items()} for n, row in per.items()}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model_dir")
    ap.add_argument("--sets", nargs="*",
                    default=["synthetic:heldout", "data/real/castle", "data/real/cube",
                             "data/real/castel"])
    ap.add_argument("--scenes", type=int, default=4, help="scenes per set (default 4)")
    ap.add_argument("--sizes", type=int, nargs="+", default=[128, 256, 512])
    ap.add_argument("--exact-up-to", type=int, default=512,
                    help="march the exact reference up to this size (it costs (N/64)^2 frames)")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--speed-set", default="data/real/castle",
                    help="set whose first scene times the bars' ratios ('' to skip)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    rt = IrisRuntime(args.model_dir, threads=args.threads)
    result = {"model": str(args.model_dir), "threads": args.threads, "configs": dict(
        (n, {k: v for k, v in kw.items()}) for n, kw in CONFIGS), "sets": {}}
    for set_name in args.sets:
        result["sets"][set_name] = {}
        for name, photos in load_set(set_name, args.scenes):
            t0 = time.perf_counter()
            result["sets"][set_name][name] = measure_scene(rt, photos, args.sizes, args.runs,
                                                           args.exact_up_to)
            print(f"{set_name} {name}: {time.perf_counter() - t0:.0f} s", flush=True)
    if args.speed_set:
        photos = load_set(args.speed_set, 1)[0][1]
        result["speed"] = speed(rt, photos, max(args.runs, 5))
        print(json.dumps(result["speed"]), flush=True)
    result["summary"] = summarise(result["sets"])
    for set_name, sizes in result["summary"].items():
        for n, row in sizes.items():
            cells = ", ".join(f"{name} {m.get('psnr', float('nan')):.2f}/"
                              f"{m.get('psnr_vs_exact', float('nan')):.1f} {m['s']:.2f}s"
                              for name, m in row.items())
            print(f"{set_name} {n}: {cells}")
    if args.json:
        atomic_write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
