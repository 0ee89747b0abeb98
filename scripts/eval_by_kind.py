"""Per-kind means of ``iris-eval`` results: PSNR / depth rho of each scene kind (walk, orbit,
handheld, indoor, or the classic scenes' name), beside the overall means, one row per file.

    python scripts/eval_by_kind.py b1.json run.json [--order rand] [--metrics psnr depth_spearman]

The capture-like sets mix kinds whose figures differ by 6 dB; a change that helps one kind and
costs another shows here, not in the overall mean (docs/TRAINING.md's tables).
"""
from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path


def by_kind(result: dict, metrics: list[str]) -> dict[str, dict[str, float]]:
    """``{kind: {metric: mean}}`` over the scenes of one order of an iris-eval result, with
    ``"all"`` the mean over every scene and ``"n"`` each group's scene count."""
    groups: dict[str, list[dict]] = defaultdict(list)
    for scene in result["scenes"]:
        groups[scene["name"]].append(scene["model"])
        groups["all"].append(scene["model"])
    table = {}
    for kind, rows in groups.items():
        table[kind] = {m: sum(r[m] for r in rows) / len(rows) for m in metrics}
        table[kind]["n"] = len(rows)
    return table


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results", nargs="+", type=Path, help="iris-eval --json files")
    parser.add_argument("--order", default="rand", choices=("rand", "seq"))
    parser.add_argument("--metrics", nargs="+", default=["psnr", "depth_spearman"])
    args = parser.parse_args(argv)
    tables = {path: by_kind(json.loads(path.read_text())[args.order], args.metrics)
              for path in args.results}
    kinds = ["all"] + sorted({k for t in tables.values() for k in t} - {"all"})
    print("| file | " + " | ".join(f"{k} ({tables[args.results[0]].get(k, {}).get('n', '?')})"
                                    for k in kinds) + " |")
    print("|---" * (len(kinds) + 1) + "|")
    for path, table in tables.items():
        cells = [" / ".join(f"{table[k][m]:.3f}" if m != "psnr" else f"{table[k][m]:.2f}"
                            for m in args.metrics) if k in table else "-" for k in kinds]
        print(f"| {path.stem} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
