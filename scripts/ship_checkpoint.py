"""Turn a training checkpoint into a shippable one: weights, config and training facts, without
the optimiser state (a third of the size; `iris-train --resume` needs the full one).

    python scripts/ship_checkpoint.py runs/L1/last.pt models/iris-tiny-rgb.pt
    python scripts/ship_checkpoint.py runs/hd/x/last.pt out.pt --train-config-from models/iris-tiny-rgb.pt

``--train-config-from``: the renderer's training record (``train_config``: the cameras it was
trained with, which the export's default follows) from the checkpoint the run started from, for a
camera-head run (``scripts/head_distill.py``) that left the renderer untouched and did not keep it.
"""
from __future__ import annotations

import argparse

from iris_train import build_model, read_checkpoint
from iris_train.config import ModelConfig
from iris_train.model import save_checkpoint

KEEP = ("step", "elapsed", "train_config", "distill")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source")
    parser.add_argument("dest")
    parser.add_argument("--train-config-from", default=None, metavar="CKPT")
    args = parser.parse_args()
    payload = read_checkpoint(args.source)
    if args.train_config_from:
        if "train_config" in payload:
            parser.error(f"{args.source} has its own train_config")
        payload["train_config"] = read_checkpoint(args.train_config_from)["train_config"]
    model = build_model(ModelConfig.from_dict(payload["config"]))
    model.load_state_dict(payload["model"])
    save_checkpoint(args.dest, model, **{k: payload[k] for k in KEEP if k in payload})
    print(f"{args.dest}: step {payload.get('step')}, {sum(p.numel() for p in model.parameters())} parameters")


if __name__ == "__main__":
    main()
