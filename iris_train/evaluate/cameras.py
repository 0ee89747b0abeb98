"""Where the cameras of an evaluated scene come from: the model's, the camera solve's, or the
data's own ("true"), for the references (the encoded scene) and for the targets (located).

``true_cameras`` puts a scene's own cameras in the frame and unit the renderer works in, by the
rule the camera solve uses (``iris_runtime.cameras.solve_cameras``): re-based on view 0 of the
presentation, and scaled so that the median depth of the reference images' triangulated points
lies ``DEPTH_TARGET`` of the way into the model's [near, far]. The points are the solve's own
matches triangulated with the true cameras (``iris_runtime.cameras.point_map_from_cameras``),
never stored depth maps: the same photos then get the same unit whichever cameras they are
rendered from, so ``--cameras true`` and ``--cameras solve`` differ only in the cameras.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from iris_runtime.errors import InputError
from iris_runtime.manifest import CAMERAS, camera_name

#: Triangulated observations needed to scale true cameras by their depth; with fewer, the mean
#: baseline is set to DEFAULT_BASELINE.
MIN_POINTS = 20
#: Mean distance between camera centres of the 16 held-out synthetic scenes' true cameras, in the
#: renderer's unit (depths in [0.1, 1.0]).
DEFAULT_BASELINE = 0.14

from .backends import focal_of
from .scenes import PreparedScene

__all__ = ["CAMERA_MODES", "LOCATE_MODES", "TrueCameras", "true_cameras", "PosedScene",
           "pose_scene", "check_modes", "camera_panel"]

#: ``--cameras``: where the references' cameras come from (the runtime's, or the data's own).
CAMERA_MODES = (*CAMERAS, "true")
#: ``--locate``: where the targets' cameras come from.
LOCATE_MODES = CAMERA_MODES


def check_modes(default_cameras: str, cameras: str | None, locate: str | None) -> tuple[str, str]:
    """``(cameras, locate)`` with the defaults filled in (cameras: the model's trained ones;
    locate: as cameras); ``InputError`` for an unknown mode, or for true target cameras with
    other reference cameras (they would lie in another frame)."""
    cameras = camera_name(default_cameras if cameras is None else cameras)
    if cameras not in CAMERA_MODES:
        raise InputError(f"cameras: expected one of {list(CAMERA_MODES)}, got {cameras!r}")
    locate = cameras if locate is None else camera_name(locate)
    if locate not in LOCATE_MODES:
        raise InputError(f"locate: expected one of {list(LOCATE_MODES)}, got {locate!r}")
    if locate == "true" and cameras != "true":
        raise InputError(f"locate: 'true' needs cameras='true' (true target poses lie in the true "
                         f"cameras' frame), got cameras={cameras!r}")
    return cameras, locate


@dataclass(frozen=True)
class TrueCameras:
    """A scene's own cameras in the renderer's frame and unit.

    world_from_cam:   float64 [V, 4, 4]  every frame's camera, view ``root`` = I, centres scaled
    focal:            float64 [2]        (fx/W, fy/H) at the model's resolution, the references' mean
    scale:            the factor applied to the re-based true centres
    scale_source:     "matches" (the depth rule), "baseline" (too few matches triangulate: the
                      references' mean baseline becomes ``DEFAULT_BASELINE``) or "none"
                      (all reference centres coincide: nothing to scale)
    principal_offset: float64 [2]  the references' mean principal point minus the image centre,
                      pixels of the model image (the renderer assumes a centred one)
    """
    world_from_cam: np.ndarray
    focal: np.ndarray
    scale: float
    scale_source: str
    principal_offset: np.ndarray


def true_cameras(images: np.ndarray, world_from_cam: np.ndarray, K: np.ndarray,
                 references: Sequence[int], depth_range: tuple[float, float],
                 photos: Sequence[np.ndarray] | None = None,
                 photo_K: np.ndarray | None = None) -> TrueCameras:
    """The true cameras of one scene for rendering from ``references`` (presentation order).

    images uint8 [V, H, W, 3] at the model's resolution; world_from_cam [V, 4, 4] the true poses
    (any world frame and unit); K [V, 3, 3] (or [3, 3]) the true intrinsics in pixels of those
    images; depth_range (near, far) of the model. The frame is rooted at ``references[0]``; the
    scale comes from the references alone (sorted, so every presentation order gets the same),
    their matches found in ``photos`` (the frames at their own resolution, one size, with
    ``photo_K`` [V, 3, 3] in their pixels) where given, as the camera solve does, else in
    ``images``.
    """
    from iris_runtime.cameras import DEPTH_TARGET
    from iris_runtime.cameras.locate import point_map_from_cameras
    images = np.asarray(images)
    T = np.asarray(world_from_cam, dtype=np.float64)
    V, H, W = images.shape[:3]
    K = np.broadcast_to(np.asarray(K, dtype=np.float64), (V, 3, 3))
    refs = [int(r) for r in references]
    if T.shape != (V, 4, 4) or not np.isfinite(T).all() or not np.isfinite(K).all():
        raise InputError(f"world_from_cam, K: expected finite [{V}, 4, 4] and [{V}, 3, 3], got "
                         f"{T.shape} and {K.shape}")
    near, far = (float(x) for x in depth_range)
    rebased = np.linalg.inv(T[refs[0]]) @ T
    rebased[refs[0]] = np.eye(4)
    focal = np.array([K[refs, 0, 0].mean() / W, K[refs, 1, 1].mean() / H])
    offset = np.array([K[refs, 0, 2].mean() - W / 2, K[refs, 1, 2].mean() - H / 2])
    ordered = sorted(refs)
    match_photos, match_fx = list(images[ordered]), float(focal[0]) * W
    if photos is not None and photo_K is not None:
        chosen = [np.asarray(photos[r]) for r in ordered]
        if all(p.shape == chosen[0].shape for p in chosen):
            pK = np.broadcast_to(np.asarray(photo_K, dtype=np.float64), (V, 3, 3))
            match_photos, match_fx = chosen, float(pK[ordered, 0, 0].mean())
    # Depths are measured in a frame rooted at the lowest reference and in units of the
    # references' mean baseline, not in the data's frame and unit: neither changes them in exact
    # arithmetic, and the triangulation (float32 inside) then sees the same numbers for every
    # presentation order, world frame and unit.
    measured = np.linalg.inv(T[ordered[0]]) @ T[ordered]
    i, j = np.triu_indices(len(ordered), 1)
    unit = float(np.linalg.norm(measured[i, :3, 3] - measured[j, :3, 3], axis=1).mean()) or 1.0
    measured[:, :3, 3] /= unit
    points = point_map_from_cameras(match_photos, measured, match_fx)
    cam_from_world = np.linalg.inv(measured)[points.view]                      # [N, 4, 4]
    depths = unit * (np.einsum("nj,nj->n", cam_from_world[:, 2, :3], points.points[points.point])
                     + cam_from_world[:, 2, 3])
    depths = depths[depths > 0]
    if len(depths) >= MIN_POINTS:
        scale = (near + DEPTH_TARGET * (far - near)) / float(np.median(depths))
        how = "matches"
    elif np.ptp(rebased[refs, :3, 3], axis=0).max() > 0:
        centres = rebased[refs, :3, 3]
        i, j = np.triu_indices(len(centres), 1)
        scale = DEFAULT_BASELINE / float(np.linalg.norm(centres[i] - centres[j], axis=1).mean())
        how = "baseline"
    else:
        scale, how = 1.0, "none"
    out = rebased.copy()
    out[:, :3, 3] *= scale
    return TrueCameras(out, focal, float(scale), how, offset)


@dataclass
class PosedScene:
    """One scene encoded from its references and with every frame posed, in frame order.

    encoded:          the backend's scene (references in presentation order)
    world_from_cam:   float64 [V, 4, 4]  the cameras rendered from / at (references and targets)
    source:           "model", "solve", "refined", "mixed" (the Scene's ``camera_source``) or
                      "true"
    references_solved: bool [V] over frames (False for targets), which reference cameras the
                      camera solve (or the data) gave; None with the model's cameras
    targets_located:  bool [V] over frames, which targets ``cameras.locate_views`` posed (or the
                      data, with ``locate="true"``); None with the model's locate
    fallbacks:        views that were to get a solved camera and kept the camera head's
    scale, scale_source, principal_offset: of ``true_cameras`` (None for the other modes)
    head_world_from_cam: float64 [V, 4, 4] over frames, the camera head's cameras of the
                      references where other cameras replaced them (``cameras`` "solve" or
                      "true"), in the head's own frame and unit; the targets' rows are NaN (the
                      scene the head posed holds the references only). None with the model's
                      cameras (then ``world_from_cam`` is the head's)
    head_focal:       float64 [2] the head's focal (fx/W, fy/H) beside ``head_world_from_cam``
    """
    encoded: object
    world_from_cam: np.ndarray
    source: str
    references_solved: np.ndarray | None
    targets_located: np.ndarray | None
    fallbacks: int
    scale: float | None = None
    scale_source: str | None = None
    principal_offset: np.ndarray | None = None
    head_world_from_cam: np.ndarray | None = None
    head_focal: np.ndarray | None = None


def pose_scene(backend, scene: PreparedScene, ref_order: Sequence[int],
               target_order: Sequence[int], cameras: str, locate: str) -> PosedScene:
    """Encode ``scene``'s references alone (``ref_order``) and pose every frame.

    The model sees ``scene.images``; the camera solve sees ``scene.photos``, the frames at their
    own resolution, as ``IrisRuntime.encode(photos, cameras="solve")`` does with a user's.
    With ``scene.output_size`` (``iris-eval --size``) the references are encoded from their
    photos (``backend.encode(photos, colour_size=...)``: the encoder sees them fitted to the
    model, which ``scene.images`` then are, and the render samples their colours); every other
    step is the same.
    References: the model's cameras, the solve's (``replace_model_cameras``: a view it cannot
    pose keeps the model's camera), the model's refined by the photos (``refine_model_cameras``)
    or ``true_cameras`` (needs the scene's true poses and K, else
    ``InputError``). Targets: the model's ``locate``; ``"solve"``: posed against the solve's
    points with its cameras fixed (``CameraSolve.locate``, as ``IrisRuntime.locate``), or with model
    or true reference cameras against those (``locate_views`` at the model's resolution), the
    model's pose kept for a target that cannot be posed; or the true cameras. Where the
    references' cameras are not the model's, the model's are kept beside them
    (``PosedScene.head_world_from_cam``, from the backend's ``head_cameras``).
    """
    images = scene.images
    V = images.shape[0]
    ref_order, target_order = list(ref_order), list(target_order)
    pred = np.empty((V, 4, 4))
    truth = _scene_true_cameras(backend, scene, ref_order) if "true" in (cameras, locate) \
        else None
    encoded = _encode_references(backend, scene, ref_order)
    encoded, source, refs_solved, solve = _reference_cameras(backend, encoded, scene, ref_order,
                                                             cameras, truth)
    pred[ref_order] = backend.poses(encoded)
    head_poses, head_focal = _head_cameras(backend, encoded, ref_order, V)
    if locate == "true":
        pred[target_order] = truth.world_from_cam[target_order]
        located = np.ones(len(target_order), dtype=bool)
    else:
        pred[target_order], located = _locate_targets(backend, encoded, scene, ref_order,
                                                      target_order, pred[ref_order], cameras,
                                                      locate, solve)
    fallbacks = 0
    if cameras in ("solve", "refined"):
        fallbacks += int((~refs_solved).sum())
    if locate in ("solve", "refined"):
        fallbacks += int((~located).sum())
    return PosedScene(
        encoded, pred, source, _over_frames(refs_solved, ref_order, V),
        _over_frames(located, target_order, V), fallbacks,
        None if truth is None else truth.scale, None if truth is None else truth.scale_source,
        None if truth is None else truth.principal_offset, head_poses, head_focal)


def _scene_true_cameras(backend, scene: PreparedScene, ref_order: list[int]) -> TrueCameras:
    """``true_cameras`` of ``scene`` for the references ``ref_order``, or ``InputError`` when the
    scene has no true poses and K."""
    if scene.poses is None or scene.K is None:
        raise InputError("cameras: 'true' needs the data's own cameras, and this scene has "
                         "none (a folder needs transforms.json or COLMAP text files)")
    return true_cameras(scene.images, scene.poses, scene.K, ref_order, backend.depth_range,
                        scene.photos, scene.photo_K)


def _encode_references(backend, scene: PreparedScene, ref_order: list[int]):
    """The backend's scene of the references ``ref_order`` alone, with the model's cameras."""
    if scene.output_size is None:
        return backend.encode(scene.images[ref_order])
    # --size: the reference photos at their own resolution, as a user hands them over
    return backend.encode([scene.photos[r] for r in ref_order], colour_size=scene.output_size)


def _reference_cameras(backend, encoded, scene: PreparedScene, ref_order: list[int],
                       cameras: str, truth: TrueCameras | None
                       ) -> tuple[object, str, np.ndarray | None, object]:
    """The references' cameras of mode ``cameras`` put in ``encoded``: ``(encoded, source,
    references_solved, solve)``, ``references_solved`` bool [R] over ``ref_order`` (None with the
    model's cameras) and ``solve`` the ``CameraSolve`` behind solved cameras (else None)."""
    if cameras == "true":
        encoded = backend.with_cameras(encoded, truth.world_from_cam[ref_order], truth.focal)
        return encoded, "true", np.ones(len(ref_order), dtype=bool), None
    if cameras not in ("solve", "refined"):
        return encoded, "model", None, None
    from iris_runtime.cameras import (canonical_start, refine_model_cameras,
                                      replace_model_cameras)
    images, photos = scene.images, scene.photos
    ref_photos = [photos[r] for r in ref_order]
    poses, focal = backend.poses(encoded), focal_of(encoded)
    if cameras == "refined":             # as IrisRuntime.encode: the head in canonical order
        def head(perm):
            again = backend.encode(images[ref_order][perm])
            return backend.poses(again), focal_of(again)
        poses, focal = canonical_start(ref_photos, poses, focal, head)
        cams = refine_model_cameras(ref_photos, poses, focal, backend.image_size,
                                    backend.depth_range)
    else:
        cams = replace_model_cameras(ref_photos, poses, focal, backend.image_size,
                                     backend.depth_range)
    encoded = backend.with_cameras(encoded, cams.world_from_cam, cams.focal)
    refs_solved = np.array([st != "unposed" for st in cams.status], dtype=bool)
    return encoded, cams.source, refs_solved, cams.solve


def _head_cameras(backend, encoded, ref_order: list[int], V: int
                  ) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The camera head's cameras of the references where other cameras replaced them:
    ``(world_from_cam [V, 4, 4]`` over frames, NaN for the targets, ``focal [2])``, or
    ``(None, None)`` (the model's cameras)."""
    head = backend.head_cameras(encoded)
    if head is None:
        return None, None
    head_poses = np.full((V, 4, 4), np.nan)
    head_poses[ref_order] = head[0]
    return head_poses, head[1]


def _locate_targets(backend, encoded, scene: PreparedScene, ref_order: list[int],
                    target_order: list[int], ref_poses: np.ndarray, cameras: str, locate: str,
                    solve) -> tuple[np.ndarray, np.ndarray | None]:
    """The targets' poses ``[T, 4, 4]`` (``target_order``) by ``locate`` ("model", "solve" or
    "refined") and which of them the camera solve posed, ``bool [T]`` (None for "model"): the
    model's ``locate``, replaced where the solve poses a target: against the points of
    ``solve`` (the references' ``CameraSolve``, where they have one), or with model cameras
    against the references at ``ref_poses [R, 4, 4]``."""
    images, photos = scene.images, scene.photos
    poses = backend.locate(encoded, images[ref_order], images[target_order])
    if locate not in ("solve", "refined"):
        return poses, None
    from iris_runtime.cameras import locate_views
    if solve is not None:                 # as IrisRuntime.locate of a solved Scene
        epi, located = solve.locate([photos[t] for t in target_order])
    elif cameras != "model":           # view 0 unposed: the runtime keeps the model's
        epi, located = poses, np.zeros(len(target_order), dtype=bool)
    else:
        epi, located = locate_views(images[ref_order], ref_poses, float(focal_of(encoded)[0]),
                                    images[target_order])
    return np.where(located[:, None, None], epi, poses), located


def _over_frames(flags: np.ndarray | None, frames: Sequence[int], V: int) -> np.ndarray | None:
    if flags is None:
        return None
    out = np.zeros(V, dtype=bool)
    out[list(frames)] = np.asarray(flags, dtype=bool)
    return out


def camera_panel(pred_poses: np.ndarray, pred_focal, gt_poses: np.ndarray | None, gt_K,
                 size: tuple[int, int], *, source: str = "model",
                 head_poses: np.ndarray | None = None, head_focal=None) -> np.ndarray:
    """Picture of the cameras rendered from (``pred_poses [V, 4, 4]`` over frames, their
    ``pred_focal``; ``iris_runtime.camera_plot``), moved into the true frame (``gt_poses [V, 4,
    4]``, ``gt_K``) by a similarity alignment of their centres when true cameras are known.

    ``head_poses [V, 4, 4]`` (``PosedScene.head_world_from_cam``: the camera head's cameras where
    ``source`` cameras replaced them; NaN rows, the targets, are left out) are drawn too, in
    green, labelled with their frames, aligned on their own (each set has its own frame and
    unit): to the true cameras of the same frames, or without those to the rendered ones.
    """
    from iris_runtime.camera_plot import CameraSet, align_poses, draw_cameras
    others, head_scale = [], None
    if head_poses is not None:
        frames = np.flatnonzero(np.isfinite(head_poses).all(axis=(1, 2)))
        target = pred_poses if gt_poses is None else gt_poses
        aligned_head, (head_scale, _, _) = align_poses(head_poses[frames], target[frames])
        others.append(CameraSet(aligned_head, head_focal, "camera head (references)",
                                labels=frames))
    if gt_poses is None:
        if not others:
            return draw_cameras(pred_poses, pred_focal, size=size, title="predicted cameras")
        return draw_cameras(pred_poses, pred_focal, size=size, others=others,
                            names=(f"rendered ({source})", "true"),
                            title=f"camera head similarity-aligned to the rendered cameras "
                                  f"(scale {head_scale:.3g})")
    aligned, (s, _, _) = align_poses(pred_poses, gt_poses)
    if not others:
        return draw_cameras(aligned, pred_focal, reference=gt_poses, reference_focal=gt_K,
                            size=size, title=f"predicted cameras, similarity-aligned to the true "
                                             f"ones (scale {s:.3g})")
    return draw_cameras(aligned, pred_focal, reference=gt_poses, reference_focal=gt_K, size=size,
                        others=others, names=(f"rendered ({source})", "true"),
                        title=f"similarity-aligned to the true cameras: rendered (scale {s:.3g}), "
                              f"camera head (scale {head_scale:.3g})")
