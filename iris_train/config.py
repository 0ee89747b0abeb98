"""Every number of the IRIS model (``ModelConfig``) and of a training run (``TrainConfig``), each
in one frozen dataclass that travels with the weights (a checkpoint's "config" and "train_config")."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from iris_runtime.errors import InputError    # an IrisError and a ValueError

#: The camera heads (``ModelConfig.camera_head``): "tokens" regresses each pose from the pooled
#: camera tokens (``camera_head.CameraHead``); "correlation" adds explicit cross-view evidence, a
#: correlation volume of each view's fine feature map with view 0's
#: (``correlation.CorrelationCameraHead``).
CAMERA_HEADS = ("tokens", "correlation")


@dataclass(frozen=True)
class ModelConfig:
    # Input images (the model's resolution; the runtime crops/resizes to it).
    image_height: int = 64
    image_width: int = 64
    patch_size: int = 8
    # Multi-view encoder (Muskie/VGGT-style: alternating per-view and cross-view attention).
    encoder_width: int = 128
    encoder_pairs: int = 2            # number of (per-view block, cross-view block) pairs
    encoder_heads: int = 4
    mlp_ratio: float = 4.0
    # Camera head: focal bounded to [focal_min, focal_max] in units of image size (fx/W, fy/H).
    focal_min: float = 0.25
    focal_max: float = 4.0
    # Latent field / renderer width and depth.
    field_width: int = 64             # model width of the view and ray transformers
    view_blocks: int = 1              # view-transformer blocks (paper: one aggregation stage)
    ray_blocks: int = 2               # ray-transformer blocks
    field_heads: int = 4
    pos_freqs: int = 6                # sinusoidal frequencies for sample positions
    dir_freqs: int = 4                # ... and for ray directions
    # Explicit colour: the field also gets the reference RGB sampled at full resolution
    # where each sample projects, and the ray's colour is a learned blend of it over samples (a
    # per-sample logit) plus a bounded learned residual; the blend weights give the soft depth.
    # False: the paper's renderer (colour from the rgb head alone, depth from the last ray
    # attention), which is what checkpoints without this field hold.
    explicit_rgb: bool = False
    # Explicit colour: the scale of the angular weighting of the views in the colour blend. Each
    # view weighs its validity times exp((cos - 1) / blend_angle), cos between the target's and
    # the view's rays at the sample, so that where the views disagree at fine scale the colour
    # follows the views looking along the target ray instead of averaging ghosts
    # (iris_runtime.colour.mean_colour). 0: the plain validity-weighted mean (what checkpoints
    # without this field hold).
    blend_angle: float = 0.0
    # Canonical-view marker (VGGT's first-frame tokens): a learnable embedding added to every token
    # of view 0, so that cross-view attention can tell the canonical view's patches from the
    # others'. Without it no token knows which view the poses are relative to, and the camera head
    # cannot learn relative rotations (docs/TRAINING.md). Views 1..V-1 stay order-free.
    canonical_marker: bool = False
    # Camera head, one of CAMERA_HEADS. "tokens": pose of view i from [camera token i, camera
    # token 0] (what checkpoints without this field hold). "correlation": the same tokens plus
    # the correlation volume of view i's fine (2x the token grid) feature map with view 0's
    # (docs/TRAINING.md, "Correlation camera head"); needs patch_size a multiple of 8.
    camera_head: str = "tokens"
    # The correlation head's grid in multiples of the token grid, 2 or 4 (64x64 photos, 8x8
    # tokens: 16x16 or 32x32 positions correlated; the volume grows with its fourth power).
    correlation_scale: int = 2
    # True: the camera head reads the camera tokens of an encoder of its own
    # (``IrisModel.camera_encoder``, the same shape as ``encoder``), so that training the cameras
    # leaves the renderer's features as they were (as Monodepth2 gives its pose network its own
    # encoder). False: one encoder for both (what checkpoints without this field hold).
    camera_encoder: bool = False
    # The field maps' grid in multiples of the token grid: 1, 2 or 4. Above 1 the field samples
    # the encoder's features upsampled (bilinear) plus a learned correction from a small
    # convolutional stem on the image (``encoder.FineFeatures``), so that a feature covers
    # patch_size / map_scale pixels instead of a whole patch: the depth of a sample is decided
    # by finer evidence (docs/ARCHITECTURE.md, "Field maps finer than the tokens"). 1: the
    # encoder's grid (what checkpoints without this field hold).
    map_scale: int = 1
    # Explicit colour: the views' disagreement as a field input (IBRNet's mean-and-variance
    # aggregation). Each view's deviation d_k from the sample's plain mean reference colour
    # enters its field-map channels through a linear map of [d_k, |d_k|] that starts at zero, so
    # the view transformer sees which views agree at a depth, the evidence of a surface there.
    # False: no such input (what checkpoints without this field hold).
    colour_deviation: bool = False
    # Ray sampling (docs/ARCHITECTURE.md: camera depths in [0.1, 1.0], 64 samples).
    near: float = 0.1
    far: float = 1.0
    samples: int = 64
    # The cameras' unit: the camera solve (and ``--cameras true``) scale a scene so that its
    # median point depth lands here. 0: ``cameras.DEPTH_TARGET`` of the way into [near, far]
    # (0.55 for the default range). Set, it frees ``far`` from the unit: a range reaching past
    # the backgrounds keeps the scale the renderer learnt its depths at.
    median_depth: float = 0.0

    def __post_init__(self):
        if self.image_height % self.patch_size or self.image_width % self.patch_size:
            raise InputError(f"image size {self.image_height}x{self.image_width} must be a multiple "
                             f"of patch_size {self.patch_size}")
        if self.encoder_width % self.encoder_heads or self.field_width % self.field_heads:
            raise InputError("widths must be divisible by their head counts")
        if not 0 < self.near < self.far:
            raise InputError(f"need 0 < near < far, got near={self.near}, far={self.far}")
        if self.median_depth and not self.near < self.median_depth < self.far:
            raise InputError(f"median_depth: expected 0 or a depth in (near, far) = "
                             f"({self.near}, {self.far}), got {self.median_depth}")
        if not 0 < self.focal_min < self.focal_max:
            raise InputError("need 0 < focal_min < focal_max")
        if self.camera_head not in CAMERA_HEADS:
            raise InputError(f"camera_head: expected one of {list(CAMERA_HEADS)}, got "
                             f"{self.camera_head!r}")
        if self.correlation_scale not in (2, 4):
            raise InputError(f"correlation_scale: expected 2 or 4, got {self.correlation_scale!r}")
        if not (isinstance(self.blend_angle, (int, float)) and 0 <= self.blend_angle < math.inf):
            raise InputError(f"blend_angle: expected a finite number >= 0, got {self.blend_angle!r}")
        if self.colour_deviation and not self.explicit_rgb:
            raise InputError("colour_deviation: the deviation of the reference colours needs "
                             "explicit_rgb")
        if self.blend_angle and not self.explicit_rgb:
            raise InputError("blend_angle: weights the explicit colour blend, so it needs "
                             "explicit_rgb")
        # Above 1 the stem reaches the finer grid by stride-2 convs: patch_size / map_scale must
        # be a power of two.
        valid = type(self.map_scale) is int and self.map_scale in (1, 2, 4)
        stride = self.patch_size // self.map_scale if valid else 0
        if not valid or (self.map_scale > 1 and (self.patch_size % self.map_scale or stride < 2
                                                 or stride & (stride - 1))):
            raise InputError(f"map_scale: expected 1, or 2 or 4 dividing patch_size "
                             f"{self.patch_size} to a power of two, got {self.map_scale!r}")
        if self.camera_head == "correlation" and self.patch_size % 8:
            raise InputError(f"camera_head 'correlation' needs patch_size a multiple of 8 (its "
                             f"stem has stride 4 and correlates at twice the token grid), got "
                             f"patch_size {self.patch_size}")

    @property
    def feature_grid(self) -> tuple[int, int]:
        """(h, w) of the encoder's feature maps."""
        return self.image_height // self.patch_size, self.image_width // self.patch_size

    @property
    def field_grid(self) -> tuple[int, int]:
        """(h, w) of the field maps the renderer samples: ``map_scale`` times the token grid."""
        h, w = self.feature_grid
        return self.map_scale * h, self.map_scale * w

    @property
    def unit_range(self) -> tuple[float, float]:
        """The (near, far) the camera solve's depth rule is given (its ``depth_range``): the one
        whose ``DEPTH_TARGET`` point is ``median_depth``; (near, far) itself when that is 0."""
        from iris_runtime.cameras import unit_range
        return unit_range(self.near, self.far, self.median_depth)

    @property
    def correlation_grid(self) -> tuple[int, int]:
        """(h, w) of the correlation camera head's fine feature maps: ``correlation_scale``
        times the token grid."""
        h, w = self.feature_grid
        return self.correlation_scale * h, self.correlation_scale * w

    @property
    def field_channels(self) -> int:
        """Channels of the per-scene (pre-projected) feature maps the renderer samples.

        u (width projection) plus, per view-transformer block, its key and value projections.
        """
        return self.field_width * (1 + 2 * self.view_blocks)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise InputError(f"unknown ModelConfig fields: {sorted(unknown)}")
        return cls(**d)


PRESETS: dict[str, ModelConfig] = {
    # Trainable on 2 CPU cores.
    "tiny": ModelConfig(),
    # The tiny preset with explicit colour: the default for new runs (docs/TRAINING.md).
    "tiny-rgb": ModelConfig(explicit_rgb=True, canonical_marker=True),
    # The same network at 128x128 with 16-pixel patches: the same token grid and encoder cost, rays
    # and explicit colours at twice the resolution (``scripts/resize_checkpoint.py`` carries a
    # tiny-rgb checkpoint to it).
    "tiny-rgb-128": ModelConfig(image_height=128, image_width=128, patch_size=16, explicit_rgb=True,
                                canonical_marker=True),
    # Muskie-base-like widths at 256x256, patch 16 (needs a GPU to train).
    "paper": ModelConfig(image_height=256, image_width=256, patch_size=16, encoder_width=768,
                         encoder_pairs=6, encoder_heads=12, field_width=256, view_blocks=1,
                         ray_blocks=1, field_heads=8, pos_freqs=10, dir_freqs=4),
}


def preset(name: str) -> ModelConfig:
    try:
        return PRESETS[name]
    except KeyError:
        raise InputError(f"unknown preset {name!r}; expected one of {sorted(PRESETS)}") from None


@dataclass(frozen=True)
class TrainConfig:
    preset: str = "tiny"
    # The model's camera head (``config.CAMERA_HEADS``); "": the head of the checkpoint the run
    # starts from (``--resume``, ``--init``), else the preset's (``model_config``).
    camera_head: str = ""
    steps: int = 20_000
    scenes_per_step: int = 2          # per process
    views_min: int = 4                # views drawn per scene (all predicted, split ref/target)
    views_max: int = 7
    targets_min: int = 1
    targets_max: int = 2
    rays_per_scene: int = 384         # random target rays per scene and step
    train_samples: int = 0            # stratified samples per training ray (0: the model's S)
    # Geometric signals for the cameras (docs/TRAINING.md has the runs that chose them):
    aux_weight: float = 1.0           # explicit-warp (learned-logit blend of reference RGB) loss
    aux_blur_weight: float = 1.0      # ... the same on blurred images (coarse to fine)
    plane_sweep_weight: float = 0.0   # parameter-free plane-sweep loss
    teacher_weight: float = 1.0       # epipolar pseudo-pose rotation loss (iris_train.pseudo_poses)
    teacher_translation_weight: float = 0.5   # ... translation direction
    teacher_focal_weight: float = 0.1         # ... log focal
    teacher_scenes: int = 0           # extra scenes per step encoded (all views) for the teacher only
    # Cameras the renderer is trained with: "model" (the camera head's, trained through the
    # render), or "solve" (each scene's cached whole-scene camera solve, "epipolar" its former
    # name; ``pseudo_poses.load_or_solve``: what ``IrisRuntime.encode(cameras="solve")`` gives the
    # renderer at inference; views the solve cannot pose are not drawn). The camera head is then
    # distilled on the same cameras (``solve_*_weight``); no label is read either way.
    render_cameras: str = "model"
    solve_rotation_weight: float = 0.0    # 1 - cos of each view's rotation vs the solve's
    solve_translation_weight: float = 0.0 # squared error of each view's centre (view 0's frame)
    solve_focal_weight: float = 0.0       # squared log focal error
    lr: float = 1e-3                  # renderer (latent field + ray renderer)
    encoder_lr_scale: float = 0.1     # encoder and camera head (paper: 0.1x)
    weight_decay: float = 0.05
    warmup: int = 500
    min_lr_ratio: float = 0.1
    grad_clip: float = 1.0
    train_scenes: int = 3000          # synthetic training seeds 0 .. train_scenes-1
    # Capture-like scenes (``iris_train.synthetic`` kind "capture": object walks, orbits,
    # hand-held and indoor paths, 25-90 deg fields of view, photometric camera effects), seeds
    # 0 .. capture_scenes-1, rendered at CAPTURE_RENDER_SIZE and brought to the model's size; drawn
    # beside the classic scenes with equal probability per scene (docs/DATA.md).
    capture_scenes: int = 0
    # Only these capture kinds of seeds 0 .. capture_scenes-1 (comma-separated names of
    # ``synthetic.CAPTURE_KINDS``, e.g. "walk,orbit"); "": every kind.
    capture_kinds: str = ""
    # The classic scenes rendered at this square size (0: the model's) and brought to the
    # model's by area averaging, so that the camera solve of ``render_cameras="solve"`` sees
    # photos at a photo's resolution, as at inference, not the model's thumbnails.
    classic_render_size: int = 0
    # The renderer's reference colours and target pixels at this square size (0: the model's):
    # the scenes are read at it (classic ones need ``classic_render_size`` equal to it, capture
    # ones are rendered at CAPTURE_RENDER_SIZE) and the encoder sees them area-downsampled to the
    # model's size, as the runtime brings a photo to the model. Features stay on the model's
    # grid, so a ray costs what it costs at the model's size, and the blend learns from texture
    # finer than the model's pixels (the runtime samples colours from the photos at the
    # output's scale).
    colour_size: int = 0
    # Keep the camera head and its own encoder as they are (no gradient, no weight decay): a
    # renderer fine-tune of a model whose head was distilled apart (``camera_encoder``).
    freeze_cameras: bool = False
    # Explicit colour: the model's ``blend_angle`` (ModelConfig): the angular weighting of the
    # views in the colour blend. It holds no weights, so a fine-tune (``--init``) may change it.
    blend_angle: float = 0.0
    # The model's ``map_scale`` (ModelConfig), 0: the preset's. A fine-tune (``--init``) from a
    # model of another map scale starts the fine-feature stem fresh (``load_init_weights``).
    map_scale: int = 0
    # Learning-rate multiple over the renderer's of the parts a fine-tune starts fresh (at zero)
    # beside a trained field: the fine-feature stem (``encoder.FineFeatures``) and the
    # colour-deviation map (``latent_field.LatentField.deviation_to_maps``).
    fine_lr_scale: float = 1.0
    # The model's ``colour_deviation`` (ModelConfig). A fine-tune (``--init``) from a model
    # without it starts its map fresh, at zero.
    colour_deviation: bool = False
    # The model's sampled depth range ends at ``far`` (0: the preset's); the cameras' unit stays
    # the preset's (ModelConfig.median_depth), so the range reaches past the backgrounds that
    # the default rule puts beyond 1.0. Holds no weights: a fine-tune may change it.
    far: float = 0.0
    # The distortion loss of Mip-NeRF 360 on the explicit-colour blend weights along each target
    # ray (``losses.distortion``): it is smallest when the weight sits in one short stretch of
    # the ray, so it pushes the soft depth to commit to one surface instead of spreading.
    distortion_weight: float = 0.0
    seed: int = 0
    log_every: int = 10
    ckpt_every: int = 250

    @classmethod
    def from_dict(cls, d: dict) -> "TrainConfig":
        """The config of a checkpoint's "train_config" (or a run's train_config.json). A key the
        class does not have is an ``InputError`` naming it, unless ``RETIRED_TRAIN_KEYS`` maps it
        (renamed) or drops it (retired); a field the dict lacks takes its default (what runs did
        before the field existed)."""
        d = dict(d)
        for old, new in RETIRED_TRAIN_KEYS.items():
            if old in d:
                value = d.pop(old)
                if new is not None:
                    d.setdefault(new, value)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise InputError(f"unknown TrainConfig fields: {unknown}")
        return cls(**d)


#: Keys a checkpoint's "train_config" may carry that ``TrainConfig`` no longer has: old name ->
#: the field it was renamed to, or None for a setting retired (read and dropped). Every other
#: unknown key is an error (``TrainConfig.from_dict``). Empty: no field has been renamed or
#: retired; the committed checkpoints (models/*.pt, models/experiments/*.pt) carry only fields
#: of today, the older ones lacking camera_head, colour_size and freeze_cameras, whose defaults
#: are what those runs did (tests/test_config.py loads every one).
RETIRED_TRAIN_KEYS: dict[str, str | None] = {}
