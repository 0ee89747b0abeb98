"""How far a pose moved by float32 rounding moves the render, per validity-fade setting, and how
far the runtime is from torch end to end.

    python benchmarks/pose_sensitivity.py MODEL_DIR [--checkpoint models/iris-tiny-rgb.pt
        --scenes 4 --settings 10x1,100x0.5,10x0.5,10x2,2x1,hard]

``MODEL_DIR`` is an iris-export output of ``--checkpoint``. Held-out scenes
(``iris_train.data.HELDOUT_SEEDS``), all 8 frames encoded, the targets of ``evaluate.split_frames``
rendered from the references at their predicted poses (the knobs part of
``benchmarks/error_vs_time.py``), 64x64. Per scene, max abs over the targets (rgb in [0, 1]):

- ``GxF`` (``layers.FADE_GAIN`` x ``geometry.EDGE_FADE`` pixels; ``hard``: a fade of 1e-9 pixel
  and a gain of 1e6, the hard mask): torch's render with the ONNX encoder's cameras (reference
  poses, focal and target pose) against its render with its own. The two encoders' cameras
  differ by float32 rounding (~2e-7), so this is the render's sensitivity to that rounding: a
  hard validity edge turns it into a jump, a fade into a slope of about FADE_GAIN / EDGE_FADE.
- ``torch32 vs 64``: torch float32 against torch float64 (each with its own cameras), at the
  shipped setting: what float32 itself allows.
- ``runtime vs torch``: ``IrisRuntime(MODEL_DIR)``'s exact render against torch's, each with its
  own encoder (the benchmark's torch parity), at the exported setting.
- ``runtime vs 64``: the same runtime render against torch float64: how close each float32 path
  comes to the float64 answer (compare ``torch32 vs 64``).
- ``pool gap``: the largest gap between the first and second view's max-pool input (u, per
  channel, over the samples seen by two views or more): ``FADE_GAIN`` must exceed it, or a view
  fading out would still lead the pool when its bias jumps from -FADE_GAIN to MASK_FILL.

Needs torch (the [train] extra). The constants are set on the torch modules for each setting
(module globals read at call time); the runtime runs the exported graph as it is.
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402


def parse_setting(text: str) -> tuple[str, float, float]:
    if text == "hard":
        return text, 1e6, 1e-9
    gain, fade = text.split("x")
    return text, float(gain), float(fade)


def max_pool_gap(model, scene, world_from_cam) -> float:
    """The largest top-1 minus top-2 gap over views of the field's max-pool input u at the
    samples of a render of ``scene`` from ``world_from_cam [4, 4]`` (torch, no grad)."""
    import torch
    import iris_train.geometry as TG
    from iris_train.model import SAMPLERS, sampler_for
    H, W = scene.image_size
    o, d = TG.rays_from_pixels(TG.pixel_centres(H, W), scene.intrinsics(), world_from_cam)
    depths = TG.sample_depths(model.cfg.near, model.cfg.far, model.cfg.samples, o.shape[0])
    s = scene.project_samples(o, d, depths)
    sampled = SAMPLERS[sampler_for(*s.field_maps.shape[-2:])](s.field_maps, s.grid)
    if s.colours is not None:
        sampled = sampled + model.field.rgb_to_maps(s.colours - 0.5)
    u = sampled[..., :model.cfg.field_width]                                  # [V, R, S, W]
    filled = torch.where((s.mask > 0)[..., None], u, torch.tensor(-torch.inf, dtype=u.dtype))
    top2 = filled.topk(2, dim=0).values
    seen_twice = torch.isfinite(top2[1])
    return float((top2[0] - top2[1])[seen_twice].max()) if bool(seen_twice.any()) else 0.0


def main(argv=None) -> int:
    import torch
    import iris_train.geometry as TG
    import iris_train.layers as L
    from iris_runtime import IrisRuntime
    from iris_train.data import HELDOUT_SEEDS, SyntheticScenes
    from iris_train.evaluate import split_frames
    from iris_train.model import load_model

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model_dir", type=Path)
    ap.add_argument("--checkpoint", type=Path, default=REPO / "models" / "iris-tiny-rgb.pt")
    ap.add_argument("--scenes", type=int, default=4)
    ap.add_argument("--settings", default="10x1,100x0.5,10x0.5,10x2,2x1,hard")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    settings = [parse_setting(s) for s in args.settings.split(",")]
    shipped = (L.FADE_GAIN, TG.EDGE_FADE)
    model = load_model(args.checkpoint)
    model64 = copy.deepcopy(model).double()
    rt = IrisRuntime(args.model_dir, threads=args.threads)
    refs, targets = (list(x) for x in split_frames(8))
    print(f"shipped setting: FADE_GAIN {shipped[0]:g}, EDGE_FADE {shipped[1]:g} px; "
          f"{len(targets)} targets per scene, max abs rgb")
    columns = [name for name, _, _ in settings] + ["torch32 vs 64", "runtime vs torch",
                                                    "runtime vs 64", "pool gap"]
    print("| scene | camera diff | " + " | ".join(columns) + " |")
    print("|---" * (len(columns) + 2) + "|")
    worst = dict.fromkeys(columns, 0.0)
    for seed in list(HELDOUT_SEEDS)[:args.scenes]:
        scene = SyntheticScenes([seed], n_views=8)[0]
        enc = rt.encode(list(scene.images), cameras="model")
        x = torch.from_numpy(np.ascontiguousarray(scene.images)).permute(0, 3, 1, 2) / 255.0
        row = {}
        with torch.no_grad():
            sc = model.encode(x.float())
            sc64 = model64.encode(x.double())
            ort_cams = dataclasses.replace(
                sc, world_from_cam=torch.from_numpy(enc.world_from_cam.copy()).float(),
                focal=torch.from_numpy(enc.focal.copy()).float())
            cam_diff = float((ort_cams.world_from_cam - sc.world_from_cam).abs().max())
            for name, gain, fade in settings:
                L.FADE_GAIN, TG.EDGE_FADE = gain, fade
                row[name] = max(float((model.render(sc.subset(refs), sc.world_from_cam[[t]],
                                                    64, 64)[0]
                                       - model.render(ort_cams.subset(refs),
                                                      ort_cams.world_from_cam[[t]], 64, 64)[0]
                                       ).abs().max()) for t in targets)
            L.FADE_GAIN, TG.EDGE_FADE = shipped
            sub, sub64 = sc.subset(refs), sc64.subset(refs)
            row["pool gap"] = max(max_pool_gap(model, sub, sc.world_from_cam[t]) for t in targets)
            r32 = [model.render(sub, sc.world_from_cam[[t]], 64, 64)[0][0].double().numpy()
                   for t in targets]
            r64 = [model64.render(sub64, sc64.world_from_cam[[t]], 64, 64)[0][0].numpy()
                   for t in targets]
        ort_sub = enc.subset(refs)
        rts = [rt.render(ort_sub, enc.world_from_cam[t], depth=True).image_float
               .astype(np.float64) for t in targets]
        for name, got, want in (("torch32 vs 64", r32, r64), ("runtime vs torch", rts, r32),
                                ("runtime vs 64", rts, r64)):
            row[name] = max(float(np.abs(a - b).max()) for a, b in zip(got, want))
        for k in columns:
            worst[k] = max(worst[k], row[k])
        print(f"| {seed} | {cam_diff:.1e} | " + " | ".join(f"{row[k]:.1e}" for k in columns)
              + " |", flush=True)
    print("| worst | | " + " | ".join(f"{worst[k]:.1e}" for k in columns) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
