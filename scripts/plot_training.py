"""Plot training loss (EMA) of one or more iris-train runs from their log.jsonl files.

    python scripts/plot_training.py models/iris-tiny.log.jsonl models/iris-tiny-run1.log.jsonl -o models/iris-tiny-loss.png
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("logs", nargs="+", type=Path)
    parser.add_argument("-o", "--out", type=Path, required=True)
    args = parser.parse_args()
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    for log in args.logs:
        rows = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
        ax.plot([r["step"] for r in rows], [-10 * __import__("math").log10(r["loss_ema"]) for r in rows],
                label=log.name)
    ax.set_xlabel("step")
    ax.set_ylabel("training PSNR of the loss EMA (dB)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
