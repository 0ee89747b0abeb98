"""The camera head's data curve: held-out RPA against the number of teacher scenes it was
distilled on, at equal steps (docs/TRAINING.md, "The data curve").

    python scripts/plot_data_curve.py docs/images/data_curve.png \\
        500=docs/logs/data-curve-c500.log.jsonl 7000=docs/logs/data-curve-c7000.log.jsonl \\
        [--fit 500=benchmarks/results/data_curve/fit_c500.json ...]

Each ``N=LOG`` is a ``scripts/head_distill.py`` log of a run on N classic teacher scenes. Left:
held-out RPA@15 and @30 at the run's last evaluation against N (log scale), with the fit to
the teacher on training scenes (``scripts/heldout_rpa.py --fit 20 --json``) where given. Right:
held-out RPA@15 along each run, so that a curve still rising at the end is seen as such.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def _pairs(items: list[str]) -> dict[int, Path]:
    out = {}
    for item in items:
        n, _, path = item.partition("=")
        if not path or not n.isdigit():
            raise SystemExit(f"expected N=PATH, got {item!r}")
        out[int(n)] = Path(path)
    return dict(sorted(out.items()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("logs", nargs="+", metavar="N=LOG")
    ap.add_argument("--fit", nargs="*", default=[], metavar="N=JSON")
    args = ap.parse_args(argv)
    logs = {n: [json.loads(line) for line in p.read_text().splitlines() if line.strip()]
            for n, p in _pairs(args.logs).items()}
    fits = {n: json.loads(p.read_text()) for n, p in _pairs(args.fit).items()}
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    ns = list(logs)
    for key, style in (("rpa@15", "o-"), ("rpa@30", "s--")):
        ax.plot(ns, [rows[-1]["heldout"][key] for rows in logs.values()], style,
                label=f"held-out {key.upper()}")
    if fits:
        ax.plot(list(fits), [f["train_fit"]["rpa@15"] for f in fits.values()], "^:",
                label="fit to the teacher, RPA@15 (20 training scenes)")
    ax.set_xscale("log")
    ax.set_xticks(ns, [str(n) for n in ns])
    ax.minorticks_off()
    ax.set_xlabel("teacher scenes (classic, solved cameras)")
    ax.set_ylabel("RPA")
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title(f"head alone after {logs[ns[0]][-1]['step']} steps")
    for n, rows in logs.items():
        ax2.plot([r["step"] for r in rows], [r["heldout"]["rpa@15"] for r in rows], "o-",
                 label=f"{n} scenes")
    ax2.set_xlabel("step")
    ax2.set_ylabel("held-out RPA@15")
    ax2.grid(alpha=0.3)
    ax2.legend(fontsize=8)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
