"""``iris-eval`` with the default preset's depth search set otherwise: the probes behind
``iris_runtime.detail``'s search constants (docs/PERFORMANCE.md, "Depth from the photos").

    python benchmarks/depth_search.py --span 4 --steps 1 0.5 --spread 5e-4 --share 0.05 -- \\
        out/model synthetic:heldout --scenes 5 --size 256 --cameras true --threads 1 --json r.json
    python benchmarks/depth_search.py --span 0 -- out/model synthetic:heldout --size 256 ...
                                                       # auto without its search

``--span``: the bins a sample may move (``RenderSettings.depth_search`` of ``auto``; 0: off);
``--steps``: ``detail.SEARCH_STEPS``; ``--spread``: ``detail.SEARCH_SPREAD``; ``--share``:
``detail.SEARCH_SHARE``; ``--prior``: ``detail.SEARCH_PRIOR``. Unset: the shipped values. The
arguments after ``--`` are iris-eval's (an exported model: the search is the runtime's).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ours, rest = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv \
        else (argv, [])
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--span", type=int, help="bins a sample may move (auto's depth_search)")
    p.add_argument("--steps", type=float, nargs="+", help="detail.SEARCH_STEPS, in bins")
    p.add_argument("--spread", type=float, help="detail.SEARCH_SPREAD")
    p.add_argument("--share", type=float, help="detail.SEARCH_SHARE")
    p.add_argument("--prior", type=float, help="detail.SEARCH_PRIOR")
    args = p.parse_args(ours)
    if not rest:
        p.error("give iris-eval's arguments after --")

    from iris_runtime import detail, quality
    for name, value in (("SEARCH_SPREAD", args.spread), ("SEARCH_SHARE", args.share),
                        ("SEARCH_PRIOR", args.prior)):
        if value is not None:
            setattr(detail, name, value)
    if args.steps:
        detail.SEARCH_STEPS = tuple(args.steps)
    if args.span is not None:
        quality.QUALITY_PRESETS["auto"] = dataclasses.replace(quality.QUALITY_PRESETS["auto"],
                                                              depth_search=args.span)
    print(f"depth search: span {quality.QUALITY_PRESETS['auto'].depth_search} bins, steps "
          f"{detail.SEARCH_STEPS}, spread >= {detail.SEARCH_SPREAD}, share >= "
          f"{detail.SEARCH_SHARE}, prior {detail.SEARCH_PRIOR}", flush=True)
    from iris_train.evaluate import main as evaluate
    return evaluate(rest)


if __name__ == "__main__":
    sys.exit(main())
