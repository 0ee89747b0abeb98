"""The measurements behind the epipolar camera choices (docs/TRAINING.md, "Epipolar cameras").

Four studies; ``rpa``, ``scale`` and ``order`` under iris-eval's protocol (8 frames; references
0, 2, 3, 5, 7 solved from their own photos; targets 1, 4, 6 located against them; RPA over all
pairs):

    python scripts/epipolar_study.py rpa synthetic:validation
    python scripts/epipolar_study.py rpa synthetic:heldout --variants search/ties/pnp,true/ties/pnp
    python scripts/epipolar_study.py scale MODEL_DIR synthetic:validation --scenes 8
    python scripts/epipolar_study.py order MODEL_DIR synthetic:validation --scenes 16
    python scripts/epipolar_study.py flow synthetic:validation --scenes 6

``rpa`` needs no model: per variant FOCAL/TRANSLATION/LOCATE with FOCAL "search" (the grid search)
or "true" (the scene's) or a number (that fx/W for every scene), TRANSLATION "ties" (baselines tied by triangulated depth, the default),
"baselines" (pair directions only) or "cross", LOCATE "pnp" or "lines"; ``--texture-min`` sets the match filter
``iris_runtime.epipolar.TEXTURE_MIN`` (0 keeps every flow vector). ``scale`` runs iris-eval
(``cameras="epipolar"``) through an exported model once per camera scale rule of
``iris_runtime.epipolar.refine_cameras`` ("depth", "model") and prints the Rand figures.
``order`` splits the Seq/Rand PSNR gap of an exported model into its two causes: per scene it
renders the targets in Seq order, in Rand order, and in each order with the cameras the *other*
order solved (re-based on this order's view 0, same focal and unit). If the swapped-camera rows
follow the cameras rather than the order, the gap comes from the camera solve, not the renderer.
``flow`` scores the correspondences of OpenCV's dense flows (through ``flow_matches``' checks)
and of SIFT against the true ones (rendered depth, true cameras): why DIS (medium) is the flow.
"""
from __future__ import annotations

import argparse
import functools
import json
import sys
import time

import numpy as np


def rpa_study(data: str, variants: list[str], limit: int | None, order: str = "rand",
              texture_min: float | None = None) -> dict:
    import iris_runtime.epipolar as E
    from iris_train.evaluate import load_scenes, presentation_order, split_frames
    from iris_train.metrics import rpa

    scenes, total = load_scenes(data, (64, 64), limit=limit)
    refs, targets = split_frames(8)
    if texture_min is not None:                    # the match filter of this run
        E.TEXTURE_MIN = texture_min
    scores = {v: [] for v in variants}
    for index, scene in enumerate(scenes):
        ref_order, target_order = presentation_order(order, refs, targets, index)
        # The solve sees the references in canonical order, rooted at the presented view 0,
        # as refine_cameras does.
        ro = [ref_order[k] for k in E.canonical_order(scene.images[ref_order])]
        root, to = ro.index(ref_order[0]), list(target_order)
        images = scene.images
        matches = E.all_flow_matches(images[ro])
        for v in variants:
            focal, translation, locate = v.split("/")
            f = (scene.K[0, 0] / images.shape[2] if focal == "true"
                 else E.search_focal(matches, *images.shape[1:3], pairs="all") if focal == "all"
                 else None if focal == "search" else float(focal))
            pp = E.pairwise_poses(images[ro], f, matches=matches)
            if translation == "ties":
                T_ref, _, _ = E.solve_views(images[ro], pp, matches, root=root)
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


def order_study(model_dir: str, data: str, limit: int | None, threads: int | None) -> dict:
    import dataclasses

    from iris_runtime import IrisRuntime
    from iris_runtime.geometry import intrinsics_from_focal
    from iris_train.evaluate import load_scenes, presentation_order, split_frames
    from iris_train.metrics import psnr

    rt = IrisRuntime(model_dir, threads=threads)
    scenes, total = load_scenes(data, rt.image_size, limit=limit)
    refs, targets = (list(x) for x in split_frames(8))
    rows = {k: [] for k in ("seq", "rand", "seq|rand cameras", "rand|seq cameras")}
    for index, scene in enumerate(scenes):
        images = scene.images
        gt = images[targets].astype(np.float64) / 255.0
        enc, cams = {}, {}
        for order in ("seq", "rand"):
            ro, to = presentation_order(order, refs, targets, index)
            s = rt.encode(images[ro], cameras="epipolar")
            pred = np.tile(np.eye(4), (8, 1, 1))                   # frame order
            pred[ro] = s.world_from_cam
            pred[to] = rt.locate(s, images[to])                   # epipolar, as in iris-eval
            enc[order], cams[order] = (s, ro), (pred, s.focal)
        for order, other in (("seq", "seq"), ("rand", "rand"), ("seq", "rand"), ("rand", "seq")):
            s, ro = enc[order]
            pred, focal = cams[other]
            pred = np.linalg.inv(pred[ro[0]]) @ pred              # re-based on this order's view 0
            scene_o = dataclasses.replace(s, world_from_cam=pred[ro], focal=focal,
                                          K=intrinsics_from_focal(focal, *rt.image_size))
            p = float(np.mean([psnr(np.clip(rt.render(scene_o, pred[t], depth=True).image_float,
                                            0, 1), g) for t, g in zip(targets, gt)]))
            rows[order if order == other else f"{order}|{other} cameras"].append(p)
        print(f"scene {index + 1}/{total}: " + ", ".join(f"{k} {v[-1]:.2f}" for k, v in rows.items()),
              flush=True)
    out = {k: {"psnr": float(np.mean(v)), "per_scene": [round(x, 2) for x in v]}
           for k, v in rows.items()}
    out["gap seq-rand"] = out["seq"]["psnr"] - out["rand"]["psnr"]
    out["gap with the same cameras (seq cams)"] = out["seq"]["psnr"] - out["rand|seq cameras"]["psnr"]
    out["gap with the same cameras (rand cams)"] = out["seq|rand cameras"]["psnr"] - out["rand"]["psnr"]
    return out


#: Dense flows of the ``flow`` study: OpenCV's, on the upsampled grey images of ``flow_matches``.
def _flows():
    import cv2

    def dis(preset, fine=False):
        def calc(g0, g1):
            d = cv2.DISOpticalFlow_create(preset)
            if fine:
                d.setFinestScale(0)
                d.setGradientDescentIterations(25)
                d.setPatchSize(8)
                d.setPatchStride(3)
            return d.calc(g0, g1, None)
        return calc
    return {
        "dis": None,                                   # flow_matches' default, epipolar.dis_flow
        "dis-fine": dis(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM, fine=True),
        "dis-ultrafast": dis(cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST),
        "farneback": lambda g0, g1: cv2.calcOpticalFlowFarneback(g0, g1, None, 0.5, 5, 15, 5, 5,
                                                                 1.1, 0),
        "deepflow": lambda g0, g1: cv2.optflow.createOptFlow_DeepFlow().calc(g0, g1, None),
        "pcaflow": lambda g0, g1: cv2.optflow.createOptFlow_PCAFlow().calc(g0, g1, None),
        "sift": "sift",
    }


def _sift_matches(a, b):
    """Mutual nearest SIFT matches passing Lowe's ratio test (0.8) on the 4x upsampled grey
    photos -> (p, q) [N, 2] in model pixels (centres at +0.5)."""
    import cv2
    import iris_runtime.epipolar as E
    up = E.FLOW_UPSAMPLE
    H, W = a.shape[:2]
    grey = [cv2.resize(cv2.cvtColor(x, cv2.COLOR_RGB2GRAY), (W * up, H * up),
                       interpolation=cv2.INTER_CUBIC) for x in (a, b)]
    sift = cv2.SIFT_create(contrastThreshold=0.01)
    (k0, d0), (k1, d1) = (sift.detectAndCompute(g, None) for g in grey)
    if d0 is None or d1 is None or len(k0) < 2 or len(k1) < 2:
        return np.zeros((0, 2)), np.zeros((0, 2))
    bf = cv2.BFMatcher(cv2.NORM_L2)
    back = {m.queryIdx: m.trainIdx for m in bf.match(d1, d0)}
    good = [m for m, n in (x for x in bf.knnMatch(d0, d1, k=2) if len(x) == 2)
            if m.distance < 0.8 * n.distance and back.get(m.trainIdx) == m.queryIdx]
    p = np.array([k0[m.queryIdx].pt for m in good]).reshape(-1, 2)
    q = np.array([k1[m.trainIdx].pt for m in good]).reshape(-1, 2)
    return (p + 0.5) / up, (q + 0.5) / up


def flow_study(data: str, methods: list[str], limit: int | None) -> dict:
    """Correspondence accuracy per method against the truth (the rendered depth and true cameras):
    per pair of views 1, 2 and 4 apart (from views 0, 2, 4, 6), the matches within 0.5 px of the
    true correspondence among those that land on geometry ("good", and their fraction)."""
    import iris_runtime.epipolar as E
    from iris_train.evaluate import load_scenes

    scenes = list(load_scenes(data, (64, 64), limit=limit)[0])
    flows = _flows()
    out = {}
    for m in methods:
        if m not in flows:
            raise SystemExit(f"flow: unknown method {m!r}; expected one of {sorted(flows)}")
        stats, t0 = {1: [], 2: [], 4: []}, time.perf_counter()
        for s in scenes:
            T, D, K = s.world_from_cam, s.depth, s.K
            H, W = s.images.shape[1:3]
            for gap, rows in stats.items():
                for i in range(0, 8 - gap, 2):
                    j = i + gap
                    a, b = s.images[i], s.images[j]
                    p, q = (_sift_matches(a, b) if flows[m] == "sift"
                            else E.flow_matches(a, b) if flows[m] is None
                            else E.flow_matches(a, b, flows[m]))
                    z = D[i].ravel()[E._cells(p, H, W)]
                    x = np.stack([(p[:, 0] - K[0, 2]) / K[0, 0], (p[:, 1] - K[1, 2]) / K[1, 1],
                                  np.ones(len(p))], 1) * z[:, None]
                    y = (x @ T[i, :3, :3].T + T[i, :3, 3] - T[j, :3, 3]) @ T[j, :3, :3]
                    with np.errstate(divide="ignore", invalid="ignore"):
                        qt = K[:2, :2] @ (y[:, :2] / y[:, 2:]).T + K[:2, 2:]
                    err = np.linalg.norm(q - qt.T, axis=1)[z > 0]
                    rows.append(((err < 0.5).sum(), (err < 0.5).mean() if len(err) else 0.0))
        out[m] = {"seconds": time.perf_counter() - t0, **{
            f"gap {g}": {"good": float(np.mean([r[0] for r in v])),
                         "fraction": float(np.mean([r[1] for r in v]))} for g, v in stats.items()}}
        print(m, json.dumps(out[m]), flush=True)
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
    a.add_argument("--texture-min", type=float, default=None,
                   help="epipolar.TEXTURE_MIN for this run (0: keep textureless flow vectors)")
    b = sub.add_parser("scale", help="iris-eval with epipolar cameras per scale rule")
    b.add_argument("model_dir")
    b.add_argument("data")
    b.add_argument("--rules", default="model,depth")
    b.add_argument("--scenes", type=int, default=None)
    b.add_argument("--threads", type=int, default=None)
    c = sub.add_parser("order", help="Seq/Rand PSNR gap: camera solve or renderer?")
    c.add_argument("model_dir")
    c.add_argument("data")
    c.add_argument("--scenes", type=int, default=None)
    c.add_argument("--threads", type=int, default=None)
    d = sub.add_parser("flow", help="correspondence accuracy of OpenCV's flows and SIFT")
    d.add_argument("data")
    d.add_argument("--methods", default="dis,dis-fine,dis-ultrafast,farneback,deepflow,pcaflow,sift")
    d.add_argument("--scenes", type=int, default=6)
    args = p.parse_args(argv)
    if args.study == "flow":
        res = flow_study(args.data, args.methods.split(","), args.scenes)
    elif args.study == "order":
        res = order_study(args.model_dir, args.data, args.scenes, args.threads)
    elif args.study == "rpa":
        res = rpa_study(args.data, args.variants.split(","), args.scenes, args.order,
                        args.texture_min)
    else:
        res = scale_study(args.model_dir, args.data, args.rules.split(","), args.scenes, args.threads)
    print(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
