"""Our camera solve against COLMAP on the same photos: registered views, RPA, focal error, time.

    python benchmarks/camera_solve.py                         # every dataset, ours + COLMAP
    python benchmarks/camera_solve.py --datasets castle --solvers ours --protocol eval
    python benchmarks/camera_solve.py --out benchmarks/results/camera_solve

Datasets (photos with true cameras):

- ``heldout``: the 16 held-out synthetic scenes (``iris_train.data.HELDOUT_SEEDS``) rendered at
  256x256, 8 views on arcs of 10-90 degrees (``validation``: the first 24 validation scenes,
  ``VALIDATION_SEEDS``, rendered alike: where a setting is chosen before held-out reports it;
  ``validation-more``: the next 24, where a choice is checked);
- ``heldout-64``, ``validation-64``: the same scenes at the model's 64x64 (the 256x256 renders
  brought down as ``iris_train.data.SyntheticScenes`` gives a 64x64 model its photos): the
  photos ``IrisRuntime.encode`` gets from a caller who has only the model's resolution;
- ``capture``: the 16 capture-like held-out scenes (``CAPTURE_HELDOUT_SEEDS``: walks, orbits,
  hand-held paths and rooms, fields of view of 25-90 degrees, principal points off centre,
  photographic textures, camera effects), 256x256 (``capture-validation``: the first 24
  ``CAPTURE_VALIDATION_SEEDS``);
- ``wide``: 8 synthetic turntables (seeds ``WIDE_SEEDS``) whose 8 cameras are moved onto arcs of
  120-180 degrees around the same target (``iris_train.synthetic``'s ``look_at`` and renderer,
  the generator itself unchanged), 256x256;
- ``castle``: ViSP ``Castle-simu`` (Debian ``visp-images-data``; 40 Blender frames, true poses
  ``CameraPose/Camera_XXX.txt`` are cam_from_world, K fx = fy = 700 at 640x480): frames
  1, 6, ..., 36 (8, wide gaps) and 21, 23, ..., 39 (10), each at 320x240 and 640x480.

Ours solves on the copies of the photos ``IrisRuntime.encode`` makes (at most
``iris_runtime.images.CAMERA_WORKING_SIZE`` = 512 pixels on the longer side: the 640x480 castle
is solved at 512x384); COLMAP gets the photos as they are.

Protocols: ``all``, every view of a scene solved together; ``eval``, iris-eval's (8 frames
taken evenly along the sequence, references 0, 2, 3, 5, 7 solved together, targets 1, 4, 6
located against them with the references fixed), ours only. RPA@5/15/30 is the paper's pose
error (``iris_train.metrics.relative_pose_errors``: max of the rotation angle and the
sign-free translation-direction angle) over all pairs of views, a pair with an unposed view
counting as a failure. Focal error: |f / f_true - 1|. Seconds: wall time of the solve on one
thread (OpenCV and COLMAP one thread each), SIFT included, image reading not.

Solvers: ``ours`` (``iris_runtime.cameras.solve_cameras``); ``colmap`` (``pycolmap``, the
``[bench]`` extra: SIFT, exhaustive matching, incremental mapping, one shared camera) with its
mapper defaults and ``colmap-relaxed`` (``init_min_num_inliers`` 30, ``abs_pose_min_num_inliers``
15), each with ``--seeds`` RANSAC seeds. Medians and means over scenes are in the markdown.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

CASTLE = Path("/usr/share/visp-images-data/ViSP-images/mbt-depth/Castle-simu")
CASTLE_SUBSETS = {"1-36": list(range(1, 37, 5)), "21-39": list(range(21, 40, 2))}
CASTLE_SIZES = ((240, 320), (480, 640))
CASTLE_FOCAL = 700.0 / 640.0                       # fx / W
WIDE_SEEDS = tuple(range(3_000_000, 3_000_008))
WIDE_ARCS = tuple(120.0 + 60.0 * k / 7 for k in range(8))
SIZE = (256, 256)
MODEL_SIZE = (64, 64)
DEPTH_RANGE = (0.1, 1.0)
EVAL_FRAMES = 8
REFERENCES, TARGETS = (0, 2, 3, 5, 7), (1, 4, 6)
THRESHOLDS = (5, 15, 30)


@dataclasses.dataclass
class Scene:
    name: str
    photos: list                   # uint8 [H, W, 3]
    world_from_cam: np.ndarray     # [V, 4, 4]
    focal: float                   # true fx / W


# -- datasets --------------------------------------------------------------------------------
def _synthetic(name: str, seeds, kind=None, size=SIZE):
    """The scenes rendered at ``SIZE``, brought down to ``size`` as the model's photos are."""
    from iris_train.data import SyntheticScenes
    scenes = SyntheticScenes(seeds, size=size, kind=kind, render_size=SIZE)
    for i, seed in enumerate(seeds):
        s = scenes[i]
        arc = s.meta.get("arc_deg")
        yield Scene(f"{name} {seed} ({s.meta['kind']}" + (f", arc {arc:.0f})" if arc else ")"),
                    list(s.images), s.world_from_cam, s.K[0, 0] / size[1])


def heldout_scenes():
    from iris_train.data import HELDOUT_SEEDS
    return _synthetic("heldout", HELDOUT_SEEDS)


def validation_scenes():
    """The first 24 validation scenes: where solve settings are chosen (held-out reports)."""
    from iris_train.data import VALIDATION_SEEDS
    return _synthetic("validation", VALIDATION_SEEDS[:24])


def heldout_64_scenes():
    """The held-out scenes at the model's 64x64 (what the quickstart's sample is)."""
    from iris_train.data import HELDOUT_SEEDS
    return _synthetic("heldout-64", HELDOUT_SEEDS, size=MODEL_SIZE)


def eval_heldout_64_scenes():
    """The held-out scenes as ``iris-eval`` brings them to the model's 64x64 (its loader's resize:
    other pixels than ``heldout_64_scenes``', so other keypoints and other paths through the
    refinement)."""
    from iris_train.data import HELDOUT_SEEDS
    from iris_train.evaluate.scenes import load_scenes
    scenes, _ = load_scenes("synthetic:heldout", MODEL_SIZE, views=8)
    for seed, scene in zip(HELDOUT_SEEDS, scenes):
        yield Scene(f"eval-heldout-64 {seed}", list(scene.images),
                    np.linalg.inv(scene.world_from_cam[0]) @ scene.world_from_cam,
                    float(scene.K[0, 0]) / MODEL_SIZE[1])


def validation_64_scenes():
    from iris_train.data import VALIDATION_SEEDS
    return _synthetic("validation-64", VALIDATION_SEEDS[:24], size=MODEL_SIZE)


def validation_more_64_scenes():
    """Validation scenes 24-47 at 64x64: a second sample where a choice that moves the first's
    RPA by a few pairs either way is checked."""
    from iris_train.data import VALIDATION_SEEDS
    return _synthetic("validation-64", VALIDATION_SEEDS[24:48], size=MODEL_SIZE)


#: The 64x64 scene sets of the refinement's benchmarks, by the name their ``--scenes`` takes.
SETS_64 = {"heldout": heldout_64_scenes, "validation": validation_64_scenes,
           "validation-more": validation_more_64_scenes, "eval-heldout": eval_heldout_64_scenes}


def validation_more_scenes():
    """Validation scenes 24-47: a second sample where a choice is checked before held-out."""
    from iris_train.data import VALIDATION_SEEDS
    return _synthetic("validation", VALIDATION_SEEDS[24:48])


def capture_scenes():
    """The 16 capture-like held-out scenes (walks, orbits, hand-held paths, rooms; wide fields
    of view, photographic textures and camera effects), 256x256."""
    from iris_train.data import CAPTURE_HELDOUT_SEEDS
    return _synthetic("capture", CAPTURE_HELDOUT_SEEDS, kind="capture")


def capture_validation_scenes():
    """The first 24 capture-like validation scenes: where settings are chosen for them."""
    from iris_train.data import CAPTURE_VALIDATION_SEEDS
    return _synthetic("capture-validation", CAPTURE_VALIDATION_SEEDS[:24], kind="capture")


def wide_scenes():
    """Turntables with their cameras on a wide arc: the generator's scene, our cameras."""
    import math

    from iris_train.synthetic import build_scene_spec, look_at, render_spec
    for seed, arc in zip(WIDE_SEEDS, WIDE_ARCS):
        spec = build_scene_spec(seed, 8, SIZE, kind="turntable")
        T0 = spec.world_from_cam
        centre = np.array([0.0, 0.0, 0.05])
        eye0 = T0[len(T0) // 2, :3, 3] - centre
        dist = np.linalg.norm(eye0)
        elev = math.asin(eye0[2] / dist)
        az0 = math.atan2(eye0[1], eye0[0])
        poses = []
        for k in range(8):
            az = az0 + math.radians(arc) * (k / 7 - 0.5)
            eye = centre + dist * np.array([math.cos(elev) * math.cos(az),
                                            math.cos(elev) * math.sin(az), math.sin(elev)])
            poses.append(look_at(eye, centre))
        spec = dataclasses.replace(spec, world_from_cam=np.stack(poses))
        s = render_spec(spec)
        yield Scene(f"wide {seed} (arc {arc:.0f})", list(s.images), s.world_from_cam,
                    s.K[0, 0] / SIZE[1])


def castle_scenes():
    import cv2
    if not CASTLE.is_dir():
        raise SystemExit(f"{CASTLE}: missing (apt-get install visp-images-data)")
    for name, frames in CASTLE_SUBSETS.items():
        grey = [cv2.imread(str(CASTLE / "Images" / f"Image_{i:04d}.pgm"), cv2.IMREAD_GRAYSCALE)
                for i in frames]
        # The files hold cam_from_world: checked on the photos' matches (docs/CAMERAS.md).
        T = np.stack([np.linalg.inv(np.loadtxt(CASTLE / "CameraPose" / f"Camera_{i:03d}.txt"))
                      for i in frames])
        for H, W in CASTLE_SIZES:
            photos = [np.repeat((g if g.shape == (H, W) else cv2.resize(
                g, (W, H), interpolation=cv2.INTER_AREA))[..., None], 3, axis=2) for g in grey]
            yield Scene(f"castle {name} {W}x{H}", photos, T, CASTLE_FOCAL)


DATASETS = {"heldout": heldout_scenes, "validation": validation_scenes,
            "heldout-64": heldout_64_scenes, "validation-64": validation_64_scenes,
            "validation-more": validation_more_scenes, "wide": wide_scenes,
            "castle": castle_scenes, "capture": capture_scenes,
            "capture-validation": capture_validation_scenes}


# -- solvers ---------------------------------------------------------------------------------
def working_copies(photos):
    """The copies ``IrisRuntime.encode`` solves the cameras on (``fit_to_working_size``)."""
    from iris_runtime.images import fit_to_working_size
    return [fit_to_working_size(p)[0] for p in photos]


def solve_ours(photos):
    """-> (world_from_cam [V, 4, 4] NaN where unposed, fx / W, seconds), on the runtime's
    working copies of the photos."""
    from iris_runtime.cameras import solve_cameras
    t0 = time.perf_counter()
    s = solve_cameras(working_copies(photos), DEPTH_RANGE)
    return s.world_from_cam, s.focal / s.image_size[1], time.perf_counter() - t0


def solve_colmap(photos, seed: int, relaxed: bool):
    import cv2
    import pycolmap
    V = len(photos)
    with tempfile.TemporaryDirectory() as d:
        images = Path(d) / "images"
        images.mkdir()
        names = [f"{k:03d}.png" for k in range(V)]
        for name, p in zip(names, photos):
            cv2.imwrite(str(images / name), p[..., ::-1])
        db = str(Path(d) / "database.db")
        t0 = time.perf_counter()
        ext = pycolmap.FeatureExtractionOptions()
        ext.num_threads, ext.use_gpu = 1, False
        pycolmap.extract_features(db, images, camera_mode=pycolmap.CameraMode.SINGLE,
                                  extraction_options=ext, device=pycolmap.Device.cpu)
        match = pycolmap.FeatureMatchingOptions()
        match.num_threads, match.use_gpu = 1, False
        pycolmap.match_exhaustive(db, matching_options=match, device=pycolmap.Device.cpu)
        opts = pycolmap.IncrementalPipelineOptions()
        opts.num_threads = 1
        opts.random_seed = opts.mapper.random_seed = seed
        if relaxed:
            opts.mapper.init_min_num_inliers = 30
            opts.mapper.abs_pose_min_num_inliers = 15
        out = Path(d) / "sparse"
        out.mkdir()
        recs = pycolmap.incremental_mapping(db, images, out, opts)
        seconds = time.perf_counter() - t0
    T = np.full((V, 4, 4), np.nan)
    focal = float("nan")
    if recs:
        rec = max(recs.values(), key=lambda r: r.num_reg_images())
        for img in rec.images.values():
            if img.has_pose:
                M = np.eye(4)
                M[:3] = img.cam_from_world().matrix()
                T[names.index(img.name)] = np.linalg.inv(M)
                cam = rec.cameras[img.camera_id]
                focal = cam.focal_length_x / cam.width
    return T, focal, seconds


# -- scoring ---------------------------------------------------------------------------------
def pair_errors(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Pose error (degrees) of every pair i < j, 180 where a view is unposed (NaN)."""
    from iris_train.metrics import relative_pose_errors
    posed = np.isfinite(pred).all(axis=(1, 2))
    rot, trans = relative_pose_errors(np.where(posed[:, None, None], pred, np.eye(4)), gt)
    i, j = np.triu_indices(len(gt), 1)
    return np.where(posed[i] & posed[j], np.maximum(rot, trans), 180.0)


def score(pred, focal, seconds, scene: Scene) -> dict:
    e = pair_errors(pred, scene.world_from_cam)
    return {"scene": scene.name, "registered": int(np.isfinite(pred).all(axis=(1, 2)).sum()),
            "views": len(scene.photos), **{f"rpa@{t}": float(np.mean(e < t)) for t in THRESHOLDS},
            "focal_error": abs(focal / scene.focal - 1.0) if np.isfinite(focal) else None,
            "seconds": seconds}


def eval_protocol(scene: Scene) -> dict:
    """iris-eval's split, ours: references solved, targets located against them."""
    from iris_runtime.cameras import locate_photos, solve_cameras
    V = len(scene.photos)
    idx = np.round(np.linspace(0, V - 1, EVAL_FRAMES)).astype(int)
    photos = working_copies([scene.photos[k] for k in idx])
    t0 = time.perf_counter()
    s = solve_cameras([photos[k] for k in REFERENCES], DEPTH_RANGE)
    pred = np.full((EVAL_FRAMES, 4, 4), np.nan)
    pred[list(REFERENCES)] = s.world_from_cam
    if s.root >= 0:
        T, ok = locate_photos(s.point_map, s.focal, s.image_size, [photos[k] for k in TARGETS])
        pred[list(TARGETS)] = T
    seconds = time.perf_counter() - t0
    sub = Scene(scene.name, photos, scene.world_from_cam[idx], scene.focal)
    return score(pred, s.focal / s.image_size[1], seconds, sub)


# -- report ----------------------------------------------------------------------------------
def summarise(rows: list[dict]) -> dict:
    out = {k: float(np.mean([r[k] for r in rows])) for k in (f"rpa@{t}" for t in THRESHOLDS)}
    out["registered"] = float(np.mean([r["registered"] / r["views"] for r in rows]))
    focal = [r["focal_error"] for r in rows if r["focal_error"] is not None]
    out["focal_error_median"] = float(np.median(focal)) if focal else None
    out["seconds_median"] = float(statistics.median(r["seconds"] for r in rows))
    out["scenes"] = len(rows)
    return out


def markdown(results: dict, command: str) -> str:
    lines = ["# Camera solve: ours against COLMAP", "", f"`{command}`", "",
             "Means over scenes (RPA, registered fraction of views), medians (focal error, "
             "seconds on one thread).", ""]
    for dataset, per_solver in results["datasets"].items():
        lines += [f"## {dataset}", "",
                  "| solver | protocol | registered | RPA@5 | RPA@15 | RPA@30 | focal error | s |",
                  "|---|---|---|---|---|---|---|---|"]
        for key, res in per_solver.items():
            s = res["summary"]
            fe = "–" if s["focal_error_median"] is None else f"{s['focal_error_median']:.3f}"
            lines.append(f"| {key} | {res['protocol']} | {s['registered']:.3f} | "
                         f"{s['rpa@5']:.3f} | {s['rpa@15']:.3f} | {s['rpa@30']:.3f} | {fe} | "
                         f"{s['seconds_median']:.2f} |")
        lines += ["", "<details><summary>per scene</summary>", "",
                  "| solver | scene | registered | RPA@5 / @15 / @30 | focal error | s |",
                  "|---|---|---|---|---|---|"]
        for key, res in per_solver.items():
            for r in res["scenes"]:
                fe = "–" if r["focal_error"] is None else f"{r['focal_error']:.3f}"
                lines.append(f"| {key} | {r['scene']} | {r['registered']}/{r['views']} | "
                             f"{r['rpa@5']:.3f} / {r['rpa@15']:.3f} / {r['rpa@30']:.3f} | {fe} | "
                             f"{r['seconds']:.2f} |")
        lines += ["", "</details>", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--datasets", default="heldout,wide,castle")
    ap.add_argument("--solvers", default="ours,colmap,colmap-relaxed")
    ap.add_argument("--protocol", default="all,eval", help="all and/or eval (eval: ours only)")
    ap.add_argument("--seeds", type=int, default=3, help="COLMAP RANSAC seeds per scene")
    ap.add_argument("--limit", type=int, default=None, help="scenes per dataset")
    ap.add_argument("--out", type=Path, default=None, help="write OUT.json and OUT.md")
    args = ap.parse_args(argv)
    import cv2
    cv2.setNumThreads(1)
    solvers = args.solvers.split(",")
    protocols = args.protocol.split(",")
    results = {"command": "python benchmarks/camera_solve.py " + " ".join(argv or sys.argv[1:]),
               "datasets": {}}
    for dataset in args.datasets.split(","):
        scenes = list(DATASETS[dataset]())[:args.limit]
        per = {}
        for solver in solvers:
            if solver == "ours":
                runs = [("ours", "all", lambda s: score(*solve_ours(s.photos), s))] \
                    if "all" in protocols else []
                if "eval" in protocols:
                    runs.append(("ours", "eval", eval_protocol))
            else:
                runs = [(f"{solver} seed {seed}", "all",
                         lambda s, seed=seed: score(*solve_colmap(s.photos, seed,
                                                                  solver == "colmap-relaxed"), s))
                        for seed in range(args.seeds)] if "all" in protocols else []
            for key, protocol, run in runs:
                rows = []
                for scene in scenes:
                    rows.append(run(scene))
                    r = rows[-1]
                    print(f"{dataset:8s} {key:24s} {protocol:4s} {r['scene']:40s} "
                          f"{r['registered']}/{r['views']} {r['rpa@5']:.3f} {r['rpa@15']:.3f} "
                          f"{r['rpa@30']:.3f} f {r['focal_error'] if r['focal_error'] is None else round(r['focal_error'], 3)} "
                          f"{r['seconds']:.2f}s", flush=True)
                per[f"{key} ({protocol})"] = {"protocol": protocol, "scenes": rows,
                                              "summary": summarise(rows)}
        results["datasets"][dataset] = per
        for key, res in per.items():
            print(f"== {dataset} {key}: {json.dumps(res['summary'])}", flush=True)
    if args.out is not None:
        from iris_runtime.fileio import atomic_write_bytes
        atomic_write_bytes(args.out.with_suffix(".json"), json.dumps(results, indent=1).encode())
        atomic_write_bytes(args.out.with_suffix(".md"),
                           markdown(results, results["command"]).encode())
    return 0


if __name__ == "__main__":
    sys.exit(main())
