"""Contact sheet of capture-kind scenes (issue: look at what the generator makes).

    python scripts/data_contact_sheet.py docs/images/data-v2.png --scenes 24 --size 128

One row per scene (its 8 views in trajectory order), scenes cycling through the capture kinds
(``kind="capture"``), seeds from ``--first``. Each row is labelled with the kind, the vertical
field of view, the median valid depth and whether the scene is grey; ``--clean`` shows the
renders without the photometric camera effects. Also prints per-kind depth statistics (median,
1st and 99th percentiles of valid depth) as JSON.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from iris_train.synthetic import render_scene


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--scenes", type=int, default=24)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--views", type=int, default=8)
    ap.add_argument("--first", type=int, default=0, help="first seed")
    ap.add_argument("--columns", type=int, default=2, help="scenes side by side")
    ap.add_argument("--clean", action="store_true", help="without photometric effects")
    a = ap.parse_args(argv)
    rows, depths = [], {}
    label_w = 150
    for seed in range(a.first, a.first + a.scenes):
        s = render_scene(seed, a.views, (a.size, a.size), kind="capture", clean=a.clean)
        z = s.depth[s.depth > 0]
        kind = s.meta["kind"]
        depths.setdefault(kind, []).append(z)
        strip = np.full((a.size, label_w, 3), 255, np.uint8)
        grey = bool(np.all(s.images[..., 0] == s.images[..., 1]))
        for k, text in enumerate([f"{seed} {kind}", f"fov {s.meta['yfov_deg']:.0f}",
                                  f"z50 {np.median(z):.2f}", f"{s.meta.get('arc_deg', 0):.0f}deg" if
                                  'arc_deg' in s.meta else f"pan {s.meta.get('pan_deg', 0):.0f}",
                                  "grey" if grey else ""]):
            cv2.putText(strip, text, (4, 18 + 20 * k), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1,
                        cv2.LINE_AA)
        rows.append(np.concatenate([strip, *s.images], axis=1))
    per = -(-len(rows) // a.columns)
    blank = np.full_like(rows[0], 255)
    cols = [np.concatenate(rows[c * per:(c + 1) * per] + [blank] * (per - len(rows[c * per:(c + 1) * per])), 0)
            for c in range(a.columns)]
    sep = np.full((cols[0].shape[0], 8, 3), 255, np.uint8)
    sheet = np.concatenate([x for c in cols for x in (c, sep)][:-1], axis=1)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    from PIL import Image
    # A 256-colour palette with dithering keeps the sheet a few MB instead of ~6.
    Image.fromarray(sheet).quantize(256, method=Image.Quantize.MEDIANCUT,
                                    dither=Image.Dither.FLOYDSTEINBERG).save(a.out, optimize=True)
    stats = {k: {"scenes": len(v), "median": float(np.median(np.concatenate(v))),
                 "p1": float(np.percentile(np.concatenate(v), 1)),
                 "p99": float(np.percentile(np.concatenate(v), 99)),
                 "scene_medians": [round(float(np.median(x)), 3) for x in v]} for k, v in depths.items()}
    print(json.dumps(stats, indent=1))


if __name__ == "__main__":
    main()
