"""Where the renderer's error on wide baselines comes from: its geometry against the true one,
per ray, binned by the angle between the target ray and the nearest reference that sees the
surface.

    OMP_NUM_THREADS=1 python benchmarks/wide_baseline.py models/iris-tiny-rgb.pt \\
        --sets walk orbit heldout --scenes 6 --json benchmarks/results/wide/b1_true.json
    ... --sets walk --arc 150 270      # the widest walks: targets 10-30 degrees from a reference
    ... --sets walk orbit --principal-point [--clean]   # what the model's assumptions cost
    ... --sweep 0.0005 [--sweep-blur 2]                 # the photos alone: a plane sweep
    ... --oracle [--size 256]                           # the model's colours at the true depth

Cameras: the TRUE ones, as ``iris-eval --cameras true`` (``evaluate.cameras.pose_scene``: re-based
on view 0, scaled into the model's units by the solve's depth rule), targets at their true poses,
so camera error is out of the picture (but for the principal point, which the renderer takes as
centred: each scene records its offset; ``--principal-point`` renders with it,
``Scene.principal_offset``). ``--clean``: the capture sets without their photometric camera
effects (the true depth and colours of the same scenes). Frames as iris-eval's Seq order:
references 0, 2, 3, 5, 7 and targets 1, 4, 6 of 8. Each target is rendered at the model's
resolution in torch (one thread, no grad) with the rays ``IrisModel.render`` casts, keeping every
ray's blend weights.

Sets (``--sets``, N = ``--scenes`` each): ``walk``, object walks (``kind="walk"``) whose
``meta["arc_deg"]`` lies in ``--arc`` (default 45-120), the first N such seeds from
``SEEDS_FROM`` on (a range no training, validation or held-out split uses); ``orbit``, the
capture-like orbits (``kind="orbit"``), the first N seeds from ``SEEDS_FROM``; both as iris-eval's
``synthetic:capture-heldout`` (photos at ``SYNTHETIC_PHOTO_SIZE`` with camera effects, fitted to
the model); ``heldout``, the classic held-out scenes (``synthetic:heldout``, first N).

Per ray: relative depth error |soft - true| / true (soft = the weights' expected depth, as
iris-eval's; true = the pixel's depth times the cameras' scale), the largest weight, the entropy
of the weights (normalised to sum 1) over log S, the weight mass within +-5 % of the true depth,
whether the true depth lies outside the model's [near, far], the squared colour error; and the
angle at the true surface point (the pixel unprojected with its true K and depth) between the
target ray and the ray to the nearest reference centre whose frustum holds the point (occlusion
not tested); the parallax of the ±5 % band around the true depth (``band_parallax``: how many
pixels it spans in the reference that sees it widest). Per target: the angle between its
viewing direction and the nearest reference's. Bins (per ray): 0-10, 10-20, 20-30, 30-45, 45-90, >90 degrees, "unseen" (no reference frustum
holds the point) and "no depth" (no true depth): they partition the rays. Then the rays by
their band's parallax (under a quarter pixel of the model's image, to one pixel, more).

``--sweep TAU``: the same statistics for a plane sweep of the reference photos on the model's
samples instead of the model (``sweep_rays``): what photo-consistency alone says of the depth.
``--oracle``: the model's colour blend at the true depth (``oracle_rays``):
what a right geometry would render; with ``--size S``, at S x S beside the ``upsampled``
baseline (``oracle_at_size``), what a right geometry would gain over it.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from iris_runtime import geometry as NG  # noqa: E402
from iris_runtime.fileio import atomic_write_json  # noqa: E402

SETS = ("walk", "orbit", "heldout")
#: First seed of the walk and orbit scenes: above every split of ``iris_train.data``.
SEEDS_FROM = 3_100_000
ARC_RANGE = (45.0, 120.0)
#: Upper edges of the angle bins (degrees); the last bin is > 90.
EDGES = (10.0, 20.0, 30.0, 45.0, 90.0)
BIN_NAMES = ("0-10", "10-20", "20-30", "30-45", "45-90", ">90", "unseen", "no depth")
#: Half width (relative to the true depth) of the band whose weight mass is reported.
NEAR_BAND = 0.05
#: Rays per renderer call (IrisModel.render: 4096): a 64x64 view took 27 s in chunks of 256 and
#: 45 s in one of 4096 (1 thread, busy 2-core machine; the weights are per ray either way).
CHUNK = 256


def walk_seeds(n: int, arc: tuple[float, float], start: int = SEEDS_FROM) -> list[int]:
    """The first ``n`` seeds from ``start`` whose walk spans ``arc`` degrees (read off the scene
    spec, nothing rendered); ``ValueError`` when 100 n seeds give fewer."""
    from iris_train.synthetic import build_scene_spec
    out = []
    for seed in range(start, start + 100 * n):
        if arc[0] <= build_scene_spec(seed, 8, (64, 64), "walk").meta["arc_deg"] <= arc[1]:
            out.append(seed)
            if len(out) == n:
                return out
    raise ValueError(f"arc: only {len(out)} of {100 * n} walks span {arc[0]:g}-{arc[1]:g} degrees")


def load_set(name: str, n: int, image_size, arc=ARC_RANGE, clean: bool = False):
    """(scenes, count) of set ``name``, as iris-eval's ``load_scenes`` gives its sets (``clean``:
    the capture sets without their photometric camera effects)."""
    from iris_train.data import SyntheticScenes
    from iris_train.evaluate.scenes import SYNTHETIC_PHOTO_SIZE, load_scenes
    if name == "heldout":
        return load_scenes("synthetic:heldout", image_size, 8, n)
    seeds = walk_seeds(n, arc) if name == "walk" else list(range(SEEDS_FROM, SEEDS_FROM + n))
    scenes = SyntheticScenes(seeds, n_views=8, size=SYNTHETIC_PHOTO_SIZE, kind=name, clean=clean)
    return (scenes[i] for i in range(len(scenes))), len(scenes)


def sweep_rays(encoded, origins, directions, z, tau: float, blurred=None):
    """The plane sweep's answer for the same samples: weights ``softmax(-variance / tau)`` over
    the samples seen by at least two views (the variance of the views' colours, each view
    weighted by its validity; with ``blurred`` [V, 3, H', W'] photos, the mean of the variances
    at both scales: a patch's consistency, not a pixel's), colour the weighted view mean ->
    ``rgb [R, 3]``, ``weights [R, S]``. No network: what the photos alone say of the depth."""
    import torch

    from iris_train.ibr import view_mean
    s = encoded.project_samples(origins, directions, z, colours=True)
    mean, var, _ = view_mean(s.colours, s.mask)                   # [R, S, 3], [R, S]
    if blurred is not None:
        var = (var + view_mean(dataclasses.replace(encoded, images=blurred).project_samples(
            origins, directions, z, colours=True).colours, s.mask)[1]) / 2
    use = (s.mask > 0.5).sum(0) >= 2                                              # [R, S]
    logits = torch.where(use, -var / tau, torch.full_like(var, -1e30))
    weights = torch.softmax(logits, -1) * use.any(-1, keepdim=True).to(var.dtype)
    return (weights[..., None] * mean).sum(1), weights


def oracle_colours(model, encoded, origins, directions, z, true):
    """The model's own colour blend (``blend_views``: the views weighted by validity and angle)
    at each ray's true depth ``true [R]`` itself, no residual head -> ``rgb [R, 3]``, one-hot
    ``weights [R, S]`` on the sample of ``z`` nearest it (for the depth statistics), and ``used
    [R]``: the rays with a true depth that some view sees (the others' rgb is meaningless)."""
    import torch

    from iris_train.model import blend_views
    at = true.clamp_min(model.cfg.near)[:, None]                                    # [R, 1]
    s = encoded.project_samples(origins, directions, at, colours=True)
    mean = blend_views(s.colours, s.mask, s.cues[..., 3], model.cfg.blend_angle)[:, 0]   # [R, 3]
    nearest = (z - true[:, None]).abs().argmin(-1)                                  # [R]
    weights = torch.nn.functional.one_hot(nearest, z.shape[-1]).to(z.dtype)
    return mean, weights, (true > 0) & (s.mask.amax(0)[:, 0] > 0)


def oracle_rays(model, encoded, origins, directions, z, true):
    """``oracle_colours``, with the model's answer on the rays it cannot use -> ``rgb [R, 3]``,
    ``weights [R, S]``: what the explicit colour gives when the geometry is right."""
    import torch
    rgb, weights, used = oracle_colours(model, encoded, origins, directions, z, true)
    model_rgb, model_weights = model.render_rays(encoded, origins, directions, z)
    return (torch.where(used[:, None], rgb, model_rgb),
            torch.where(used[:, None], weights, model_weights))


def oracle_at_size(model, scene, size: int, index: int = 0, chunk: int = CHUNK):
    """A scene at ``size`` x ``size`` (``iris-eval --size``'s protocol, true cameras): per target,
    the ``upsampled`` baseline (the model's render at its resolution, bicubic to the size) and
    the oracle (``oracle_colours`` on the output's own rays, with the photos' colours at their
    resolution; ``upsampled`` where it has no answer) -> a record with both PSNRs, over all
    pixels and over the oracle's, or None when the scene has fewer than 8 frames."""
    import cv2
    import torch

    from iris_train import geometry as G
    from iris_train.evaluate import TorchBackend, prepare_scene, split_frames
    from iris_train.evaluate.cameras import pose_scene
    from iris_train.metrics import psnr
    backend = TorchBackend(model)
    prepared = prepare_scene(scene, 8, backend.image_size, index, output_size=(size, size))
    if prepared is None:
        return None
    refs, targets = split_frames(8)
    posed = pose_scene(backend, prepared, refs, targets, "true", "true")
    encoded, T, (H, W) = posed.encoded, posed.world_from_cam, backend.image_size
    dtype = encoded.field_maps.dtype
    out = {"upsampled": [], "oracle": [], "upsampled_used": [], "oracle_used": [], "used": []}
    with torch.no_grad():
        for t in targets:
            low = np.clip(render_target(model, encoded, T[t])[0], 0.0, 1.0).reshape(H, W, 3)
            up = np.clip(cv2.resize(np.ascontiguousarray(low), (size, size),
                                    interpolation=cv2.INTER_CUBIC), 0.0, 1.0).reshape(-1, 3)
            true = prepared.true_depth[t].reshape(-1) * posed.scale
            origins, directions = G.rays_from_pixels(G.pixel_centres(size, size, dtype=dtype),
                                                     encoded.intrinsics(size, size),
                                                     torch.as_tensor(T[t]).to(dtype))
            parts = []
            for start in range(0, size * size, chunk):
                sl = slice(start, start + chunk)
                z = G.sample_depths(model.cfg.near, model.cfg.far, model.cfg.samples,
                                    origins[sl].shape[0], dtype=dtype)
                rgb, _, used = oracle_colours(model, encoded, origins[sl], directions[sl], z,
                                              torch.as_tensor(true[sl]).to(dtype))
                parts.append((rgb.double().numpy(), used.numpy()))
            rgb, used = (np.concatenate(p) for p in zip(*parts))
            oracle = np.where(used[:, None], np.clip(rgb, 0.0, 1.0), up)
            gt = prepared.gt_images[t].reshape(-1, 3)
            out["upsampled"].append(psnr(up, gt))
            out["oracle"].append(psnr(oracle, gt))
            out["upsampled_used"].append(psnr(up[used], gt[used]))
            out["oracle_used"].append(psnr(oracle[used], gt[used]))
            out["used"].append(float(used.mean()))
    meta = getattr(scene, "meta", None) or {}
    return {"name": prepared.name, **{k: meta.get(k) for k in ("seed", "kind", "arc_deg")},
            **{k: float(np.mean(v)) for k, v in out.items()}}


def render_target(model, encoded, world_from_cam: np.ndarray, chunk: int = CHUNK,
                  sweep: tuple[float, int] | None = None, oracle_depth: np.ndarray | None = None):
    """One target at the model's resolution, the rays, samples and soft depth of
    ``IrisModel.render`` (in chunks of ``chunk`` rays) -> ``rgb [R, 3]``, blend ``weights [R,
    S]``, sample depths ``z [R, S]``, soft depth ``[R]`` (float64 numpy). ``sweep``: (tau,
    blur dilation or 0) to answer with ``sweep_rays`` instead of the model; ``oracle_depth [R]``:
    with ``oracle_rays`` at that depth (the true one)."""
    import torch

    from iris_train import geometry as G
    from iris_train import ibr
    (H, W), dtype, out = encoded.image_size, encoded.field_maps.dtype, []
    blurred = (ibr.blur(encoded.images, sweep[1]) if sweep is not None and sweep[1] else None)
    with torch.no_grad():
        origins, directions = G.rays_from_pixels(G.pixel_centres(H, W, dtype=dtype),
                                                 encoded.intrinsics(H, W),
                                                 torch.as_tensor(world_from_cam).to(dtype))
        for start in range(0, H * W, chunk):
            sl = slice(start, start + chunk)
            z = G.sample_depths(model.cfg.near, model.cfg.far, model.cfg.samples,
                                origins[sl].shape[0], dtype=dtype)
            if oracle_depth is not None:
                rgb, weights = oracle_rays(model, encoded, origins[sl], directions[sl], z,
                                           torch.as_tensor(oracle_depth[sl]).to(dtype))
            elif sweep is None:
                rgb, weights = model.render_rays(encoded, origins[sl], directions[sl], z)
            else:
                rgb, weights = sweep_rays(encoded, origins[sl], directions[sl], z, sweep[0], blurred)
            out.append((rgb, weights, z, (weights * z).sum(-1)))
    return tuple(torch.cat(parts).double().numpy() for parts in zip(*out))


def ray_stats(weights, z, soft, true, near: float, far: float) -> dict[str, np.ndarray]:
    """Per-ray geometry of ``weights, z [R, S]``, soft depth ``[R]`` against ``true [R]`` (0: no
    geometry; its depth error and band mass are nan)."""
    has = true > 0
    safe = np.where(has, true, np.nan)
    total = weights.sum(-1)
    p = weights / np.where(total > 0, total, np.nan)[:, None]
    plogp = np.where(p > 0, p * np.log(np.where(p > 0, p, 1.0)), 0.0)
    band = np.abs(z - safe[:, None]) <= NEAR_BAND * safe[:, None]
    return {"depth_err": np.abs(soft - safe) / safe, "max_weight": weights.max(-1),
            "entropy": -plogp.sum(-1) / np.log(weights.shape[-1]),
            "mass_near": np.where(has, (weights * band).sum(-1), np.nan),
            "outside": has & ((true < near) | (true > far))}


def surface_angles(points, target_centre, ref_world_from_cam, ref_K, height: int, width: int):
    """Angle (degrees) at each point ``[N, 3]`` between the rays to ``target_centre`` and to the
    nearest reference centre (``ref_world_from_cam [V, 4, 4]``, true ``ref_K [V, 3, 3]``) whose
    frustum holds it; nan where none does. ``[N]``."""
    cam_from_world = NG.invert_pose(np.asarray(ref_world_from_cam, dtype=np.float64))
    seen = np.stack([NG.project_points(points, K, T[None], height, width)[2][0]
                     for K, T in zip(ref_K, cam_from_world)])                        # [V, N]
    cos = NG.cue_cosine(points, target_centre, ref_world_from_cam[:, :3, 3])       # [V, N]
    angle = np.where(seen, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), np.inf).min(0)
    return np.where(np.isfinite(angle), angle, np.nan)


def band_parallax(origins, directions, true, ref_world_from_cam, ref_K, height: int, width: int):
    """How far (pixels of the model's image) the ±``NEAR_BAND`` band around each ray's true
    depth ``true [N]`` (rays ``origins, directions [N, 3]``) spans in the reference that sees it
    widest: the most any method can tell depths apart within the band from those photos. nan
    where no reference sees both ends (or no true depth). ``[N]``."""
    cam_from_world = NG.invert_pose(np.asarray(ref_world_from_cam, dtype=np.float64))
    ends = [origins + (true * f)[:, None] * directions for f in (1 - NEAR_BAND, 1 + NEAR_BAND)]
    spans = []
    for K, T in zip(ref_K, cam_from_world):
        (uv0, _, ok0), (uv1, _, ok1) = (NG.project_points(e, K, T[None], height, width)
                                        for e in ends)
        spans.append(np.where(ok0[0] & ok1[0], np.linalg.norm(uv1[0] - uv0[0], axis=-1), -1.0))
    widest = np.max(spans, axis=0)
    return np.where((widest >= 0) & (true > 0), widest, np.nan)


def bin_index(angle, has_depth) -> np.ndarray:
    """Each ray's position in ``BIN_NAMES``."""
    idx = np.digitize(np.nan_to_num(angle, nan=0.0), EDGES, right=True)
    return np.where(~has_depth, 7, np.where(np.isnan(angle), 6, idx))


def scene_rays(model, scene, index: int = 0, principal_point: bool = False,
               sweep: tuple[float, int] | None = None, oracle: bool = False):
    """One scene rendered at its true cameras -> (per-ray arrays over its targets, its record),
    or None when it has fewer than 8 frames. ``principal_point``: render with the references'
    true principal point (``Scene.principal_offset``) instead of the centred one the model
    assumes. ``sweep``: the plane sweep's geometry instead of the model's (``render_target``);
    ``oracle``: the true depth's (``oracle_rays``)."""
    import torch

    from iris_train import geometry as G
    from iris_train.evaluate import TorchBackend, prepare_scene, split_frames
    from iris_train.evaluate.cameras import pose_scene
    from iris_train.evaluate.evaluation import depth_score
    from iris_train.evaluate.protocol import nvs_scores
    backend = TorchBackend(model)
    prepared = prepare_scene(scene, 8, backend.image_size, index)
    if prepared is None:
        return None
    refs, targets = split_frames(8)
    posed = pose_scene(backend, prepared, refs, targets, "true", "true")
    T, (H, W), refs = posed.world_from_cam, backend.image_size, list(refs)
    encoded = posed.encoded
    if principal_point:
        encoded = dataclasses.replace(encoded, principal_offset=torch.as_tensor(
            posed.principal_offset, dtype=encoded.field_maps.dtype))
    uv = G.pixel_centres(H, W, dtype=torch.float64).numpy()     # the rendered rays' pixels
    rays, rgbs, softs, view_deg = [], [], [], []
    for t in targets:
        true = prepared.true_depth[t].reshape(-1) * posed.scale
        rgb, weights, z, soft = render_target(model, encoded, T[t], sweep=sweep,
                                              oracle_depth=true if oracle else None)
        stats = ray_stats(weights, z, soft, true, model.cfg.near, model.cfg.far)   # sampled range
        gt = prepared.gt_images[t].reshape(-1, 3)
        stats["sq_err"] = ((np.clip(rgb, 0.0, 1.0) - gt) ** 2).mean(-1)
        origins, directions = NG.rays_from_pixels(uv, prepared.K[t], T[t])
        points = origins + true[:, None] * directions
        stats["angle"] = np.where(true > 0, surface_angles(points, T[t, :3, 3], T[refs],
                                                           prepared.K[refs], H, W), np.nan)
        stats["has_depth"] = true > 0
        stats["parallax"] = band_parallax(origins, directions, true, T[refs], prepared.K[refs], H, W)
        rays.append(stats)
        rgbs.append(np.clip(rgb, 0.0, 1.0).reshape(H, W, 3))
        softs.append(soft.reshape(H, W))
        axes = np.einsum("i,ki->k", T[t, :3, 2], T[refs, :3, 2])
        view_deg.append(float(np.degrees(np.arccos(np.clip(axes, -1.0, 1.0))).min()))
    meta = getattr(scene, "meta", None) or {}
    record = {"name": prepared.name, **{k: meta.get(k) for k in ("seed", "kind", "arc_deg")},
              "psnr": nvs_scores(rgbs, prepared.gt_images[list(targets)])["psnr"],
              "depth_spearman": depth_score(np.stack(softs), prepared.true_depth[list(targets)]),
              "view_deg": view_deg, "scale": posed.scale,
              "principal_offset": [float(x) for x in posed.principal_offset]}
    return {k: np.concatenate([r[k] for r in rays]) for k in rays[0]}, record


def _value(x) -> float | None:
    return None if x is None or not np.isfinite(x) else round(float(x), 5)


def bin_row(name: str, rays: dict, mask) -> dict:
    """The summary of the rays ``mask`` selects."""
    from iris_train.metrics import PSNR_CAP
    n = int(mask.sum())
    row = {"bin": name, "rays": n}
    if n == 0:
        return row
    mse = float(rays["sq_err"][mask].mean())
    depth = rays["depth_err"][mask]
    has = bool(np.isfinite(depth).any())
    with np.errstate(all="ignore"):
        row.update(psnr=min(PSNR_CAP, -10.0 * np.log10(mse)) if mse > 0 else PSNR_CAP,
                   depth_err_median=np.nanmedian(depth) if has else None,
                   depth_err_mean=np.nanmean(depth) if has else None,
                   max_weight_median=np.median(rays["max_weight"][mask]),
                   entropy_median=np.nanmedian(rays["entropy"][mask]),
                   mass_near_mean=np.nanmean(rays["mass_near"][mask]) if has else None,
                   outside_fraction=float(rays["outside"][mask].mean()),
                   parallax_median=np.nanmedian(rays["parallax"][mask])
                   if np.isfinite(rays["parallax"][mask]).any() else None)
    return {k: v if isinstance(v, (str, int)) else _value(v) for k, v in row.items()}


#: Edges (pixels of the model's image) of the parallax bins: a quarter pixel is one pixel of
#: the 256x256 photos the colours come from.
PARALLAX_EDGES = (0.25, 1.0)


def summarise(rays: dict) -> list[dict]:
    """One row per bin of ``BIN_NAMES`` (they partition the rays), then "all", then the rays
    with a true depth by the parallax of their ±5% band (``band_parallax``)."""
    idx = bin_index(rays["angle"], rays["has_depth"])
    par = rays["parallax"]
    lo, hi = PARALLAX_EDGES
    by_parallax = [(f"par<{lo:g}", par < lo), (f"par{lo:g}-{hi:g}", (par >= lo) & (par < hi)),
                   (f"par>={hi:g}", par >= hi)]
    return ([bin_row(name, rays, idx == b) for b, name in enumerate(BIN_NAMES)]
            + [bin_row("all", rays, np.ones(len(idx), dtype=bool))]
            + [bin_row(name, rays, mask) for name, mask in by_parallax])


def format_report(sets: dict) -> str:
    cols = ("rays", "psnr", "depth_err_median", "depth_err_mean", "max_weight_median",
            "entropy_median", "mass_near_mean", "outside_fraction", "parallax_median")
    lines = [f"{'set':8}{'bin':>9}{'rays':>8}{'PSNR':>7}{'relerr med':>11}{'mean':>7}"
             f"{'maxw med':>9}{'H/logS med':>11}{'mass+-5%':>9}{'outside':>8}{'par med':>8}"]
    for name, s in sets.items():
        for row in s["bins"]:
            vals = ["-" if row.get(c) is None else f"{row[c]:.3f}" if c != "rays" else str(row[c])
                    for c in cols]
            vals[1] = vals[1] if row.get("psnr") is None else f"{row['psnr']:.2f}"
            lines.append(f"{name:8}{row['bin']:>9}" + "".join(
                f"{v:>{w}}" for v, w in zip(vals, (8, 7, 11, 7, 9, 11, 9, 8, 8))))
    lines.append("")
    lines.append(f"{'set':8}{'scene':>14}{'arc':>7}{'PSNR':>7}{'rho':>7}  target view angles "
                 f"(deg)  principal offset (px)")
    for name, s in sets.items():
        for r in s["scenes"]:
            rho = "-" if r["depth_spearman"] is None else f"{r['depth_spearman']:.3f}"
            scene = r["name"] if r["seed"] is None else str(r["seed"])
            lines.append(f"{name:8}{scene:>14}{r['arc_deg'] or 0:7.1f}{r['psnr']:7.2f}{rho:>7}"
                         f"  {' '.join(f'{a:5.1f}' for a in r['view_deg']):17}  "
                         f"{r['principal_offset'][0]:+.1f} {r['principal_offset'][1]:+.1f}")
    return "\n".join(lines)


def run(model, sets, n: int, arc=ARC_RANGE, progress: bool = True, clean: bool = False,
        principal_point: bool = False, sweep: tuple[float, int] | None = None,
        oracle: bool = False) -> dict:
    """``{set: {"bins": rows, "scenes": records}}`` over the first ``n`` scenes of each set
    (``clean``, ``principal_point``: as ``load_set`` and ``scene_rays`` take them)."""
    from tqdm import tqdm
    image_size = (model.cfg.image_height, model.cfg.image_width)
    out = {}
    for name in sets:
        scenes, count = load_set(name, n, image_size, arc, clean)
        parts, records = [], []
        for i, scene in enumerate(tqdm(scenes, total=count, desc=name, unit="scene",
                                       disable=not progress, dynamic_ncols=True)):
            result = scene_rays(model, scene, i, principal_point, sweep, oracle)
            if result is not None:
                parts.append(result[0])
                records.append({k: _value(v) if isinstance(v, float) else v
                                for k, v in result[1].items()})
        rays = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        out[name] = {"bins": summarise(rays), "scenes": records}
    return out


def main_at_size(model, args, start: float) -> int:
    """``--oracle --size S``: ``oracle_at_size`` over each set's scenes, printed and written."""
    from tqdm import tqdm
    image_size = (model.cfg.image_height, model.cfg.image_width)
    sets = {}
    for name in dict.fromkeys(args.sets):
        scenes, count = load_set(name, args.scenes, image_size, tuple(args.arc), args.clean)
        records = [r for i, scene in enumerate(tqdm(scenes, total=count, desc=name, unit="scene",
                                                    disable=args.no_progress, dynamic_ncols=True))
                   if (r := oracle_at_size(model, scene, args.size, i)) is not None]
        sets[name] = {"scenes": records, **{k: float(np.mean([r[k] for r in records])) for k in
                      ("upsampled", "oracle", "upsampled_used", "oracle_used", "used")}}
    seconds = time.perf_counter() - start
    print(f"{'set':8}{'upsampled':>10}{'oracle':>8}{'margin':>8}   over the oracle's pixels "
          f"({'share':>5}): upsampled, oracle")
    for name, s in sets.items():
        print(f"{name:8}{s['upsampled']:10.2f}{s['oracle']:8.2f}{s['oracle'] - s['upsampled']:+8.2f}"
              f"   {s['used']:.3f}: {s['upsampled_used']:.2f}, {s['oracle_used']:.2f}")
    print(f"\n{seconds:.0f} s")
    if args.json is not None:
        atomic_write_json(args.json, {"model": {"oracle_depth": True, "blend_of": str(args.model)},
                                      "size": args.size, "cameras": "true", "clean": args.clean,
                                      "seconds": round(seconds, 1), "sets": sets})
        print(f"wrote {args.json}")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 epilog=__doc__.split("\n\n")[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("model", metavar="MODEL", help="checkpoint (.pt), e.g. models/iris-tiny-rgb.pt")
    ap.add_argument("--sets", nargs="+", choices=SETS, default=list(SETS), metavar="SET",
                    help=f"scene sets, any of {', '.join(SETS)} (default: all)")
    ap.add_argument("--scenes", type=int, default=8, metavar="N", help="scenes per set (default 8)")
    ap.add_argument("--arc", type=float, nargs=2, default=ARC_RANGE, metavar=("MIN", "MAX"),
                    help="walk set: the arcs (degrees) kept (default 45 120)")
    ap.add_argument("--json", type=Path, default=None, metavar="FILE",
                    help="write the bins and per-scene records to FILE (atomically)")
    ap.add_argument("--principal-point", action="store_true",
                    help="render with the scenes' true principal points (the model assumes "
                         "centred ones): what that assumption costs")
    ap.add_argument("--clean", action="store_true",
                    help="the capture sets without their photometric camera effects (exposure, "
                         "white balance, vignetting, blur, noise, JPEG)")
    ap.add_argument("--sweep", type=float, default=None, metavar="TAU",
                    help="answer with a plane sweep of the photos (weights softmax(-variance / "
                         "TAU) over the samples two views see) instead of the model: the depth "
                         "the photos alone give, on the same samples")
    ap.add_argument("--sweep-blur", type=int, default=0, metavar="D",
                    help="with --sweep: also the variance of the photos blurred with dilation D "
                         "(a patch's consistency)")
    ap.add_argument("--oracle", action="store_true",
                    help="answer with the model's colour blend at the true depth (no residual): "
                         "what a right geometry would give")
    ap.add_argument("--size", type=int, default=None, metavar="S",
                    help="with --oracle: at S x S against the photos brought to S (iris-eval "
                         "--size), the oracle beside the `upsampled` baseline, per scene")
    ap.add_argument("--no-progress", action="store_true", help="no progress bars")
    args = ap.parse_args(argv)
    if args.scenes < 1:
        ap.error("--scenes must be at least 1")
    if args.oracle and args.sweep is not None:
        ap.error("--oracle and --sweep: choose one answer")
    if args.size is not None and (not args.oracle or args.size < 1):
        ap.error("--size S: only with --oracle, S >= 1")
    if not 0 <= args.arc[0] < args.arc[1]:
        ap.error("--arc: expected 0 <= MIN < MAX")
    import torch

    from iris_train.model import CheckpointError, load_model
    torch.set_num_threads(1)
    try:
        model = load_model(args.model)
    except CheckpointError as exc:
        ap.error(str(exc))
    start = time.perf_counter()
    if args.size is not None:
        return main_at_size(model, args, start)
    try:
        sets = run(model, list(dict.fromkeys(args.sets)), args.scenes, tuple(args.arc),
                   not args.no_progress, args.clean, args.principal_point,
                   None if args.sweep is None else (args.sweep, args.sweep_blur), args.oracle)
    except ValueError as exc:               # no walk spans --arc
        ap.error(str(exc))
    seconds = time.perf_counter() - start
    print(format_report(sets))
    print(f"\n{seconds:.0f} s")
    if args.json is not None:
        from iris_train.evaluate import split_frames
        refs, targets = split_frames(8)
        path = Path(args.model).resolve()       # named as given, relative to the repository
        name = str(path.relative_to(REPO)) if path.is_relative_to(REPO) else path.name
        atomic_write_json(args.json, {
            "model": ({"oracle_depth": True, "blend_of": name} if args.oracle else name
                      if args.sweep is None else
                      {"sweep_tau": args.sweep, "sweep_blur": args.sweep_blur, "samples_of": name}),
            "cameras": "true", "principal_point": "true" if
            args.principal_point else "centred", "clean": args.clean,
            "references": list(refs), "targets": list(targets),
            "arc_range": list(args.arc), "seeds_from": SEEDS_FROM,
            "near_band": NEAR_BAND, "bins": list(BIN_NAMES), "seconds": round(seconds, 1),
            "sets": sets})
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
