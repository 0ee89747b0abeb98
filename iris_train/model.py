"""IRIS composed from its stages; checkpoints; the torch API shared by training, export, tests and
benchmarks.

    model = build_model(preset("tiny"))
    scene = model.encode(images)                     # images [V, 3, H, W] in [0, 1]: references
    rgb, depth = model.render(scene, poses, H, W)    # poses [N, 4, 4] world_from_cam
    poses = model.locate(images, queries)            # queries [Q, 3, H, W] -> [Q, 4, 4]

References and queries (``iris_train.encoder``): ``encode`` treats every image as a reference;
``locate(references, queries)`` runs the encoder once on references + queries with the queries
isolated (``is_reference = [True] * V + [False] * Q``) and returns the queries' poses in the
references' frame. The references' features and cameras are the same with or without queries, and
queries never see each other, so ``locate`` does not change ``encode(references)`` and locating Q
photos at once equals locating them one by one (up to float rounding).

Checkpoints are a plain dict (format tag, config dict, state dict, training info) loaded with
``torch.load(..., weights_only=True)``: no pickled classes, nothing executed on load.
"""
from __future__ import annotations

import dataclasses
import os
import pickle
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn as nn

from iris_runtime.errors import IrisError
from iris_runtime.fileio import atomic_write

from . import geometry as G
from .camera_head import CameraHead
from .config import ModelConfig
from .correlation import CorrelationCameraHead
from .encoder import FineFeatures, MultiViewEncoder
from .latent_field import LatentField
from .layers import MASK_FILL
from .ray_renderer import RayRenderer

CHECKPOINT_FORMAT = "iris-checkpoint"
CHECKPOINT_VERSION = 1
#: Feature grids up to this many cells are sampled with a dense interpolation matmul
#: (``geometry.sample_bilinear_dense``: faster forward and much faster backward than grid_sample
#: on CPU, and no GridSample in the exported renderer; same values), larger ones with grid_sample.
DENSE_SAMPLING_MAX_CELLS = 1024
#: The field-map samplers by name (``sampler_for`` picks one; the renderer graph records it).
SAMPLERS = {"dense": G.sample_bilinear_dense, "grid_sample": G.sample_bilinear}


def sampler_for(height: int, width: int) -> str:
    """The sampler of a ``height`` x ``width`` feature grid: "dense" up to
    ``DENSE_SAMPLING_MAX_CELLS`` cells, else "grid_sample"."""
    return "dense" if height * width <= DENSE_SAMPLING_MAX_CELLS else "grid_sample"


class CheckpointError(IrisError, ValueError):
    """A file that is not a readable IRIS checkpoint (foreign, truncated, corrupt, wrong version).
    An ``IrisError`` (the project's one base class) and a ``ValueError``."""


@dataclass(frozen=True)
class Scene:
    """What the encoder leaves for rendering: the latent scene memory S = {(f_k, K, P_k)}.

    ``field_maps [V, C', h, w]`` are the per-scene field maps (LatentField.prepare of the features;
    the name of the encoder graph's output and of ``iris_runtime.Scene.field_maps``),
    ``world_from_cam [V, 4, 4]`` the predicted poses (view 0 = I), ``focal [2]`` (fx/W, fy/H) and
    ``image_size`` (H, W) the model's resolution; ``images [V, 3, H, W]`` in [0, 1] the reference
    photos (needed by models with ``explicit_rgb``, None otherwise). When ``world_from_cam`` and
    ``focal`` are other cameras than the camera head's (``iris-eval --cameras``),
    ``encoder_world_from_cam [V, 4, 4]`` and ``encoder_focal [2]`` keep the head's, as
    ``iris_runtime.Scene`` does; None when the cameras are the head's. ``principal_offset [2]``
    (analysis only: the model and the runtime assume a centred principal point) moves every
    view's principal point by that many pixels of the model's image, e.g. to render a synthetic
    scene at its true intrinsics; None: centred.
    """
    field_maps: torch.Tensor
    world_from_cam: torch.Tensor
    focal: torch.Tensor
    image_size: tuple[int, int]
    images: torch.Tensor | None = None
    encoder_world_from_cam: torch.Tensor | None = None
    encoder_focal: torch.Tensor | None = None
    principal_offset: torch.Tensor | None = None

    @property
    def num_views(self) -> int:
        return self.field_maps.shape[0]

    def intrinsics(self, height: int | None = None, width: int | None = None) -> torch.Tensor:
        """``K [3, 3]`` for an image of (height, width) pixels, as the runtime's
        ``Scene.intrinsics``: another aspect than the model's keeps the focal in pixels of the
        model's image scaled to the shorter side and widens the view."""
        H, W = self.image_size
        h, w = height or H, width or W
        if h * W == w * H:
            K = G.intrinsics_from_focal(self.focal, h, w)
        else:
            scale = min(h / H, w / W)
            K = G.intrinsics_from_focal(self.focal, H * scale, W * scale).clone()
            K[0, 2], K[1, 2] = w / 2.0, h / 2.0
        if self.principal_offset is None:
            return K
        K = K.clone()
        K[:2, 2] = K[:2, 2] + self.principal_offset.to(K.dtype) * min(h / H, w / W)
        return K

    def subset(self, indices) -> "Scene":
        """Keep only these views as references, in the same camera frame."""
        idx = torch.as_tensor(list(indices), dtype=torch.long)
        return dataclasses.replace(self, field_maps=self.field_maps[idx],
                                   world_from_cam=self.world_from_cam[idx],
                                   images=None if self.images is None else self.images[idx],
                                   encoder_world_from_cam=None if self.encoder_world_from_cam
                                   is None else self.encoder_world_from_cam[idx])

    def project_samples(self, origins: torch.Tensor, directions: torch.Tensor,
                        depths: torch.Tensor, colours: bool | None = None) -> "RaySamples":
        """The samples ``origins + depths * directions`` (``origins, directions [R, 3]``,
        ``depths [R, S]``) projected into every view of the scene (Algorithm 1's projection,
        cue and mask) -> ``RaySamples``. ``colours``: also sample the reference photos' RGB at
        the projections (default: when the scene carries its photos)."""
        H, W = self.image_size
        points = origins[:, None, :] + depths[..., None] * directions[:, None, :]      # [R, S, 3]
        cam_from_world = G.invert_pose(self.world_from_cam)
        uv, z, _ = G.project_points(points, self.intrinsics(), cam_from_world, H, W)    # [V, R, S, .]
        weight = G.validity(uv, z, H, W)                                                 # [V, R, S]
        grid = G.pixels_to_grid(uv, H, W)
        cues = G.geometric_cue(points, origins[:, None, :], self.world_from_cam[:, :3, 3])  # [R, S, V, 4]
        if colours is None:
            colours = self.images is not None
        if colours and self.images is None:
            raise ValueError("scene.images: this model (explicit_rgb) needs the reference photos")
        rgb = G.sample_bilinear(self.images, grid) if colours else None                 # [V, R, S, 3]
        return RaySamples(self.field_maps, grid, cues.permute(2, 0, 1, 3), weight, points, directions,
                          rgb)


@dataclass(frozen=True)
class RaySamples:
    """Ray samples projected into a scene's V reference views, view-major: exactly the inputs of
    the exported renderer graph, in its order (``iris_runtime.io_spec.RENDERER``; the runtime
    builds the same in numpy). ``mask`` is the sample's validity weight in the view
    (``geometry.validity``: 1 in the image, fading to 0 just outside it, 0 behind the camera);
    ``colours`` (explicit-colour models only) is each view's RGB at the sample's projection."""
    field_maps: torch.Tensor            # [V, C', h, w]
    grid: torch.Tensor                  # [V, R, S, 2] grid_sample coordinates
    cues: torch.Tensor                  # [V, R, S, 4] geometric cue
    mask: torch.Tensor                  # [V, R, S] validity weights in [0, 1]
    positions: torch.Tensor             # [R, S, 3]
    directions: torch.Tensor            # [R, 3]
    colours: torch.Tensor | None = None  # [V, R, S, 3] or None


def blend_views(colours: torch.Tensor, mask: torch.Tensor, cos: torch.Tensor,
                blend_angle: float) -> torch.Tensor:
    """Each sample's reference colour over the views, ``colours [V, ..., 3]``, validity ``mask
    [V, ...]``, ``cos [V, ...]`` the cue's cosine between target and view rays ->
    ``[..., 3]``: the validity-weighted mean, or with ``blend_angle`` > 0 each view also weighted
    by ``exp((cos - 1) / blend_angle)`` (``iris_runtime.colour.mean_colour``, its twin, says why
    and how a sample seen by few views still fades)."""
    m = mask.to(colours.dtype)
    if not blend_angle:
        return (colours * m[..., None]).sum(0) / m.sum(0).clamp_min(1.0)[..., None]
    # The common factor exp((c - 1) / blend_angle), c the best cosine of a seeing view, cancels.
    # Views that do not see the sample are pushed down by MASK_FILL (an add, not a Where: the
    # fast renderer graph has none); where no view sees it, cos - best is huge, clamped to 0,
    # and the mask zeroes the weights as the numpy twin's best = 1 does.
    unseen = (m <= 0).to(cos.dtype) * MASK_FILL
    best = (cos + unseen).amax(0, keepdim=True).detach()
    a = m * torch.exp((cos - best).clamp_max(0.0) / blend_angle)
    total = a.sum(0)
    return ((colours * a[..., None]).sum(0) / total.clamp_min(1e-30)[..., None]
            * m.sum(0).clamp_max(1.0)[..., None])


class IrisModel(nn.Module):
    def __init__(self, cfg: ModelConfig, encoder: MultiViewEncoder,
                 camera_head: CameraHead | CorrelationCameraHead,
                 field: LatentField, renderer: RayRenderer):
        super().__init__()
        self.cfg = cfg
        self.encoder = encoder
        self.camera_head = camera_head
        self.field = field
        self.renderer = renderer
        # cfg.camera_encoder: the camera head's own encoder (build_model adds it).
        self.camera_encoder: MultiViewEncoder | None = None
        # cfg.map_scale > 1: the field's features at the finer grid (build_model adds it).
        self.fine_features: FineFeatures | None = None

    # -- encoding ---------------------------------------------------------------------------
    def encode_batch(self, images: torch.Tensor, is_reference: torch.Tensor | None = None):
        """``images [B, V, 3, H, W]``, ``is_reference`` bool ``[V]`` or ``[B, V]`` (None: all
        references; view 0 must be one) -> features ``[B, V, D, *cfg.field_grid]``, poses
        ``[B, V, 4, 4]`` (view 0 = I), focal ``[B, 2]``. Reference outputs never depend on the
        query views."""
        if is_reference is not None and not bool(is_reference[..., 0].all()):
            raise ValueError("is_reference: view 0 is the canonical frame and must be a reference")
        return self.encode_stages(images, is_reference)

    def encode_stages(self, images: torch.Tensor, is_reference: torch.Tensor | None):
        """``encode_batch`` without its input check (what the exported graph traces): the
        encoder's features, and the camera head's cameras from the camera tokens of its own
        encoder where the model has one (``cfg.camera_encoder``), else of the same encoder."""
        features, camera_tokens = self.encoder(images, is_reference)
        if self.fine_features is not None:
            features = self.fine_features(features, images)
        if self.camera_encoder is not None:
            return (features, *self.camera_stages(images, is_reference))
        # The correlation head also reads the images (each view against view 0, a reference).
        world_from_cam, focal = self.camera_head(camera_tokens, images)
        return features, world_from_cam, focal

    def camera_stages(self, images: torch.Tensor, is_reference: torch.Tensor | None):
        """``encode_stages``' cameras alone, for a model whose camera head reads an encoder of its
        own (``cfg.camera_encoder``): the field's encoder is not run (the exported
        "encoder_cameras" graph)."""
        if self.camera_encoder is None:
            raise ValueError("camera_stages: this model's camera head reads the field's encoder "
                             "(config.camera_encoder is false)")
        _, camera_tokens = self.camera_encoder(images, is_reference)
        return self.camera_head(camera_tokens, images)

    def _check_images(self, images: torch.Tensor, name: str) -> None:
        cfg = self.cfg
        if images.ndim != 4 or images.shape[1:] != (3, cfg.image_height, cfg.image_width) \
                or images.shape[0] == 0:
            raise ValueError(f"{name}: expected [V, 3, {cfg.image_height}, {cfg.image_width}] with "
                             f"V >= 1, got {tuple(images.shape)}")

    def encode(self, images: torch.Tensor) -> Scene:
        """``images [V, 3, H, W]`` in [0, 1] at the model's resolution, all references -> Scene."""
        cfg = self.cfg
        self._check_images(images, "images")
        features, world_from_cam, focal = self.encode_batch(images[None])
        return Scene(self.field.prepare(features[0]), world_from_cam[0], focal[0],
                     (cfg.image_height, cfg.image_width), images if cfg.explicit_rgb else None)

    def locate(self, references: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
        """Poses of ``queries [Q, 3, H, W]`` in the frame of ``references [V, 3, H, W]`` (both in
        [0, 1] at the model's resolution) -> ``world_from_cam [Q, 4, 4]``, the frame of
        ``encode(references)`` (reference 0 = I). One encoder run over V + Q views with the queries
        isolated; each query sees the references and itself only."""
        self._check_images(references, "references")
        self._check_images(queries, "queries")
        V, Q = references.shape[0], queries.shape[0]
        is_reference = torch.arange(V + Q, device=references.device) < V
        images = torch.cat([references, queries.to(references)])
        _, world_from_cam, _ = self.encode_batch(images[None], is_reference)
        return world_from_cam[0, V:]

    # -- rendering --------------------------------------------------------------------------
    def render_rays(self, scene: Scene, origins: torch.Tensor, directions: torch.Tensor,
                    depths: torch.Tensor, need_weights: bool = True):
        """Render rays ``origins, directions [R, 3]`` with sample depths ``[R, S]`` from the
        scene's reference views -> ``rgb [R, 3]``, ``weights [R, S]`` (None unless need_weights)."""
        s = scene.project_samples(origins, directions, depths, colours=self.cfg.explicit_rgb)
        return self.render_samples(s.field_maps, s.grid, s.cues, s.mask, s.positions, s.directions,
                                   s.colours, need_weights=need_weights)

    def render_samples(self, field_maps: torch.Tensor, grid: torch.Tensor, cues: torch.Tensor,
                       mask: torch.Tensor, positions: torch.Tensor, directions: torch.Tensor,
                       colours: torch.Tensor | None = None, *, need_weights: bool = True,
                       sampler: str | None = None):
        """``render_rays`` after the projection: the fields of ``RaySamples`` (the renderer
        graph's inputs, view-major) -> ``rgb [R, 3]``, ``weights [R, S]``."""
        f, mean_colour = self.field_from_samples(field_maps, grid, cues, mask, colours,
                                                 sampler=sampler)
        # A sample's weight: its best view's (0: seen by no view, masked out of the ray).
        return self.renderer(f, positions, directions, mask.amax(0), need_weights, mean_colour)

    def field_at(self, scene: Scene, origins: torch.Tensor, directions: torch.Tensor,
                 depths: torch.Tensor):
        """The latent field at the ray samples (Algorithm 1): ``origins, directions [R, 3]``,
        ``depths [R, S]`` -> point features ``f [R, S, W]``, ``points [R, S, 3]``, validity
        ``mask [R, S, V]`` (the sample's validity weight in reference view k) and, with ``explicit_rgb``, each
        sample's mean reference colour over the views that see it ``[R, S, 3]`` (else None)."""
        s = scene.project_samples(origins, directions, depths, colours=self.cfg.explicit_rgb)
        f, mean_colour = self.field_from_samples(s.field_maps, s.grid, s.cues, s.mask, s.colours)
        return f, s.positions, s.mask.permute(1, 2, 0), mean_colour

    def field_from_samples(self, field_maps: torch.Tensor, grid: torch.Tensor, cues: torch.Tensor,
                           mask: torch.Tensor, colours: torch.Tensor | None = None, *,
                           sampler: str | None = None):
        """The latent field from projected samples (view-major, as in ``RaySamples``): sample
        ``field_maps`` at ``grid`` (``sampler``: a name of ``SAMPLERS``; default ``sampler_for``
        the maps' grid), run the field -> ``f [R, S, W]`` and, with ``explicit_rgb``, each sample's
        mean colour over the views that see it ``[R, S, 3]`` (else None)."""
        V, R, S = mask.shape
        sample = SAMPLERS[sampler or sampler_for(*field_maps.shape[-2:])]
        sampled = sample(field_maps, grid)                                              # [V, R, S, C']
        point_colours = mean_colour = None
        if self.cfg.explicit_rgb:
            if colours is None:
                raise ValueError("colours: this model (explicit_rgb) needs the reference RGB at "
                                 "the samples, [V, R, S, 3]")
            mean_colour = blend_views(colours, mask, cues[..., 3], self.cfg.blend_angle)  # [R, S, 3]
            point_colours = colours.permute(1, 2, 0, 3).reshape(R * S, V, 3)
        # The field is point-major: [R*S, V, ...].
        f = self.field(sampled.permute(1, 2, 0, 3).reshape(R * S, V, -1),
                       cues.permute(1, 2, 0, 3).reshape(R * S, V, 4),
                       mask.permute(1, 2, 0).reshape(R * S, V), point_colours)
        return f.reshape(R, S, -1), mean_colour

    @torch.no_grad()
    def render(self, scene: Scene, world_from_cam: torch.Tensor, height: int | None = None,
               width: int | None = None, chunk: int = 4096):
        """Render target poses ``world_from_cam [N, 4, 4]`` -> ``rgb [N, H, W, 3]``, ``depth [N, H, W]``.

        Deterministic bin-centre samples; intrinsics are the scene's shared focal scaled to
        (height, width); rays in chunks of ``chunk`` so memory stays bounded.
        """
        cfg = self.cfg
        if world_from_cam.ndim != 3 or world_from_cam.shape[1:] != (4, 4):
            raise ValueError(f"world_from_cam: expected target poses [N, 4, 4], got {tuple(world_from_cam.shape)}")
        height = height or cfg.image_height
        width = width or cfg.image_width
        dtype, device = scene.field_maps.dtype, scene.field_maps.device
        K = scene.intrinsics(height, width)
        uv = G.pixel_centres(height, width, dtype=dtype, device=device)
        rgbs, depths_out = [], []
        for pose in world_from_cam.to(device=device, dtype=dtype):
            origins, directions = G.rays_from_pixels(uv, K, pose)
            rgb = torch.empty(height * width, 3, dtype=dtype, device=device)
            depth = torch.empty(height * width, dtype=dtype, device=device)
            for start in range(0, height * width, chunk):
                sl = slice(start, start + chunk)
                z = G.sample_depths(cfg.near, cfg.far, cfg.samples, origins[sl].shape[0], dtype=dtype,
                                    device=device)
                rgb[sl], w = self.render_rays(scene, origins[sl], directions[sl], z)
                depth[sl] = (w * z).sum(-1)
            rgbs.append(rgb.reshape(height, width, 3))
            depths_out.append(depth.reshape(height, width))
        return torch.stack(rgbs), torch.stack(depths_out)


def build_model(cfg: ModelConfig) -> IrisModel:
    """The one place that builds IRIS from its config."""
    # Built in this order (the encoder first): a seeded token-head model gets the same weights
    # as before ``camera_head`` existed.
    encoder = MultiViewEncoder(cfg)
    head = CorrelationCameraHead(cfg) if cfg.camera_head == "correlation" else CameraHead(cfg)
    model = IrisModel(cfg, encoder, head, LatentField(cfg), RayRenderer(cfg))
    if cfg.camera_encoder:          # built last: the other stages draw the weights they did
        model.camera_encoder = MultiViewEncoder(cfg)
    if cfg.map_scale > 1:
        model.fine_features = FineFeatures(cfg)
    return model


# -- checkpoints ------------------------------------------------------------------------------
def save_checkpoint(path: str | os.PathLike, model: IrisModel, **extra) -> None:
    """Write ``{format, version, config, model, **extra}`` atomically (temp file + rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION,
               "config": model.cfg.to_dict(), "model": model.state_dict(), **extra}
    atomic_write(path, lambda f: torch.save(payload, f))


def read_checkpoint(path: str | os.PathLike) -> dict:
    """Load a checkpoint dict safely (``weights_only=True``); typed error for anything else."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {str(path)!r}: no such file")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:   # truncated zip, foreign pickle, random bytes, empty file...
        if isinstance(exc, pickle.UnpicklingError):
            # torch's own message suggests weights_only=False: never the right advice for a file
            # we could not vouch for.
            reason = "it holds objects other than tensors and plain containers; refused unread"
        else:
            reason = (str(exc).splitlines() or [""])[0][:200]   # an empty file raises EOFError('')
        raise CheckpointError(f"checkpoint {str(path)!r} is not a readable IRIS checkpoint "
                              f"({type(exc).__name__}: {reason})") from None
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"checkpoint {str(path)!r} is not an IRIS checkpoint "
                              f"(expected format {CHECKPOINT_FORMAT!r})")
    if payload.get("version") != CHECKPOINT_VERSION:
        raise CheckpointError(f"checkpoint {str(path)!r} has version {payload.get('version')!r}; "
                              f"this code reads version {CHECKPOINT_VERSION}")
    for key in ("config", "model"):
        if key not in payload:
            raise CheckpointError(f"checkpoint {str(path)!r} lacks {key!r}")
    return payload


def trained_cameras(payload: dict) -> str:
    """The cameras a checkpoint's renderer was trained with (``TrainConfig.render_cameras``, one
    of ``iris_runtime.manifest.CAMERAS``; "model" for checkpoints without a training config).
    The exported manifest records it as the runtime's default ``cameras``."""
    from iris_runtime.manifest import CAMERAS, camera_name
    train_config = payload.get("train_config")
    value = camera_name(train_config.get("render_cameras", "model")
                        if isinstance(train_config, dict) else "model")
    if value not in CAMERAS:
        raise CheckpointError(f"train_config.render_cameras: expected one of {list(CAMERAS)}, "
                              f"got {value!r}")
    return value


def load_model(path: str | os.PathLike) -> IrisModel:
    """Checkpoint -> IrisModel in eval mode on the CPU."""
    payload = read_checkpoint(path)
    try:
        cfg = ModelConfig.from_dict(payload["config"])
        model = build_model(cfg)
        model.load_state_dict(payload["model"])
    except (TypeError, ValueError, RuntimeError) as exc:
        reason = (str(exc).splitlines() or [""])[0]
        raise CheckpointError(f"checkpoint {str(path)!r} does not match the IRIS model: "
                              f"{reason[:300]}") from None
    return model.eval()
