"""The measurements behind the epipolar camera choices (docs/TRAINING.md, "Epipolar cameras").

Two studies, both under iris-eval's protocol (8 frames; references 0, 2, 3, 5, 7 in Rand order
solved from their own photos; targets 1, 4, 6 located against them; RPA over all pairs):

    python scripts/epipolar_study.py rpa synthetic:validation
    python scripts/epipolar_study.py rpa synthetic:heldout --variants search/ties/pnp,true/ties/pnp
    python scripts/epipolar_study.py scale MODEL_DIR synthetic:validation --scenes 8

``rpa`` needs no model: per variant FOCAL/TRANSLATION/LOCATE with FOCAL "search" (the grid search)
or "true" (the scene's), TRANSLATION "ties" (baselines tied by triangulated depth, the default),
"baselines" (pair directions only) or "cross", LOCATE "pnp" or "lines". ``scale`` runs iris-eval
(``cameras="epipolar"``) through an exported model once per camera scale rule of
``iris_runtime.epipolar.refine_cameras`` ("depth", "model") and prints the Rand figures.
"""
from __future__ import annotations

import argparse
import functools
import json
import sys
import time

import numpy as np


def rpa_study(data: str, variants: list[str], limit: int | None, order: str = "rand") -> dict:
    import iris_runtime.epipolar as E
    from iris_train.evaluate import load_scenes, presentation_order, split_frames
    from iris_train.metrics import rpa

    scenes, total = load_scenes(data, (64, 64), limit=limit)
    refs, targets = split_frames(8)
    scores = {v: [] for v in variants}
    for index, scene in enumerate(scenes):
        ref_order, target_order = presentation_order(order, refs, targets, index)
        ro, to = list(ref_order), list(target_order)
        images = scene.images
        matches = E.all_flow_matches(images[ro])
        for v in variants:
            focal, translation, locate = v.split("/")
            f = (scene.K[0, 0] / images.shape[2] if focal == "true"
                 else E.search_focal(matches, *images.shape[1:3], pairs="all") if focal == "all"
                 else None)
            pp = E.pairwise_poses(images[ro], f, matches=matches)
            if translation == "ties":
                T_ref, _, _ = E.solve_views(images[ro], pp, matches)
            else:
                T_ref = E.solve_global(pp, translation=translation).world_from_cam
            T_ref = np.where(np.isfinite(T_ref), T_ref, np.eye(4))   # unsolved: identity
            pred = np.tile(np.eye(4), (8, 1, 1))
            pred[ro] = T_ref
            T, ok = E.locate_views(images[ro], T_ref, pp.focal, images[to], method=locate)
            pred[to] = np.where(ok[:, None, None], T, np.eye(4))
            r = rpa(pred, scene.world_from_cam)
            scores[v].append((r["rpa@15"], r["rpa@30"], pp.focal))
        print(f"scene {index + 1}/{total}: " + ", ".join(
            f"{v} {scores[v][-1][0]:.3f}/{scores[v][-1][1]:.3f}" for v in variants), flush=True)
    return {v: {"rpa@15": float(np.mean([s[0] for s in scores[v]])),
                "rpa@30": float(np.mean([s[1] for s in scores[v]])),
                "per_scene_rpa@30": [round(s[1], 3) for s in scores[v]],
                "per_scene_focal": [round(s[2], 3) for s in scores[v]]} for v in variants}


def scale_study(model_dir: str, data: str, rules: list[str], limit: int | None,
                threads: int | None) -> dict:
    import iris_runtime.epipolar as E
    from iris_runtime import IrisRuntime
    from iris_train.evaluate import evaluate, load_scenes

    rt = IrisRuntime(model_dir, threads=threads)
    scenes = list(load_scenes(data, rt.image_size, limit=limit)[0])
    original = E.refine_cameras
    out = {}
    try:
        for rule in rules:
            E.refine_cameras = functools.partial(original, scale=rule)
            t0 = time.perf_counter()
            r = evaluate(rt, scenes, cameras="epipolar", progress=False)["rand"]
            out[rule] = {"psnr": r["model"]["psnr"], "ssim": r["model"]["ssim"],
                         "rpa@15": r["model"]["rpa@15"], "rpa@30": r["model"]["rpa@30"],
                         "depth_spearman": r["model"]["depth_spearman"],
                         "nearest_reference_psnr": r["baselines"]["nearest_reference"]["psnr"],
                         "seconds": time.perf_counter() - t0}
            print(json.dumps({rule: out[rule]}), flush=True)
    finally:
        E.refine_cameras = original
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="study", required=True)
    a = sub.add_parser("rpa", help="camera accuracy of solve/locate variants (no model)")
    a.add_argument("data", help="synthetic:validation, synthetic:heldout or a folder")
    a.add_argument("--variants", default="search/baselines/lines,search/ties/lines,search/ties/pnp")
    a.add_argument("--scenes", type=int, default=None)
    a.add_argument("--order", choices=("rand", "seq"), default="rand",
                   help="presentation order of the frames (iris-eval's Seq or Rand)")
    b = sub.add_parser("scale", help="iris-eval with epipolar cameras per scale rule")
    b.add_argument("model_dir")
    b.add_argument("data")
    b.add_argument("--rules", default="model,depth")
    b.add_argument("--scenes", type=int, default=None)
    b.add_argument("--threads", type=int, default=None)
    args = p.parse_args(argv)
    if args.study == "rpa":
        res = rpa_study(args.data, args.variants.split(","), args.scenes, args.order)
    else:
        res = scale_study(args.model_dir, args.data, args.rules.split(","), args.scenes, args.threads)
    print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
