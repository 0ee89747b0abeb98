"""Turn a training checkpoint into a shippable one: weights, config and training facts, without
the optimiser state (a third of the size; `iris-train --resume` needs the full one).

    python scripts/ship_checkpoint.py runs/L1/last.pt models/iris-tiny-rgb.pt
    python scripts/ship_checkpoint.py runs/hd/x/last.pt out.pt --train-config-from models/iris-tiny-rgb.pt
    python scripts/ship_checkpoint.py G1.pt out.pt --camera-head-from runs/hd/x/last.pt

``--train-config-from``: the renderer's training record (``train_config``: the cameras it was
trained with, which the export's default follows) from the checkpoint the run started from, for a
camera-head run (``scripts/head_distill.py``) that left the renderer untouched and did not keep it.

``--camera-head-from``: the cameras of another checkpoint of the same model (a camera-head run
from this one): its camera head, and its encoder as the camera head's own
(``ModelConfig.camera_encoder``); the renderer, its encoder and its training record stay the
source's. A camera-head run moves the encoder the renderer reads (at a third of the head's rate),
and so the renders; this keeps the renders of the source bit for bit and the cameras of the run.

``--blend-sharpness G`` (explicit colour): the per-sample logits of the colour blend (and of the
soft depth) multiplied by G, i.e. the blend's softmax at temperature 1/G: G > 1 commits each
ray's colour to fewer depths. Exact as a weight edit (the last linear layer of the logits is
scaled); the checkpoint records G as ``blend_sharpness``.
"""
from __future__ import annotations

import argparse
import dataclasses
import math

from iris_train import build_model, read_checkpoint
from iris_train.config import ModelConfig
from iris_train.model import save_checkpoint

KEEP = ("step", "elapsed", "train_config", "distill", "blend_sharpness")
#: The linear layer whose output is the colour blend's per-sample logits (``--blend-sharpness``).
BLEND_LOGIT = "renderer.sample_logit."
HEAD_FIELDS = ("camera_head", "correlation_scale", "camera_encoder")
#: Settings of the renderer alone: a head from a model that differs in them still merges.
RENDERER_FIELDS = ("blend_angle", "map_scale", "colour_deviation", "far", "samples", "median_depth")


def with_cameras_of(payload: dict, cameras: dict, error) -> dict:
    """``payload`` (a checkpoint dict) with the camera head of ``cameras`` and, as its own
    encoder, the encoder ``cameras``' head reads; ``error(message)`` where the two models differ
    in anything but the camera head."""
    config, theirs = (ModelConfig.from_dict(p["config"]) for p in (payload, cameras))
    head = {k: getattr(theirs, k) for k in HEAD_FIELDS}
    # The renderer's own settings (the colour blend's weighting, the field maps' grid, the
    # colour deviation input, the sampled depth range) are kept from the renderer.
    renderer = {k: getattr(config, k) for k in RENDERER_FIELDS}
    if dataclasses.replace(config, **head) != dataclasses.replace(theirs, **renderer):
        error(f"--camera-head-from: another model (only the camera head's settings and "
              f"{', '.join(RENDERER_FIELDS)} may differ)")
    # The head's translations are in its cameras' unit: the renderer's must be the same.
    if config.unit_range != theirs.unit_range:
        error(f"--camera-head-from: the cameras' unit differs (the solve's depth range "
              f"{theirs.unit_range} against the renderer's {config.unit_range})")
    encoder = "camera_encoder." if theirs.camera_encoder else "encoder."
    state = {k: v for k, v in payload["model"].items()
             if not k.startswith(("camera_head.", "camera_encoder."))}
    for k, v in cameras["model"].items():
        if k.startswith("camera_head."):
            state[k] = v
        elif k.startswith(encoder):
            state["camera_encoder." + k[len(encoder):]] = v
    out = dict(payload, config=dataclasses.replace(config, **(head | {"camera_encoder": True})).to_dict(),
               model=state)
    if "distill" in cameras:
        out["distill"] = cameras["distill"]
    return out


def with_blend_sharpness(payload: dict, sharpness: float, error) -> dict:
    """``payload`` with its colour blend's logits multiplied by ``sharpness`` (> 0, finite);
    ``error(message)`` for another value or a model without explicit colour."""
    if not (math.isfinite(sharpness) and sharpness > 0):
        error(f"--blend-sharpness: expected a finite number > 0, got {sharpness}")
    if not ModelConfig.from_dict(payload["config"]).explicit_rgb:
        error("--blend-sharpness: the model has no colour blend (explicit_rgb is off)")
    state = {k: v * sharpness if k.startswith(BLEND_LOGIT) else v
             for k, v in payload["model"].items()}
    previous = float(payload.get("blend_sharpness", 1.0))
    return dict(payload, model=state, blend_sharpness=previous * sharpness)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source")
    parser.add_argument("dest")
    parser.add_argument("--train-config-from", default=None, metavar="CKPT")
    parser.add_argument("--camera-head-from", default=None, metavar="CKPT")
    parser.add_argument("--blend-sharpness", type=float, default=None, metavar="G",
                        help="multiply the colour blend's logits by G > 0 (explicit colour)")
    args = parser.parse_args()
    payload = read_checkpoint(args.source)
    if args.camera_head_from:
        payload = with_cameras_of(payload, read_checkpoint(args.camera_head_from), parser.error)
    if args.train_config_from:
        if "train_config" in payload:
            parser.error(f"{args.source} has its own train_config")
        payload["train_config"] = read_checkpoint(args.train_config_from)["train_config"]
    if args.blend_sharpness is not None:
        payload = with_blend_sharpness(payload, args.blend_sharpness, parser.error)
    model = build_model(ModelConfig.from_dict(payload["config"]))
    model.load_state_dict(payload["model"])
    save_checkpoint(args.dest, model, **{k: payload[k] for k in KEEP if k in payload})
    print(f"{args.dest}: step {payload.get('step')}, {sum(p.numel() for p in model.parameters())} parameters")


if __name__ == "__main__":
    main()
