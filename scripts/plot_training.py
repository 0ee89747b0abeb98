"""Plot the training curves of one or more iris-train runs from their log.jsonl files.

    python scripts/plot_training.py models/iris-tiny-rgb.log.jsonl -o models/iris-tiny-rgb-loss.png

Left: training PSNR of the learned renderer (its own term when the log has per-term values, else
the whole loss). Right, for runs with the epipolar teacher: the teacher's rotation term as an
angle (arccos(1 - loss), degrees) and its translation-direction term; for runs on the solved
cameras (``--render-cameras solve``) the head's rotation against them and the centre term. Curves are smoothed with a
moving average over 10 log rows.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def _smooth(x, n=10):
    x = np.asarray(x, dtype=float)
    if len(x) < n:
        return x
    return np.convolve(x, np.ones(n) / n, mode="valid")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("logs", nargs="+", type=Path)
    parser.add_argument("-o", "--out", type=Path, required=True)
    args = parser.parse_args()
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 3.5), dpi=100)
    for log in args.logs:
        rows = [json.loads(line) for line in log.read_text().splitlines() if line.strip()]
        steps = [r["step"] for r in rows]
        render = [r["terms"]["render"] if "terms" in r else r["loss"] for r in rows]
        s = _smooth(steps)
        ax.plot(s, [-10 * math.log10(max(v, 1e-10)) for v in _smooth(render)], label=log.name)
        if rows and "teacher_rot" in rows[0].get("terms", {}):
            rot = [math.degrees(math.acos(max(-1.0, 1 - r["terms"]["teacher_rot"]))) for r in rows]
            ax2.plot(s, _smooth(rot), label=f"{log.name}: rotation (deg)")
            ax2.plot(s, 10 * _smooth([r["terms"]["teacher_dir"] for r in rows]),
                     label=f"{log.name}: direction term x10")
        if rows and "solve_rot" in rows[0].get("terms", {}):
            # --render-cameras solve: the head against the scene's solved cameras.
            rot = [math.degrees(math.acos(max(-1.0, 1 - r["terms"]["solve_rot"]))) for r in rows]
            ax2.plot(s, _smooth(rot), label=f"{log.name}: rotation vs solve (deg)")
            ax2.plot(s, 100 * _smooth([r["terms"]["solve_trans"] for r in rows]),
                     label=f"{log.name}: centre term x100")
    ax.set_xlabel("step")
    ax.set_ylabel("training PSNR of the render term (dB)")
    ax2.set_xlabel("step")
    ax2.set_ylabel("camera-head terms (teacher / solve)")
    for a in (ax, ax2):
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
