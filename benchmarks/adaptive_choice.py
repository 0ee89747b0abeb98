"""Why the "adaptive" preset is what it is: errors of the coarse-to-fine knobs (no timings).

    python benchmarks/adaptive_choice.py --model-dir MODEL [--scenes 4] [--out FILE.json]

Everything here is an error or a work count, which do not depend on the machine's load (the
timings are benchmarks/error_vs_time.py's). On the held-out scenes' targets at the model's
resolution (the knobs part's frames), against the exact render and the ground truth:

- **Which pixels to refine.** The coarse pass (``coarse`` = 1/4: the render at a quarter of the
  rows and columns, exactly as ``IrisRuntime.render`` marches it), upsampled bicubically; then
  the ``budget`` fraction of the pixels with the highest score replaced by the exact render.
  Scores: ``range+depth`` (``adaptive.untrusted``, the shipped one), its colour and depth halves
  alone, the disagreement of the bicubic and bilinear upsamplings, the coarse image's
  difference from its 3x3 blur, and the oracle (the true error of the upsampled pixel, which a
  renderer cannot know: the bound). Also: the coarse pass upsampled bilinearly / bicubically
  with nothing refined.
- **How concentrated the renderer's weights are.** For ``depth_window`` w and ``depth_mass`` m,
  the rays a depth-guided render marches on a window (the others fall back to every sample), the
  samples they keep and the error (``IrisRuntime.render(depth_window=w, depth_mass=m)``, first
  scene only: each render costs about a full render when most rays fall back).
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

BUDGETS = (0.05, 0.1, 0.12, 0.15, 0.2, 0.3)
SCORES = ("range+depth", "range", "depth", "interpolators", "blur", "oracle")
WINDOWS = ((8, 0.5), (8, 0.9), (16, 0.5), (16, 0.9))


def scores(coarse_rgb, coarse_depth, up_cubic, up_linear, exact, size, depth_range) -> dict:
    """Every candidate score of the pixels of a ``size`` x ``size`` render, [size, size]."""
    import cv2

    from iris_runtime import adaptive
    h = coarse_rgb.shape[0]
    centre = adaptive._centre_index(size, h)
    blur = np.abs(coarse_rgb - cv2.GaussianBlur(coarse_rgb, (3, 3), 0)).max(axis=2)
    return {
        "range+depth": adaptive.untrusted(coarse_rgb, coarse_depth, size, size, depth_range),
        "range": adaptive.untrusted(coarse_rgb, np.zeros_like(coarse_depth), size, size,
                                    depth_range),
        "depth": adaptive.untrusted(np.zeros_like(coarse_rgb), coarse_depth, size, size,
                                    depth_range),
        "interpolators": np.abs(up_cubic - up_linear).max(axis=2),
        "blur": blur[centre[:, None], centre[None, :]],
        "oracle": ((up_cubic - exact) ** 2).sum(axis=2),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model-dir", type=Path, required=True, help="an iris-export output")
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", type=Path, default=REPO / "benchmarks" / "results" /
                    "adaptive_choice.json")
    args = ap.parse_args(argv)
    import cv2

    from benchmarks.evt.measure import gt_image, heldout_scenes, psnr
    from iris_runtime import IrisRuntime
    from iris_runtime import geometry as G
    from iris_runtime.adaptive import coarse_size
    from iris_runtime.fileio import atomic_write_text, sha256_file
    from iris_train.evaluate import split_frames

    rt = IrisRuntime(args.model_dir, threads=args.threads)
    refs, targets = split_frames(8)
    size = args.size
    h, w = coarse_size(size, size, 0.25)
    per = {}                                  # (what, budget) -> [(psnr vs full, gt delta)]
    depth_rows = []
    frame = 0
    for si, s in enumerate(heldout_scenes(args.scenes)):
        scene = rt.encode(list(s.images), cameras="model")
        sub = scene.subset(list(refs))
        for t in targets:
            pose = scene.world_from_cam[t]
            gt = gt_image(s.images[t], size)
            ex = rt.render(sub, pose, height=size, width=size, depth=True)
            exact = ex.image_float.astype(np.float64)
            exact_gt = psnr(np.clip(exact, 0, 1), gt)
            # The coarse pass exactly as the runtime marches it: the render's intrinsics scaled.
            K = G.scale_intrinsics(sub.intrinsics(size, size), (size, size), (h, w))
            co = rt.render(sub, pose, height=h, width=w, intrinsics=K, depth=True)
            rgb_c, depth_c = co.image_float, co.depth
            up = {m: np.clip(cv2.resize(rgb_c, (size, size), interpolation=i), 0, 1)
                  .astype(np.float64) for m, i in (("cubic", cv2.INTER_CUBIC),
                                                   ("linear", cv2.INTER_LINEAR))}
            for m, img in up.items():
                per.setdefault((f"coarse only, {m}", 0.0), []).append(
                    (psnr(img, exact), psnr(img, gt) - exact_gt))
            sc = scores(rgb_c, depth_c, up["cubic"], up["linear"], exact, size, rt.far - rt.near)
            for name, score in sc.items():
                order = np.argsort(-score.reshape(-1), kind="stable")
                for b in BUDGETS:
                    pick = order[:int(b * size * size + 0.5)]
                    out = up["cubic"].reshape(-1, 3).copy()
                    out[pick] = exact.reshape(-1, 3)[pick]
                    out = out.reshape(size, size, 3)
                    per.setdefault((name, b), []).append((psnr(out, exact),
                                                          psnr(out, gt) - exact_gt))
            # The shipped preset, through the runtime.
            res = rt.render(sub, pose, height=size, width=size, depth=True, quality="adaptive")
            o = res.image_float.astype(np.float64)
            per.setdefault(("preset adaptive", res.settings.refine_budget), []).append(
                (psnr(o, exact), psnr(np.clip(o, 0, 1), gt) - exact_gt))
            if si == 0:
                for win, mass in WINDOWS:
                    r = rt.render(sub, pose, height=size, width=size, depth=True,
                                  depth_window=win, depth_mass=mass)
                    o = r.image_float.astype(np.float64)
                    depth_rows.append({
                        "frame": frame, "depth_window": win, "depth_mass": mass,
                        "windowed_fraction": r.work["windowed_rays"] / r.work["pixels"],
                        "kept_sample_fraction": r.work["kept_samples"]
                        / (r.work["pixels"] * rt.samples),
                        "psnr_vs_full": psnr(o, exact), "max_abs_vs_full":
                        float(np.abs(o - exact).max()),
                        "psnr_gt_delta": psnr(np.clip(o, 0, 1), gt) - exact_gt})
            frame += 1
            print(f"frame {frame}: exact PSNR gt {exact_gt:.2f}", flush=True)
    rows = []
    for (name, b), v in per.items():
        v = np.array(v)
        rows.append({"what": name, "budget": b, "psnr_vs_full": float(v[:, 0].mean()),
                     "psnr_gt_delta": float(v[:, 1].mean()),
                     "psnr_gt_delta_worst_frame": float(v[:, 1].min())})
    depth = []
    for win, mass in WINDOWS:
        d = [r for r in depth_rows if (r["depth_window"], r["depth_mass"]) == (win, mass)]
        depth.append({"depth_window": win, "depth_mass": mass, **{
            k: float(np.mean([r[k] for r in d])) for k in
            ("windowed_fraction", "kept_sample_fraction", "psnr_vs_full", "psnr_gt_delta")},
            "max_abs_vs_full": max(r["max_abs_vs_full"] for r in d), "frames": len(d)})
    model = json.loads((args.model_dir / "iris.json").read_text()).get("source", {})
    out = {"model": model, "renderer_sha256": sha256_file(args.model_dir / "renderer.onnx"),
           "scenes": args.scenes, "frames": frame, "size": size, "coarse": [h, w],
           "refine": rows, "depth_guided": depth}
    atomic_write_text(args.out, json.dumps(out, indent=1))
    for r in rows:
        print(f"{r['what']:18s} {r['budget']:.2f}  PSNR vs full {r['psnr_vs_full']:6.2f}  "
              f"gt {r['psnr_gt_delta']:+.3f} (worst frame {r['psnr_gt_delta_worst_frame']:+.3f})")
    for r in depth:
        print(f"depth window {r['depth_window']:2d} mass {r['depth_mass']:.1f}: windowed "
              f"{100 * r['windowed_fraction']:.1f}%  samples kept "
              f"{100 * r['kept_sample_fraction']:.1f}%  PSNR vs full {r['psnr_vs_full']:.2f}  "
              f"gt {r['psnr_gt_delta']:+.3f}  "
              f"max abs {r['max_abs_vs_full']:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
