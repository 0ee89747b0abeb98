"""What ``iris-eval`` writes: the summary table, the per-scene table, the JSON and the PNG grid."""
from __future__ import annotations

import os
from typing import Sequence

import numpy as np

from iris_runtime.fileio import atomic_write_bytes, atomic_write_json
from iris_runtime.manifest import camera_name

from ..metrics import RPA_THRESHOLDS, depth_spearman
from .protocol import LOCATE_RPA_KEYS, ORDERS, RPA_KEYS, capped_psnr

__all__ = ["format_table", "format_scenes", "format_cameras", "write_json", "save_grid"]

#: Rows of the summary table: (label, where in an order's results).
_ROWS = (("IRIS", ("model",)), ("upsampled", ("baselines", "upsampled")),
         ("best reference", ("baselines", "best_reference")),
         ("nearest reference", ("baselines", "nearest_reference")),
         ("mean colour", ("baselines", "mean_colour")),
         ("identity poses", ("baselines", "identity_poses")))


def format_table(results: dict) -> str:
    """The results as a fixed-width text table (one row per order and method; "-" = not measured).
    DEPTH-RHO is ``depth_spearman``, LOC@t is ``locate_rpa@t``; "best reference" is the oracle
    photo baseline (``protocol.best_reference``), "nearest reference" the nearest camera's;
    "upsampled" (``--size`` only) the model-resolution render resized to the output size."""
    cols = ("psnr", "ssim", *RPA_KEYS, *LOCATE_RPA_KEYS, "depth_spearman")
    labels = {"depth_spearman": "DEPTH-RHO",
              **{k: f"LOC@{t:g}" for k, t in zip(LOCATE_RPA_KEYS, RPA_THRESHOLDS)}}
    width = {c: max(9, len(labels.get(c, c)) + 1) for c in cols}
    head = f"{'order':<6} {'method':<18}" + "".join(f"{labels.get(c, c.upper()):>{width[c]}}"
                                                     for c in cols)
    lines = [head, "-" * len(head)]
    for order in ORDERS:
        for name, where in _ROWS:
            values = results[order]
            for key in where:
                values = values.get(key, {})
            if not values:
                continue
            cells = []
            for c in cols:
                v, w = values.get(c), width[c]
                cells.append(f"{'-':>{w}}" if v is None else
                             f"{v:>{w}.2f}" if c == "psnr" else f"{v:>{w}.3f}")
            lines.append(f"{order.capitalize():<6} {name:<18}" + "".join(cells))
    return "\n".join(lines)


def _cell(v, fmt: str, width: int) -> str:
    return f"{'-':>{width}}" if v is None else f"{v:>{width}{fmt}}"


def _flags(flags) -> str:
    return "-" if flags is None else f"{sum(flags)}/{len(flags)}"


def format_scenes(results: dict) -> str:
    """One row per scene and order: PSNR of the render and of the two photo baselines, where the
    cameras came from (``cameras.source``), how many references the solve (or the data) gave and
    how many targets were located that way, and the views that fell back to the camera head.
    With ``--size``, the PSNR of the "upsampled" baseline too (column UPSAMPLED)."""
    name_w = max([5] + [len(s["name"]) for o in ORDERS for s in results[o].get("scenes", [])])
    upsampled = any("upsampled" in s["baselines"] for o in ORDERS
                    for s in results[o].get("scenes", []))
    head = (f"{'order':<6} {'scene':<{name_w}} {'PSNR':>7} {'SSIM':>6} "
            + (f"{'UPSAMPLED':>9} " if upsampled else "")
            + f"{'BEST':>7} {'NEAREST':>8} {'cameras':>9} {'refs':>5} {'targets':>7} {'fallbacks':>9}")
    lines = [head, "-" * len(head)]
    for order in ORDERS:
        for s in results[order].get("scenes", []):
            c = s["cameras"]
            near = s["baselines"]["nearest_reference"]
            lines.append(
                f"{order.capitalize():<6} {s['name']:<{name_w}} {_cell(s['model']['psnr'], '.2f', 7)} "
                f"{_cell(s['model']['ssim'], '.3f', 6)} "
                + (f"{_cell(s['baselines']['upsampled']['psnr'], '.2f', 9)} " if upsampled else "")
                + f"{_cell(s['baselines']['best_reference']['psnr'], '.2f', 7)} "
                f"{_cell(None if near is None else near['psnr'], '.2f', 8)} {c['source']:>9} "
                f"{_flags(c['references_solved']):>5} {_flags(c['targets_located']):>7} "
                f"{c['fallbacks']:>9}")
    return "\n".join(lines)


def format_cameras(results: dict) -> list[str]:
    """One line per order saying where the cameras came from (only when not the model's), with
    the reference pairs' RPA@15 of the rendered cameras and of the camera head they replaced."""
    out = []
    for order in ORDERS:
        c = results[order].get("cameras")
        if c is None:
            continue
        m = results[order]["model"]
        rendered, head = m.get("reference_rpa@15"), m.get("head_reference_rpa@15")
        frac = c["targets_epipolar"]
        out.append(f"{order.capitalize()}: references' cameras {c['references']} (scenes by "
                   f"source: {c['sources']}), targets {c['targets']}"
                   + ("" if frac is None or camera_name(c["targets"]) not in ("solve", "refined")
                      else f" ({100 * frac:.0f}% of targets posed by the camera solve)")
                   + f"; {c['fallbacks']} view(s) fell back to the camera head in "
                     f"{c['scenes_with_fallbacks']} scene(s)"
                   + ("" if rendered is None or head is None else
                      f"; RPA@15 over reference pairs {rendered:.3f}, the camera head's "
                      f"{head:.3f}"))
    return out


def write_json(path: str | os.PathLike, results: dict) -> None:
    """Write ``results`` as JSON atomically (temp file + rename); refuses NaN/inf."""
    atomic_write_json(path, results)


def save_grid(path: str | os.PathLike, references: np.ndarray, targets: np.ndarray,
              renders: np.ndarray, depths: np.ndarray, depth_range: tuple[float, float],
              ref_frames: Sequence[int] | None = None, target_frames: Sequence[int] | None = None,
              *, true_depths: np.ndarray | None = None, cameras: np.ndarray | None = None) -> None:
    """PNG of one scene: reference views; ground-truth targets; renders (with their PSNR); soft
    depth (turbo colour map over the model's [near, far]); the targets' true depth (same colour map
    and range; grey where there is no geometry; the soft depth's title then gives its Spearman
    correlation with it); and a picture of the cameras below (``cameras``: an RGB uint8 image, e.g.
    from ``iris_runtime.camera_plot.draw_cameras``). Images float ``[n, H, W, 3]`` in [0, 1],
    depths ``[n, H, W]``; ``*_frames`` label the columns with frame indices. Panels grow with
    images above ~116 pixels (``iris-eval --size``), so they show at about their own size.
    Written atomically."""
    import matplotlib
    matplotlib.use("Agg")
    import io

    import matplotlib.pyplot as plt
    ref_frames = range(len(references)) if ref_frames is None else ref_frames
    target_frames = range(len(targets)) if target_frames is None else target_frames
    depth_titles = [f"{d.min():.2f}-{d.max():.2f}" for d in depths]
    if true_depths is not None:
        rhos = [depth_spearman(d, t) for d, t in zip(depths, true_depths)]
        depth_titles = [f"{t}, \u03c1 {r:.2f}" if np.isfinite(r) else t
                        for t, r in zip(depth_titles, rhos)]
    rows = [("references", references, [f"frame {i}" for i in ref_frames]),
            ("targets (GT)", targets, [f"frame {i}" for i in target_frames]),
            ("renders", renders, [f"{capped_psnr(np.clip(r, 0, 1), t):.1f} dB" for r, t in zip(renders, targets)]),
            ("soft depth", depths, depth_titles)]
    if true_depths is not None:
        masked = [np.ma.masked_where(~(np.asarray(t) > 0), t) for t in true_depths]
        rows.append(("true depth", masked,
                     [f"{t.min():.2f}-{t.max():.2f}" if t.count() else "no geometry" for t in masked]))
    ncols = max(len(r[1]) for r in rows)
    cam_rows = 3 if cameras is not None else 0
    # Panels of 1.4 x 1.5 inches at 100 dpi, larger where the images are (--size): shown at
    # about their own resolution.
    h, w = np.asarray(renders).shape[1:3] if len(renders) else (0, 0)
    cell_w, cell_h = max(1.4, (w + 24) / 100), max(1.5, (h + 36) / 100)
    fig = plt.figure(figsize=(cell_w * ncols, cell_h * (len(rows) + cam_rows)))
    gs = fig.add_gridspec(len(rows) + cam_rows, ncols)
    cmap = matplotlib.colormaps["turbo"].with_extremes(bad="0.85")   # no geometry: grey

    def bare(ax):
        ax.set_xticks([])
        ax.set_yticks([])
        for spine in ax.spines.values():
            spine.set_visible(False)

    for r, (label, ims, titles) in enumerate(rows):
        for c in range(ncols):
            ax = fig.add_subplot(gs[r, c])
            bare(ax)
            if c < len(ims):
                if ims[c].ndim == 2:
                    ax.imshow(ims[c], cmap=cmap, vmin=depth_range[0], vmax=depth_range[1])
                else:
                    ax.imshow(np.clip(ims[c], 0, 1))
                ax.set_title(titles[c], fontsize=7)
            if c == 0:
                ax.set_ylabel(label, fontsize=8)
    if cameras is not None:
        ax = fig.add_subplot(gs[len(rows):, :])
        bare(ax)
        ax.imshow(np.asarray(cameras))
        ax.set_ylabel("cameras", fontsize=8)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())

