"""``evaluate``: the protocol run over scenes, one step per function (prepare the frames, score the
photo baselines, pose the scene, render the targets, score and record)."""
from __future__ import annotations

import contextlib
import os
import warnings
from typing import Iterable

import numpy as np

from iris_runtime.errors import InputError

from ..metrics import depth_spearman, rpa
from .backends import backend_for, check_quality, focal_of
from .cameras import PosedScene, camera_panel, check_modes, pose_scene
from .protocol import (HEAD_RPA_KEYS, LOCATE_RPA_KEYS, ORDERS, RAND_SEED, DEFAULT_VIEWS,
                       REFERENCE_RPA_KEYS, RPA_KEYS, best_reference, locate_rpa,
                       nearest_reference, nvs_scores, presentation_order, reference_rpa,
                       split_frames)
from .report import save_grid
from .scenes import PreparedScene, prepare_scene

__all__ = ["evaluate", "depth_score"]

#: Pixel size (H, W) of the camera picture in ``--grid``.
_CAMERA_PANEL_SIZE = (450, 700)
_MODEL_KEYS = ("psnr", "ssim", *RPA_KEYS, *LOCATE_RPA_KEYS, "depth_spearman",
               *REFERENCE_RPA_KEYS, *HEAD_RPA_KEYS)
_POSE_KEYS = (*RPA_KEYS, *LOCATE_RPA_KEYS)
_IMAGE_BASELINES = ("best_reference", "nearest_reference", "mean_colour")
#: The baseline of ``--size``: the model-resolution render resized to the output size.
_UPSAMPLED = "upsampled"


def evaluate(model, scenes: Iterable, *, views: int = DEFAULT_VIEWS, seed: int = RAND_SEED,
             grid: str | os.PathLike | None = None, progress: bool = True,
             total: int | None = None, cameras: str | None = None, locate: str | None = None,
             grid_scene: int = 0, size: int | None = None, quality: str | None = None) -> dict:
    """Evaluate ``model`` (an ``IrisModel`` or an ``iris_runtime.IrisRuntime``) on ``scenes``.

    ``scenes``: objects with ``images`` uint8 ``[V, H, W, 3]`` (trajectory order) and
    ``world_from_cam`` ``[V, 4, 4]`` or None (no ground-truth cameras), optionally ``K`` (true
    intrinsics, needed by ``cameras="true"``), ``depth`` and ``meta``. Images of another size are
    brought to the model's resolution by ``iris_runtime.images.fit_to_model``. The Rand order of a
    scene is ``presentation_order("rand", ..., i, seed)`` with i its position in ``scenes``.
    ``grid``: write a PNG of scene ``grid_scene`` (default the first; Seq order). ``total``:
    number of scenes, for the progress bar.

    Returns ``{"seq": R, "rand": R}`` with ``R = {"model": {"psnr", "ssim", "rpa@5", "rpa@15",
    "rpa@30", "locate_rpa@5", "locate_rpa@15", "locate_rpa@30", "depth_spearman",
    "reference_rpa@5", ..., "head_reference_rpa@5", ...}, "baselines":
    {"best_reference": {"psnr", "ssim"}, "nearest_reference": {"psnr", "ssim"}, "mean_colour":
    {"psnr", "ssim"}, "identity_poses": {"rpa@5", ..., "locate_rpa@30"}}, "scenes": [...]}``:
    means over scenes (module docstring of ``iris_train.evaluate``; a value is None when no scene
    measures it), and one record per scene (``_scene_record``: its name, scores, baselines, the
    frames each baseline copied, and where its cameras came from). Raises ``InputError`` when no
    scene has ``views`` frames.

    ``cameras``: None (default): the cameras the model was trained with (an exported model's
    ``IrisRuntime.default_cameras``, a checkpoint's training config); "model"; "solve": the
    references' cameras (and focal) are the global camera solve of the reference images scaled
    to the model's units (``iris_runtime.cameras.replace_model_cameras``); "true": the data's own
    cameras (``cameras.true_cameras``: re-based on view 0, scaled by the solve's depth rule, the
    true focal). ``locate``: how the targets are posed, "model" (``locate``), "solve"
    (``iris_runtime.cameras.locate_views`` against the references' cameras; a target it cannot
    pose keeps the model's located pose) or "true" (only with ``cameras="true"``); default: the
    value of ``cameras``. With anything but model cameras each ``R`` also holds ``"cameras":
    {"references", "targets", "sources": {camera source: scenes}, "targets_epipolar": fraction
    of targets posed by the camera solve (the key keeps the solve's former name), "fallbacks": views that kept the camera head's camera
    where a solved one was asked for, "scenes_with_fallbacks"}``.

    ``reference_rpa@t``: RPA of the rendered cameras over the pairs of two references (with
    ``locate_rpa@t``'s pairs, all pairs). ``head_reference_rpa@t``: the same pairs posed by the
    camera head, where other cameras (``cameras`` "solve" or "true") replaced its own: the
    head's own score beside the cameras that replaced it (None with model cameras, where it
    equals ``reference_rpa@t``). References only: a scene's head cameras are its references'
    (the targets' poses come from ``locate``). ``grid``'s camera picture then draws the head's
    cameras too.

    ``size`` (S, ``iris-eval --size S``; a square model): the targets are rendered at S x S and
    scored against their photos brought to S (``scenes.to_output_size``: centre crop to a
    square, ``cv2.INTER_AREA``; ``InputError`` naming the photos' size where they are smaller
    than S); the references reach the encoder as photos at their own resolution
    (``scenes.prepare_scene``); cameras, split, orders and located poses as without it (a pose
    is rendered at S with the same normalised focal). Each ``R`` then also holds
    ``"output_size": [S, S]`` and ``"model_size": [H, W]``, the photo baselines are at S, and
    ``"baselines"`` (means and per scene) holds ``"upsampled": {"psnr", "ssim"}``: the render of
    the same pose at the model's resolution (clipped to [0, 1], as scored without ``size``)
    resized to S with ``cv2.INTER_CUBIC`` and clipped again. ``depth_spearman`` is the depth
    rendered at S against the true depth brought to S (nearest neighbour). ``grid`` shows the S
    images. ``quality``: a preset of ``iris_runtime.quality`` passed to every render
    (``IrisRuntime.render(..., quality=)``, the model-resolution one of "upsampled" too); a
    checkpoint takes "exact" only. Without either, the protocol and its numbers are the ones
    above, bit for bit.
    """
    backend = backend_for(model)
    cameras, locate = check_modes(backend.default_cameras, cameras, locate)
    check_quality(backend, quality)
    out_size = _output_size(backend, size)
    if grid is not None and not (0 <= grid_scene and (total is None or grid_scene < total)):
        raise InputError(f"grid_scene: expected a scene position in [0, {total}), got {grid_scene}")
    run = _Evaluation(backend, views, seed, cameras, locate, out_size, quality, grid, grid_scene)
    bar = _progress_bar(scenes, total, progress)
    with _eval_mode(model), contextlib.closing(bar):
        for index, scene in enumerate(bar):
            run.add_scene(index, scene)
    return run.results()


class _Evaluation:
    """One ``evaluate`` run: its checked settings, and scene by scene the records of each
    presentation order (``_OrderRecord``) and the counts of scenes used and skipped."""

    def __init__(self, backend, views: int, seed: int, cameras: str, locate: str,
                 out_size: tuple[int, int] | None, quality: str | None,
                 grid: str | os.PathLike | None, grid_scene: int):
        self.backend, self.views, self.seed = backend, views, seed
        self.cameras, self.locate = cameras, locate
        self.out_size, self.quality = out_size, quality
        self.grid, self.grid_scene = grid, grid_scene
        self.refs, self.targets = split_frames(views)
        self.runs = {order: _OrderRecord() for order in ORDERS}
        self.n_used, self.n_skipped = 0, 0

    def add_scene(self, index: int, scene) -> None:
        """Score ``scene`` (position ``index`` in ``scenes``) in every order, its photo baselines
        computed once for both; a scene with fewer than ``views`` frames is counted skipped."""
        out_size = self.out_size
        prepared = prepare_scene(scene, self.views, self.backend.image_size, index,
                                 **({} if out_size is None else {"output_size": out_size}))
        if prepared is None:
            self.n_skipped += 1
            return
        self.n_used += 1
        baselines = _image_baselines(prepared, self.refs, self.targets)
        for order in ORDERS:
            self._add_order(index, prepared, order, baselines)

    def _add_order(self, index: int, prepared: PreparedScene, order: str,
                   baselines: dict) -> None:
        """One scene in one order: posed (``pose_scene``), its targets rendered and scored into
        ``runs[order]`` (``_scene_record``), and the grid written when it is the Seq order of
        scene ``grid_scene``."""
        backend, refs, targets = self.backend, self.refs, self.targets
        out_size, quality = self.out_size, self.quality
        ref_order, target_order = presentation_order(order, refs, targets, index, self.seed)
        try:
            posed = pose_scene(backend, prepared, ref_order, target_order, self.cameras,
                               self.locate)
        except InputError as exc:
            raise InputError(f"scene {index} ({prepared.name}): {exc}") from None
        where = f"scene {index} ({order})"
        rgb, depth = _render_targets(backend, posed, targets, where, out_size, quality)
        upsampled = None if out_size is None else _upsampled(
            backend, posed, targets, where, out_size, quality)
        self.runs[order].add(_scene_record(index, prepared, posed, rgb, depth, refs, targets,
                                           baselines, upsampled))
        if self.grid is not None and order == "seq" and index == self.grid_scene:
            _write_grid(self.grid, prepared, posed, rgb, depth, refs, targets, backend)

    def results(self) -> dict:
        """``evaluate``'s ``{"seq": R, "rand": R}``, or ``InputError`` when no scene had
        ``views`` frames; a warning counts the scenes skipped."""
        views, n_skipped, out_size = self.views, self.n_skipped, self.out_size
        if self.n_used == 0:
            raise InputError(f"no scene with at least {views} frames to evaluate"
                             + (f" ({n_skipped} skipped)" if n_skipped else ""))
        if n_skipped:
            warnings.warn(f"iris-eval: skipped {n_skipped} scene(s) with fewer than {views} frames")
        cameras, locate = self.cameras, self.locate
        report_cameras = cameras != "model" or locate != "model"
        results = {order: self.runs[order].summary(cameras, locate, report_cameras)
                   for order in ORDERS}
        if out_size is not None:
            results = {order: {"output_size": list(out_size),
                               "model_size": list(self.backend.image_size), **R}
                       for order, R in results.items()}
        return results


def _progress_bar(scenes: Iterable, total: int | None, progress: bool):
    """``scenes`` under iris-eval's progress bar (tqdm; silent without ``progress``)."""
    from tqdm import tqdm
    return tqdm(scenes, total=total, desc="iris-eval", unit="scene", disable=not progress,
                dynamic_ncols=True)


def _output_size(backend, size) -> tuple[int, int] | None:
    """``(S, S)`` of ``size`` S, or None; ``InputError`` for a non-integer or S < 1, or a model
    that is not square (S x S renders would change its field of view)."""
    if size is None:
        return None
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
        raise InputError(f"size: expected an integer output size >= 1, got {size!r}")
    H, W = backend.image_size
    if H != W:
        raise InputError(f"size: S x S outputs need a square model, this one is {W}x{H} "
                         "(width x height)")
    return int(size), int(size)


@contextlib.contextmanager
def _eval_mode(model):
    training = getattr(model, "training", None)
    if training:
        model.eval()
    try:
        yield
    finally:
        if training:
            model.train()


def _image_baselines(prepared: PreparedScene, refs, targets) -> dict:
    """The photo baselines of one scene (the same frames in either order, so computed once):
    ``{name: {"psnr", "ssim", "frames"} or None}``, "frames" the reference copied per target."""
    gt = prepared.gt_images
    targets_gt = gt[list(targets)]
    mean_rgb = gt[list(refs)].reshape(-1, 3).mean(0)
    out = {"mean_colour": nvs_scores([np.broadcast_to(mean_rgb, g.shape) for g in targets_gt],
                                     targets_gt),
           "nearest_reference": None}
    best = best_reference(gt, refs, targets)
    out["best_reference"] = {**nvs_scores(gt[best], targets_gt), "frames": best}
    if prepared.poses is not None:
        nearest = nearest_reference(prepared.poses, refs, targets)
        out["nearest_reference"] = {**nvs_scores(gt[nearest], targets_gt), "frames": nearest}
    return out


def _render_targets(backend, posed: PosedScene, targets, where: str, size=None, quality=None):
    """The targets rendered at their poses (at the model's size or ``size``), clipped to [0, 1],
    and their soft depth."""
    poses = posed.world_from_cam[list(targets)]
    if size is None and quality is None:
        rgb, depth = backend.render(posed.encoded, poses)
    else:
        rgb, depth = backend.render(posed.encoded, poses, size=size, quality=quality)
    if not (np.isfinite(rgb).all() and np.isfinite(posed.world_from_cam).all()):
        raise InputError(f"{where}: the model returned NaN or inf (poses or colours); nothing to "
                         "score")
    return np.clip(rgb, 0.0, 1.0), depth


def _upsampled(backend, posed: PosedScene, targets, where: str, size, quality) -> np.ndarray:
    """The ``upsampled`` baseline of ``--size``: each target rendered at the model's resolution
    (``_render_targets``: clipped to [0, 1]), resized to ``size`` (S, S) with
    ``cv2.INTER_CUBIC``, clipped to [0, 1] again (cubic overshoots). ``[N, S, S, 3]`` float64."""
    import cv2
    rgb, _ = _render_targets(backend, posed, targets, f"{where}, at the model's resolution",
                             None, quality)
    H, W = size
    return np.stack([np.clip(cv2.resize(np.ascontiguousarray(im), (W, H),
                                        interpolation=cv2.INTER_CUBIC), 0.0, 1.0) for im in rgb])


def depth_score(pred_depths: np.ndarray, true_depths: np.ndarray) -> float | None:
    """A scene's ``depth_spearman``: the mean of ``iris_train.metrics.depth_spearman`` over its
    targets' depth maps ``[N, H, W]`` where it is defined (not nan), or None."""
    values = [depth_spearman(p, t) for p, t in zip(pred_depths, true_depths)]
    values = [v for v in values if np.isfinite(v)]
    return float(np.mean(values)) if values else None


def _flag_list(flags, frames):
    return None if flags is None else [bool(flags[f]) for f in frames]


def _scene_record(index: int, prepared: PreparedScene, posed: PosedScene, rgb, depth, refs,
                  targets, baselines: dict, upsampled: np.ndarray | None = None) -> dict:
    """One scene in one order: ``{"index", "name", "model": {...}, "baselines": {...},
    "cameras": {"source", "references", "references_solved", "targets", "targets_located",
    "fallbacks", "scale", "scale_source", "principal_offset"}}`` (flags per frame of
    ``references`` / ``targets``; the last three for true cameras only, the principal point's
    offset from the centre in pixels of the model image, which the renderer takes as centred).
    ``upsampled`` (``--size``): the targets' upsampled renders, scored into
    ``baselines["upsampled"]``."""
    targets_a = list(targets)
    model = dict.fromkeys(_MODEL_KEYS)
    model.update(nvs_scores(rgb, prepared.gt_images[targets_a]))
    if prepared.true_depth is not None:
        model["depth_spearman"] = depth_score(depth, prepared.true_depth[targets_a])
    identity = None
    if prepared.poses is not None:
        # RPA does not depend on the world frame, so frame order serves both orders.
        model.update({**rpa(posed.world_from_cam, prepared.poses),
                      **locate_rpa(posed.world_from_cam, prepared.poses, targets),
                      **reference_rpa(posed.world_from_cam, prepared.poses, refs)})
        if posed.head_world_from_cam is not None:
            model.update(reference_rpa(posed.head_world_from_cam, prepared.poses, refs,
                                       prefix="head_reference_"))
        eye = np.broadcast_to(np.eye(4), prepared.poses.shape)
        identity = {**rpa(eye, prepared.poses), **locate_rpa(eye, prepared.poses, targets)}
    if upsampled is not None:
        baselines = {_UPSAMPLED: nvs_scores(upsampled, prepared.gt_images[targets_a]),
                     **baselines}
    return {
        "index": index, "name": prepared.name, "model": model,
        "baselines": {**baselines, "identity_poses": identity},
        "cameras": {"source": posed.source, "references": list(refs),
                    "references_solved": _flag_list(posed.references_solved, refs),
                    "targets": targets_a, "targets_located": _flag_list(posed.targets_located, targets),
                    "fallbacks": posed.fallbacks, "scale": posed.scale,
                    "scale_source": posed.scale_source,
                    "principal_offset": None if posed.principal_offset is None
                    else [float(x) for x in posed.principal_offset]}}


class _OrderRecord:
    """The scene records of one order and their means."""

    def __init__(self):
        self.scenes: list[dict] = []

    def add(self, record: dict) -> None:
        self.scenes.append(record)

    def _mean(self, get) -> float | None:
        values = [v for v in (get(s) for s in self.scenes) if v is not None]
        return float(np.mean(values)) if values else None

    def _means(self, keys, where) -> dict:
        def value(s, k):
            d = where(s)
            return None if d is None else d.get(k)
        return {k: self._mean(lambda s, k=k: value(s, k)) for k in keys}

    def summary(self, cameras: str, locate: str, report_cameras: bool) -> dict:
        names = _IMAGE_BASELINES
        if any(_UPSAMPLED in s["baselines"] for s in self.scenes):
            names = (_UPSAMPLED, *names)
        out = {"model": self._means(_MODEL_KEYS, lambda s: s["model"]),
               "baselines": {name: self._means(("psnr", "ssim"), lambda s, n=name: s["baselines"][n])
                             for name in names}}
        out["baselines"]["identity_poses"] = self._means(
            _POSE_KEYS, lambda s: s["baselines"]["identity_poses"])
        if report_cameras:
            sources: dict[str, int] = {}
            located = []                    # targets posed by the camera solve
            for s in self.scenes:
                c = s["cameras"]
                sources[c["source"]] = sources.get(c["source"], 0) + 1
                if locate != "true":
                    located.extend(c["targets_located"] or [False] * len(c["targets"]))
            out["cameras"] = {"references": cameras, "targets": locate,
                              "sources": dict(sorted(sources.items())),
                              "targets_epipolar": float(np.mean(located)) if located else None,
                              "fallbacks": sum(s["cameras"]["fallbacks"] for s in self.scenes),
                              "scenes_with_fallbacks": sum(s["cameras"]["fallbacks"] > 0
                                                           for s in self.scenes)}
        out["scenes"] = self.scenes
        return out


def _write_grid(path, prepared: PreparedScene, posed: PosedScene, rgb, depth, refs, targets,
                backend) -> None:
    targets_a = list(targets)
    save_grid(path, prepared.gt_images[list(refs)], prepared.gt_images[targets_a], rgb, depth,
              backend.depth_range, refs, targets,
              true_depths=None if prepared.true_depth is None else prepared.true_depth[targets_a],
              cameras=camera_panel(posed.world_from_cam, focal_of(posed.encoded), prepared.poses,
                                   prepared.stored_K, _CAMERA_PANEL_SIZE, source=posed.source,
                                   head_poses=posed.head_world_from_cam,
                                   head_focal=posed.head_focal))
