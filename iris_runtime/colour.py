"""Reference colours of explicit-colour models, from the photos at their own resolution.

The encoder sees every photo at the model's resolution (64x64 for the shipped model), but the
renderer of an explicit-colour model blends the reference photos' colours at each sample's
projection, and those can come from the photo as it was given. ``encode`` keeps each reference
photo centre-cropped to the model's aspect (the crop the encoder sees) and no longer than
``MAX_PHOTO_SIDE`` on its long side (``keep_photo``; 3 bytes a pixel, at most 3 MB a photo).

A render samples each view's colours from one level of that photo's pyramid: the photo halved
while it stays larger than the model's resolution, then the model-resolution image the encoder
saw (``level_sizes``). The level is the one whose focal length in pixels is nearest, in octaves,
to the render's (``choose_level``): one photo pixel per output pixel where the photo has them,
so a small output does not alias and a large one gets the photo's detail. A render at the
model's own size and focal therefore reads the model-resolution images exactly as before (the
same float32 values, bit for bit). The choice assumes the reference sees the surface at about
the target's distance, which is what neighbouring views of a capture do.

Sampling is bilinear, align_corners=False and border-clamped, on the normalised grid the
renderer's field maps use, so any level size works. The ray march reads through
``geometry.sample_taps`` (bit for bit the renderer's ``grid_sample`` at the model's level); the
two-scale pass, which reads many more samples, through ``cv2.remap`` on float32 images
(``ColourSource.read``; the same values to float32 rounding). Levels above the model's are kept
as uint8 (3 bytes a pixel) and made float32 (12 bytes a pixel) for the views a render reads.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from . import geometry as G
from .images import plan_crop_resize

__all__ = ["MAX_PHOTO_SIDE", "BLEND_EPS", "keep_photo", "level_sizes", "choose_level",
           "ColourSource", "mean_colour", "angular_view_weights", "blend_residual", "compose"]

#: Longest side of a reference photo kept for colour (pixels): 1024 x 1024 x 3 bytes = 3 MB a
#: view; a larger photo is shrunk (``cv2.INTER_AREA``) when it is encoded.
MAX_PHOTO_SIDE = 1024

#: The explicit-colour renderer clamps its blend to [BLEND_EPS, 1 - BLEND_EPS] before the logit
#: (finite at black and white); iris_train's renderer reads it from here.
BLEND_EPS = 1e-4

f32 = np.float32


def keep_photo(photo: np.ndarray, model_size: tuple[int, int],
               max_side: int = MAX_PHOTO_SIDE) -> np.ndarray:
    """``photo uint8 [H, W, 3]`` centre-cropped to the aspect of ``model_size`` (the crop
    ``images.fit_to_model`` makes) and shrunk to at most ``max_side`` on its long side
    (``cv2.INTER_AREA``; never enlarged) -> uint8 [h, w, 3], C-contiguous, read-only."""
    Hm, Wm = model_size
    plan = plan_crop_resize(photo.shape[0], photo.shape[1], Hm, Wm)
    crop = photo[plan.y0:plan.y0 + plan.crop_h, plan.x0:plan.x0 + plan.crop_w]
    long_side = max(plan.crop_h, plan.crop_w)
    if long_side > max_side:
        s = max_side / long_side
        size = (max(1, round(plan.crop_w * s)), max(1, round(plan.crop_h * s)))
        out = cv2.resize(np.ascontiguousarray(crop), size, interpolation=cv2.INTER_AREA)
    else:
        out = np.array(crop, copy=True, order="C")
    out.setflags(write=False)
    return out


def level_sizes(photo_size: tuple[int, int], model_size: tuple[int, int]) -> list[tuple[int, int]]:
    """The pyramid of a kept photo of ``photo_size`` (h, w): the photo, then halved (rounded)
    while both sides stay larger than the model's, then ``model_size`` itself, largest first.
    A photo no larger than the model's resolution has the model's level alone."""
    h, w = photo_size
    Hm, Wm = model_size
    sizes = []
    while h > Hm and w > Wm:
        sizes.append((h, w))
        h, w = max(1, round(h / 2)), max(1, round(w / 2))
    sizes.append((Hm, Wm))
    return sizes


def choose_level(sizes: list[tuple[int, int]], model_size: tuple[int, int],
                 focal_ratio: float) -> int:
    """Index into ``sizes`` (``level_sizes``) of the level whose focal in pixels is nearest, in
    octaves, to ``focal_ratio`` x the model-resolution focal (``focal_ratio``: the render's focal
    in its pixels over the reference's in the model's pixels). Ties go to the larger level."""
    Hm, Wm = model_size
    want = math.log2(max(focal_ratio, 1e-12))
    errors = [abs(math.log2(math.sqrt(h * w / (Hm * Wm))) - want) for h, w in sizes]
    return int(np.argmin(np.round(errors, 9)))


@dataclass(frozen=True, eq=False)
class ColourSource:
    """Each view's colour level for one render.

    model_photos: float32 [V, 3, H, W]   the model-resolution photos (the encoder's input)
    fine:         per view None (the model's level) or uint8 [h, w, 3], the level it reads
    model_size:   (H, W)

    Two readers of the same levels: ``sample`` (the ray march's, on normalised grids, bit for bit
    the renderer's ``grid_sample``) and ``read`` (the two-scale pass's, on model pixels, through
    ``cv2.remap``). Each builds what it needs on first use (bilinear taps, float32 images) and
    keeps it for the render.
    """
    model_photos: np.ndarray
    fine: tuple
    model_size: tuple[int, int]
    _made: dict = field(default_factory=dict, repr=False)

    @classmethod
    def build(cls, model_photos: np.ndarray, photos: tuple | None, focal_ratio: float,
              levels: dict | None = None) -> "ColourSource":
        """Colours of views with model-resolution photos ``model_photos`` float32 [V, 3, H, W]
        and kept photos ``photos`` (per view uint8 [h, w, 3], or None: the model's level for
        every view) for a render whose focal is ``focal_ratio`` x the references'. ``levels``:
        a cache {(id of photo, size): uint8 level} shared by the renders of a scene."""
        V, _, H, W = model_photos.shape
        model_size = (H, W)
        fine = []
        for v in range(V):
            photo = None if photos is None else photos[v]
            entry = None
            if photo is not None:
                sizes = level_sizes(photo.shape[:2], model_size)
                level = choose_level(sizes, model_size, focal_ratio)
                if level < len(sizes) - 1:
                    entry = _level(photo, sizes[level], levels)
            fine.append(entry)
        return cls(model_photos, tuple(fine), model_size)

    @property
    def sizes(self) -> list[tuple[int, int]]:
        """The level size each view reads."""
        return [self.model_size if e is None else e.shape[:2] for e in self.fine]

    def sample(self, grid: np.ndarray, views: np.ndarray) -> np.ndarray:
        """Colours float32 [v, ..., 3] in [0, 1] of views ``views`` [v] at ``grid [v, ..., 2]``
        (normalised, align_corners=False): ``geometry.sample_taps`` on the level's taps, so a
        view at the model's level reads exactly what the renderer's ``grid_sample`` would."""
        if all(self.fine[int(v)] is None for v in views):   # the model's level: one call
            return G.sample_taps(self._model_taps(), self.model_size, grid, views)
        out = np.empty(grid.shape[:-1] + (3,), f32)
        first = np.zeros(1, np.intp)
        for k, view in enumerate(views):
            level = self.fine[int(view)]
            if level is None:
                out[k] = G.sample_taps(self._model_taps(), self.model_size, grid[k:k + 1],
                                       np.asarray([view]))[0]
            else:
                taps = self._cached(("taps", int(view)),
                                    lambda: G.bilinear_taps(level.transpose(2, 0, 1)[None]))
                out[k] = G.sample_taps(taps, level.shape[:2], grid[k:k + 1], first)[0]
                out[k] *= f32(1.0 / 255.0)
        return out

    def read(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Colours float32 [V, P, 3] in [0, 1] of every view ``k`` at ``(u[k], v[k])`` float32
        [V, P], positions in the model's pixels (``geometry.project_points``' convention: the
        image spans [0, W] x [0, H]): bilinear, border-clamped, as ``sample`` reads them (to
        float32 rounding). ``cv2.remap`` on each level in float32 (12 bytes a pixel, made once
        per render), for the many samples of a large output."""
        V, P = u.shape
        H, W = self.model_size
        cols = min(P, 8192)                 # remap's maps must stay below 32767 on a side
        rows = -(-P // cols)
        pad = rows * cols - P
        out = np.empty((V, P, 3), f32)
        for k in range(V):
            image = self._image(k)
            h, w = image.shape[:2]
            # Model pixel -> the level's pixel centres (align_corners=False), clamped to the
            # outermost centres as grid_sample's border padding clamps.
            x = np.clip(u[k] * f32(w / W) - f32(0.5), f32(0), f32(w - 1))
            y = np.clip(v[k] * f32(h / H) - f32(0.5), f32(0), f32(h - 1))
            if pad:
                x, y = np.pad(x, (0, pad)), np.pad(y, (0, pad))
            got = cv2.remap(image, x.reshape(rows, cols), y.reshape(rows, cols),
                            cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            out[k] = got.reshape(-1, 3)[:P]
        return out

    def _model_taps(self) -> np.ndarray:
        return self._cached("model_taps", lambda: G.bilinear_taps(self.model_photos))

    def _image(self, view: int) -> np.ndarray:
        """View ``view``'s level as float32 [h, w, 3] in [0, 1], C-contiguous."""
        level = self.fine[view]
        if level is None:
            return self._cached(("image", view), lambda: np.ascontiguousarray(
                self.model_photos[view].transpose(1, 2, 0), dtype=f32))
        return self._cached(("image", view), lambda: level.astype(f32) * f32(1.0 / 255.0))

    def _cached(self, key, make):
        hit = self._made.get(key)
        if hit is None:
            hit = self._made[key] = make()
        return hit


def _level(photo: np.ndarray, size: tuple[int, int], levels: dict | None) -> np.ndarray:
    """``photo`` brought to ``size`` (``cv2.INTER_AREA``), cached in ``levels``."""
    if size == photo.shape[:2]:
        return photo
    key = (id(photo), size)
    if levels is not None:
        hit = levels.get(key)
        if hit is not None and hit[0] is photo:
            return hit[1]
    image = cv2.resize(photo, (size[1], size[0]), interpolation=cv2.INTER_AREA)
    image.setflags(write=False)
    if levels is not None:
        levels[key] = (photo, image)
    return image


# ----------------------------------------------------------------------------------------------
# The colour formula of the explicit-colour renderer (iris_train.ray_renderer.RayRenderer):
#     rgb = sigmoid(logit(clamp(sum_s w_s mean_s)) + head(h))
# with mean_s the validity-weighted mean of the views' colours at sample s. The two-scale render
# (iris_runtime.detail) keeps w and the head's term from the field and takes mean_s from the
# photos at the output's resolution.
# ----------------------------------------------------------------------------------------------

def mean_colour(colours: np.ndarray, mask: np.ndarray, cos: np.ndarray | None = None,
                blend_angle: float = 0.0) -> np.ndarray:
    """Each sample's reference colour as the renderer blends it over the views: ``colours
    [V, ..., 3]``, validity weights ``mask [V, ...]`` -> float32 [..., 3].

    With ``blend_angle`` 0 the validity-weighted mean, ``sum_v m c / max(sum_v m, 1)``. With
    ``blend_angle`` > 0 (a model's ``ModelConfig.blend_angle``) each view also weighs
    ``exp((cos_v - 1) / blend_angle)``, ``cos [V, ...]`` the cosine between the target's and the
    view's rays at the sample (the geometric cue's last entry): where the views disagree at
    fine scale -- a depth slightly off, a reflection -- the colour follows the views that look
    along the target ray instead of averaging ghosts. The sum is renormalised to the
    validity-weighted one, ``sum_v a c / sum_v a * min(sum_v m, 1)`` with ``a = m exp(...)``, so
    a sample seen by few views fades as before and a large ``blend_angle`` is the plain mean.
    ``angular_view_weights`` gives ``a``."""
    m = mask.astype(f32)[..., None]
    if not blend_angle:
        return (colours * m).sum(axis=0) / np.maximum(m.sum(axis=0), f32(1.0))
    a = angular_view_weights(mask, cos, blend_angle)[..., None]
    total = a.sum(axis=0)
    return ((colours * a).sum(axis=0) / np.maximum(total, f32(1e-30))
            * np.minimum(m.sum(axis=0), f32(1.0)))


def angular_view_weights(mask: np.ndarray, cos: np.ndarray, blend_angle: float) -> np.ndarray:
    """``mask * exp((cos - c) / blend_angle)`` float32 [V, ...], ``c`` the largest ``cos`` among
    the views with ``mask > 0`` (1 where none): the factor ``exp((c - 1) / blend_angle)`` common
    to every view cancels in the blend and keeps the best view's weight at its mask, so far
    angles underflow to 0 only beside a view that sees the point."""
    mask, cos = mask.astype(f32), cos.astype(f32)
    best = np.where(mask > 0, cos, f32(-np.inf)).max(axis=0)
    best = np.where(np.isfinite(best), best, f32(1.0))
    return mask * np.exp(np.minimum(cos - best, f32(0)) / f32(blend_angle))


def _logit(x: np.ndarray) -> np.ndarray:
    return np.log(x) - np.log1p(-x)


def blend_residual(rgb: np.ndarray, blend: np.ndarray) -> np.ndarray:
    """What the colour head added: ``logit(rgb) - logit(clamp(blend))`` float32 [..., 3]
    (``rgb`` kept within float32's open unit interval, so the result is finite)."""
    tiny = f32(1e-7)
    rgb = np.clip(rgb.astype(f32), tiny, f32(1.0) - tiny)
    blend = np.clip(blend.astype(f32), f32(BLEND_EPS), f32(1.0 - BLEND_EPS))
    return (_logit(rgb) - _logit(blend)).astype(f32)


def compose(blend: np.ndarray, residual: np.ndarray) -> np.ndarray:
    """The renderer's colour from a blend and the head's residual: ``sigmoid(logit(clamp(blend))
    + residual)`` float32 [..., 3]."""
    blend = np.clip(blend.astype(f32), f32(BLEND_EPS), f32(1.0 - BLEND_EPS))
    x = _logit(blend) + residual
    with np.errstate(over="ignore"):        # exp(-x) of a large negative x: inf -> colour 0
        return (f32(1.0) / (f32(1.0) + np.exp(-x))).astype(f32)
