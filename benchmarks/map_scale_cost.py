"""What finer field maps (``ModelConfig.map_scale``) and the colour-deviation input cost, in torch,
one thread: a training step's forward and backward for one scene, and a 32x32 frame rendered
without gradients, each as CPU seconds (``time.process_time``: valid beside other jobs on a
shared machine), median of ``--repeats``, and the ratio to map_scale 1.

    OMP_NUM_THREADS=1 python benchmarks/map_scale_cost.py --json benchmarks/results/map_scale_cost.json

The training step is the shape of B1's recipe (docs/TRAINING.md): 8 views at 64x64, 5 of them
references with colours at 256x256, 3 targets x 192 rays of 24 samples. Random weights: the
cost does not depend on them.
"""
from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import torch  # noqa: E402

from iris_runtime.fileio import atomic_write_json  # noqa: E402
from iris_train.config import preset  # noqa: E402
from iris_train.model import Scene, build_model  # noqa: E402

SETTINGS = {"map_scale 1": {}, "map_scale 2": {"map_scale": 2}, "map_scale 4": {"map_scale": 4},
            "colour_deviation": {"colour_deviation": True},
            "map_scale 2 + colour_deviation": {"map_scale": 2, "colour_deviation": True}}


def _step(model, images, colours, rays, depths) -> float:
    t = time.process_time()
    features, cams, focal = model.encode_batch(images)
    scene = Scene(model.field.prepare(features[0, :5]), cams[0, :5], focal[0], (64, 64), colours)
    rgb, _ = model.render_rays(scene, *rays, depths)
    rgb.mean().backward()
    return time.process_time() - t


def _frame(model, images) -> float:
    t = time.process_time()
    with torch.no_grad():
        scene = model.encode(images)
        model.render(scene, scene.world_from_cam[1:2], 32, 32)
    return time.process_time() - t


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    images = torch.rand(1, 8, 3, 64, 64, generator=g)
    colours = torch.rand(5, 3, 256, 256, generator=g)
    R = 3 * 192
    origins = torch.zeros(R, 3)
    directions = torch.nn.functional.normalize(
        torch.randn(R, 3, generator=g) * 0.2 + torch.tensor([0.0, 0.0, 1.0]), dim=-1)
    depths = torch.linspace(0.1, 1.0, 24).expand(R, 24).contiguous()
    results = {}
    for name, change in SETTINGS.items():
        torch.manual_seed(0)
        model = build_model(dataclasses.replace(preset("tiny-rgb"), blend_angle=0.01, **change))
        step = [_step(model, images, colours, (origins, directions), depths)
                for _ in range(args.repeats + 1)][1:]
        frame = [_frame(model.eval(), images[0, :5]) for _ in range(args.repeats + 1)][1:]
        results[name] = {"train_step_s": statistics.median(step),
                         "frame_32_s": statistics.median(frame)}
    base = results["map_scale 1"]
    for name, r in results.items():
        r["train_step_ratio"] = r["train_step_s"] / base["train_step_s"]
        r["frame_32_ratio"] = r["frame_32_s"] / base["frame_32_s"]
        print(f"{name:32s} step {r['train_step_s']:.3f} s ({r['train_step_ratio']:.2f}x)  "
              f"frame {r['frame_32_s']:.3f} s ({r['frame_32_ratio']:.2f}x)")
    if args.json:
        atomic_write_json(args.json, {"repeats": args.repeats, "threads": 1, "settings": results})


if __name__ == "__main__":
    main()
