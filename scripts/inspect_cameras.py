"""Print the cameras a checkpoint predicts on held-out scenes, and their RPA against the truth.

    python scripts/inspect_cameras.py models/iris-tiny-rgb.pt [--scenes 8]

Used for the model card's evidence that the shipped model's cameras are collapsed.
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from iris_train import load_model, read_checkpoint
from iris_train.data import HELDOUT_SEEDS, SyntheticScenes
from iris_train.metrics import rpa


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint")
    parser.add_argument("--scenes", type=int, default=8)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print("step", read_checkpoint(args.checkpoint).get("step"))
    model = load_model(args.checkpoint)
    scenes = SyntheticScenes(HELDOUT_SEEDS[:args.scenes])
    results = []
    for i in range(len(scenes)):
        data = scenes[i]
        images = torch.from_numpy(data.images).permute(0, 3, 1, 2).float() / 255
        with torch.no_grad():
            scene = model.encode(images)
        poses = scene.world_from_cam.double().numpy()
        results.append(rpa(poses, data.world_from_cam))
        if i < 2:
            print(f"scene {HELDOUT_SEEDS[i]}: camera centres {poses[:, :3, 3].round(3).tolist()}, "
                  f"focal {scene.focal.numpy().round(3).tolist()}")
    print({k: round(float(np.mean([r[k] for r in results])), 4) for k in results[0]})


if __name__ == "__main__":
    main()
