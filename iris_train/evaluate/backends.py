"""One interface over the two things ``iris-eval`` evaluates: an ``IrisModel`` checkpoint run in
torch, and an exported model run by ``iris_runtime.IrisRuntime`` (numpy + onnxruntime).

Both backends: ``encode(images uint8 [V, H, W, 3])`` -> a scene whose references are exactly
those images, with the model's own cameras; ``poses(scene) -> [V, 4, 4]``; ``locate(scene,
references, queries) -> [Q, 4, 4]``, the model's own prediction; ``with_cameras(scene,
world_from_cam, focal)``: the same field maps rendered from other cameras (the solve's or the
data's, ``evaluate.cameras.pose_scene``), the camera head's kept beside them;
``head_cameras(scene) -> (world_from_cam [V, 4, 4], focal [2])`` those kept cameras of the head,
or None when the scene's cameras are the head's; ``render(scene, poses [N, 4, 4]) -> (rgb [N, H,
W, 3], depth [N, H, W])`` float64 at the model's resolution. ``default_cameras``: the cameras the
model was trained with, ``iris-eval``'s default.

``iris-eval --size S``: ``encode(photos, colour_size=(S, S))`` takes the reference photos at their
own resolution (a list of uint8 [h, w, 3], any sizes; the encoder sees them fitted to the model),
and ``render(scene, poses, size=(S, S), quality=...)`` renders at S. The runtime keeps and samples
the photos itself (``IrisRuntime.encode``); the checkpoint's explicit colours are sampled from the
reference photos brought to S (centre crop, ``cv2.INTER_AREA``) in place of the model-resolution
images (``Scene.images``; torch samples them at normalised coordinates, so any size serves).
"""
from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["TorchBackend", "RuntimeBackend", "backend_for", "focal_of", "check_quality"]


def check_quality(backend, quality) -> None:
    """``InputError`` unless ``quality`` is None or a preset of ``iris_runtime.quality``; a
    checkpoint (``TorchBackend``, which renders exactly) takes None or "exact" only."""
    if quality is None:
        return
    from iris_runtime.errors import InputError
    from iris_runtime.quality import QUALITY_PRESETS
    if not isinstance(quality, str) or quality not in QUALITY_PRESETS:
        raise InputError(f"quality: expected one of {list(QUALITY_PRESETS)}, got {quality!r}")
    if isinstance(backend, TorchBackend) and quality != "exact":
        raise InputError(f"quality: {quality!r} is a preset of the runtime; a checkpoint renders "
                         "exactly in torch (export it with iris-export to evaluate the presets)")


def focal_of(encoded) -> np.ndarray | None:
    """The normalised focal [fx/W, fy/H] of an encoded scene (torch or runtime), or None."""
    f = getattr(encoded, "focal", None)
    if f is None:
        return None
    if hasattr(f, "detach"):
        f = f.detach().cpu().double().numpy()
    return np.asarray(f, dtype=np.float64)


class TorchBackend:
    """``IrisModel`` in torch (a checkpoint)."""

    def __init__(self, model):
        self.model = model
        self.image_size = (model.cfg.image_height, model.cfg.image_width)
        self.depth_range = model.cfg.unit_range
        # A checkpoint loaded by load_evaluable knows the cameras it was trained with.
        self.default_cameras = getattr(model, "trained_cameras", "model")

    @staticmethod
    def _tensor(images: np.ndarray):
        import torch
        return torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float() / 255.0

    def encode(self, images, colour_size: tuple[int, int] | None = None):
        """``images`` uint8 [V, H, W, 3] at the model's size; with ``colour_size`` (``--size``)
        a list of photos of any size: fitted to the model for the encoder, and (explicit-colour
        models) brought to ``colour_size`` for the colours sampled at render time."""
        import torch
        if colour_size is None:
            with torch.no_grad():
                return self.model.encode(self._tensor(images))
        from iris_runtime.images import fit_to_model
        photos = [np.asarray(p) for p in images]
        model_in = np.stack([fit_to_model(p, *self.image_size)[0] for p in photos])
        with torch.no_grad():
            scene = self.model.encode(self._tensor(model_in))
        if scene.images is None:            # no explicit colour: the field maps are all
            return scene
        colours = np.stack([fit_to_model(p, *colour_size)[0] for p in photos])
        return dataclasses.replace(scene, images=self._tensor(colours).to(scene.images))

    def with_cameras(self, scene, world_from_cam: np.ndarray, focal: np.ndarray):
        import torch
        head_poses = (scene.world_from_cam if scene.encoder_world_from_cam is None
                      else scene.encoder_world_from_cam)
        head_focal = scene.focal if scene.encoder_focal is None else scene.encoder_focal
        return dataclasses.replace(
            scene, world_from_cam=torch.as_tensor(np.asarray(world_from_cam)).to(scene.world_from_cam),
            focal=torch.as_tensor(np.asarray(focal)).to(scene.focal),
            encoder_world_from_cam=head_poses, encoder_focal=head_focal)

    def poses(self, scene) -> np.ndarray:
        return scene.world_from_cam.detach().double().numpy()

    def head_cameras(self, scene) -> tuple[np.ndarray, np.ndarray] | None:
        if scene.encoder_world_from_cam is None:
            return None
        return (scene.encoder_world_from_cam.detach().double().numpy(),
                scene.encoder_focal.detach().double().numpy())

    def locate(self, scene, references: np.ndarray, queries: np.ndarray) -> np.ndarray:
        """The model's poses [Q, 4, 4] of ``queries`` in the frame of ``encode(references)``."""
        import torch
        with torch.no_grad():
            return self.model.locate(self._tensor(references), self._tensor(queries)).double().numpy()

    def render(self, scene, poses: np.ndarray, size: tuple[int, int] | None = None,
               quality: str | None = None):
        """At the model's size or ``size``; ``quality`` None or "exact" (torch renders exactly:
        presets are the runtime's, ``check_quality``)."""
        import torch
        check_quality(self, quality)
        H, W = self.image_size if size is None else size
        rgb, depth = self.model.render(scene, torch.as_tensor(poses, dtype=scene.field_maps.dtype), H, W)
        return rgb.double().numpy(), depth.double().numpy()


class RuntimeBackend:
    """An exported model run by ``iris_runtime.IrisRuntime`` (numpy + onnxruntime)."""

    def __init__(self, runtime):
        self.rt = runtime
        H, W = runtime.image_size
        self.image_size = (int(H), int(W))
        self.depth_range = runtime.unit_range
        self.default_cameras = getattr(runtime, "default_cameras", "model")

    def encode(self, images, colour_size: tuple[int, int] | None = None):
        """``images`` uint8 [V, H, W, 3], or (``colour_size``: ``--size``) a list of photos at
        their own resolution, which ``IrisRuntime.encode`` fits to the model and keeps for the
        colours it samples at render time (so ``colour_size`` is not needed here)."""
        if self.default_cameras == "model":     # (duck-typed runtimes need not know cameras=)
            return self.rt.encode(list(images))
        return self.rt.encode(list(images), cameras="model")

    def with_cameras(self, scene, world_from_cam: np.ndarray, focal: np.ndarray):
        """The same field maps and images with other cameras; ``encoder_focal`` keeps the
        encoder's focal so that ``IrisRuntime.locate`` still recognises the reference images,
        and ``encoder_world_from_cam`` the camera head's poses (``head_cameras``)."""
        from iris_runtime import geometry as G
        H, W = self.image_size
        focal = np.asarray(focal, dtype=np.float64)
        encoder_focal = scene.focal if scene.encoder_focal is None else scene.encoder_focal
        encoder_poses = (scene.world_from_cam if scene.encoder_world_from_cam is None
                         else scene.encoder_world_from_cam)
        return dataclasses.replace(scene, world_from_cam=np.asarray(world_from_cam, np.float64),
                                   focal=focal, K=G.intrinsics_from_focal(focal, H, W),
                                   encoder_focal=encoder_focal, camera_source="model",
                                   encoder_world_from_cam=encoder_poses)

    def poses(self, scene) -> np.ndarray:
        return np.asarray(scene.world_from_cam, dtype=np.float64)

    def head_cameras(self, scene) -> tuple[np.ndarray, np.ndarray] | None:
        # getattr: duck-typed runtimes' scenes need not carry the head's cameras.
        poses = getattr(scene, "encoder_world_from_cam", None)
        if poses is None:
            return None
        focal = getattr(scene, "encoder_focal", None)
        return (np.asarray(poses, dtype=np.float64),
                np.asarray(scene.focal if focal is None else focal, dtype=np.float64))

    def locate(self, scene, references: np.ndarray, queries: np.ndarray) -> np.ndarray:
        """The model's poses [Q, 4, 4] of ``queries`` in ``scene``'s frame (the scene keeps its
        references). Asked on the scene with ``camera_source`` "model": ``IrisRuntime.locate``
        of a solved scene would run the solve's location itself, which ``evaluate`` runs once
        where it is asked for (and records which targets it posed)."""
        if getattr(scene, "camera_source", "model") != "model" and dataclasses.is_dataclass(scene):
            scene = dataclasses.replace(scene, camera_source="model")
        return np.asarray(self.rt.locate(scene, list(queries)), dtype=np.float64)

    def render(self, scene, poses: np.ndarray, size: tuple[int, int] | None = None,
               quality: str | None = None):
        """``IrisRuntime.render`` of each pose at the model's size or ``size`` (height, width),
        with ``quality`` (a preset name, passed through) when given."""
        H, W = self.image_size if size is None else (int(size[0]), int(size[1]))
        knobs = {} if quality is None else {"quality": quality}
        rgbs, depths = [], []
        for pose in poses:
            result = self.rt.render(scene, pose, height=H, width=W, depth=True, **knobs)
            image = getattr(result, "image_float", None)
            if image is None:
                image = np.asarray(getattr(result, "image", result), dtype=np.float64) / 255.0
            rgbs.append(np.asarray(image, dtype=np.float64))
            depth = getattr(result, "depth", None)
            depths.append(np.zeros((H, W)) if depth is None else np.asarray(depth, dtype=np.float64))
        return np.stack(rgbs), np.stack(depths)


def backend_for(model):
    """``TorchBackend`` for an ``IrisModel``, else ``RuntimeBackend`` (an ``IrisRuntime`` or an
    object with its interface)."""
    try:
        from ..model import IrisModel
    except ImportError:          # torch missing: only the runtime path is possible
        IrisModel = ()
    if isinstance(model, IrisModel):
        return TorchBackend(model)
    return RuntimeBackend(model)
