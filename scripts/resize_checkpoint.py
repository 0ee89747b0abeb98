"""Carry a trained checkpoint to k times its image size at the same token grid.

    python scripts/resize_checkpoint.py models/iris-tiny-rgb.pt runs/F1-128.pt --factor 2

The new model takes k times larger images with k times larger patches, so the encoder's token grid,
its cost and every weight except the patch embedding are unchanged. The patch kernel is each
original weight repeated over a k x k block and divided by k^2: the new encoder on an image equals
the old encoder on that image averaged over k x k blocks (what ``cv2.INTER_AREA`` does at an
integer factor), exactly up to float rounding (``tests/test_resize_checkpoint.py``). What changes
is everything per pixel: rays at the finer resolution, and an explicit-colour model samples its
reference colours from the finer photos. It is the starting point of a fine-tune at the new size
(``iris-train --init``), not a finished model.
"""
from __future__ import annotations

import argparse
import dataclasses

import torch

from iris_train import build_model, read_checkpoint
from iris_train.config import ModelConfig
from iris_train.model import save_checkpoint

KEEP = ("step", "elapsed", "train_config")


def resize_state(config: ModelConfig, state: dict, factor: int) -> tuple[ModelConfig, dict]:
    """``(config, state_dict)`` of a model at ``factor`` times the image and patch size."""
    if not isinstance(factor, int) or isinstance(factor, bool) or factor < 1:
        raise ValueError(f"factor: expected a positive integer, got {factor!r}")
    new_config = dataclasses.replace(config, image_height=config.image_height * factor,
                                     image_width=config.image_width * factor,
                                     patch_size=config.patch_size * factor)
    new_state = dict(state)
    kernel = state["encoder.patch_embed.weight"]                                 # [D, 3, p, p]
    new_state["encoder.patch_embed.weight"] = (
        kernel.repeat_interleave(factor, dim=2).repeat_interleave(factor, dim=3) / factor ** 2)
    return new_config, new_state


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source")
    parser.add_argument("dest")
    parser.add_argument("--factor", type=int, default=2, help="image and patch size multiplier")
    args = parser.parse_args()
    payload = read_checkpoint(args.source)
    config, state = resize_state(ModelConfig.from_dict(payload["config"]), payload["model"],
                                 args.factor)
    model = build_model(config)
    model.load_state_dict(state)
    save_checkpoint(args.dest, model, **{k: payload[k] for k in KEEP if k in payload},
                    resized_from={"image_size": [payload["config"]["image_height"],
                                                 payload["config"]["image_width"]],
                                  "factor": args.factor})
    print(f"{args.dest}: {config.image_height}x{config.image_width}, patch {config.patch_size}")


if __name__ == "__main__":
    with torch.no_grad():
        main()
