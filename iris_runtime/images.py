"""Image input for IRIS: load anything image-like as uint8 RGB, and bring it to model resolution.

numpy + Pillow + OpenCV only (the runtime never imports torch).

``load_image`` accepts a file path, the bytes of an image file (e.g. an HTTP upload), a PIL image or
a numpy array and returns ``uint8 [H, W, 3]`` RGB:

- grayscale (``[H, W]`` or ``[H, W, 1]``) is repeated to three channels;
- RGBA (``[H, W, 4]``) loses its alpha channel (no compositing: the colour channels are kept as is);
- 16-bit (``uint16``) is scaled to 8 bits by ``round(x / 257)`` (65535 -> 255 exactly);
- float arrays must hold values in [0, 1] (``validation.check_images``: NaN/inf, or values
  beyond [0, 1] by more than ``FLOAT_IMAGE_ATOL = 1e-6``, raise an ``ImageError`` that says how to
  fix the data, e.g. divide 0..255 values by 255); they become ``round(clip(x, 0, 1) * 255)``,
  the clip removing only that rounding excess;
- files are decoded by Pillow (EXIF orientation applied); 16-bit colour PNG/TIFF files, which
  Pillow would truncate to 8 bits, are decoded by OpenCV at full depth and then scaled as above.

``fit_to_model`` is the one documented crop/resize from any image size to the model's size:

1. centre-crop to the target aspect ratio (the crop keeps the full height or the full width,
   offsets are ``(W - crop_w) // 2`` and ``(H - crop_h) // 2``);
2. resize the crop to ``(height, width)`` with ``cv2.INTER_AREA`` when shrinking (an area average,
   no aliasing) and ``cv2.INTER_LINEAR`` when enlarging (no overshoot, unlike cubic).

With pixel centres at (j + 0.5, i + 0.5) both steps are affine in pixel coordinates: a source point
(u, v) lands at ``((u - x0) * width / crop_w, (v - y0) * height / crop_h)``. ``CropResize`` records
the crop box and the scales and maps intrinsics and points between the two images.
"""
from __future__ import annotations

import io
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Union

import cv2
import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from .errors import ImageError
from .validation import check_images, check_integer

ImageLike = Union[str, os.PathLike, bytes, Image.Image, np.ndarray]

__all__ = ["ImageLike", "load_image", "to_rgb_uint8", "CropResize", "plan_crop_resize", "fit_to_model",
           "fit_to_working_size", "camera_copies", "CAMERA_WORKING_SIZE"]

#: Longer side of the copy of a photo the camera solve works on (``fit_to_working_size``): the
#: cameras are solved on the photos near their own resolution, the encoder gets the model's.
CAMERA_WORKING_SIZE = 512


# ----------------------------------------------------------------------------------------------
# Loading
# ----------------------------------------------------------------------------------------------

def load_image(x: ImageLike, name: str = "image") -> np.ndarray:
    """Load ``x`` (path, bytes of an image file, PIL image or numpy array) as ``uint8 [H, W, 3]``
    RGB. Bytes are decoded exactly as the file holding them would be.

    ``name`` is the argument's name used in error messages (e.g. ``"images[2]"``).
    Raises ``ImageError`` for unreadable, truncated, non-image or empty inputs and for arrays of
    an unsupported shape or dtype.
    """
    if isinstance(x, (str, os.PathLike)):
        return _load_file(Path(x), name)
    if isinstance(x, (bytes, bytearray, memoryview)):
        return _decode(bytes(x), name)
    if isinstance(x, Image.Image):
        return _from_pil(x, name, source=f"{name} (PIL image)")
    if isinstance(x, np.ndarray):
        return to_rgb_uint8(x, name)
    raise ImageError(
        f"{name}: expected a file path, a PIL image or a numpy array (or the bytes of an image "
        f"file), got {type(x).__name__}")


def to_rgb_uint8(a: np.ndarray, name: str = "image") -> np.ndarray:
    """Convert an image array to ``uint8 [H, W, 3]`` RGB (see the module docstring for the rules;
    shape, dtype and values are checked by ``validation.check_images``)."""
    a = check_images(a, name)
    if a.ndim == 2:
        a = a[:, :, None]

    if a.dtype == np.uint8:
        out = a
    elif a.dtype == np.uint16:
        # round(x / 257): maps 0..65535 onto 0..255 with 65535 -> 255 and 257*k -> k exactly.
        out = ((a.astype(np.uint32) * 2 + 257) // 514).astype(np.uint8)
    else:                            # float in [0, 1] up to rounding (checked): clip the rounding
        out = np.rint(np.clip(a.astype(np.float64), 0.0, 1.0) * 255.0).astype(np.uint8)

    if out.shape[2] == 1:
        out = np.repeat(out, 3, axis=2)
    elif out.shape[2] == 4:
        out = out[:, :, :3]          # drop alpha: the brief asks for no compositing
    return np.ascontiguousarray(out)


def _load_file(path: Path, name: str) -> np.ndarray:
    where = f"{name} ({path})" if name != str(path) else str(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ImageError(f"{where}: no such file") from None
    except IsADirectoryError:
        raise ImageError(f"{where}: is a directory, expected an image file") from None
    except OSError as e:
        raise ImageError(f"{where}: cannot read file: {e}") from None
    return _decode(data, where)


def _decode(data: bytes, where: str) -> np.ndarray:
    """The image file content ``data`` as uint8 RGB (``where``: how messages name it)."""
    if not data:
        raise ImageError(f"{where}: file is empty, expected an image (PNG, JPEG, ...)")
    try:
        img = Image.open(io.BytesIO(data))
        # The raw decoder mode tells whether the file holds 16 bits per channel, which Pillow
        # silently truncates to 8 bits for colour images; it is gone after load().
        rawmodes = [t[3][0] if isinstance(t[3], tuple) else t[3] for t in (img.tile or [])
                    if len(t) > 3 and t[3]]
        img.load()               # decodes fully: raises on truncated / corrupt data
    except UnidentifiedImageError:
        raise ImageError(f"{where}: not a readable image file (expected PNG, JPEG or another "
                         f"format Pillow reads): unknown image format") from None
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as e:
        raise ImageError(
            f"{where}: not a readable image file (expected PNG, JPEG or another format Pillow "
            f"reads): {e}") from None
    colour16 = img.mode in ("RGB", "RGBA") and any(";16" in str(m) for m in rawmodes)
    if colour16:
        a = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if a is not None and a.ndim == 3 and a.dtype == np.uint16:
            a = cv2.cvtColor(a, cv2.COLOR_BGRA2RGBA if a.shape[2] == 4 else cv2.COLOR_BGR2RGB)
            return to_rgb_uint8(a, where)
    try:
        img = ImageOps.exif_transpose(img)
    except Exception:        # a broken EXIF block must not make a decodable image unreadable
        pass
    return _from_pil(img, where, source=where)


def _from_pil(img: Image.Image, name: str, source: str) -> np.ndarray:
    if img.width == 0 or img.height == 0:
        raise ImageError(f"{source}: image is empty ({img.width}x{img.height})")
    mode = img.mode
    try:
        if mode in ("RGB", "L", "RGBA"):
            a = np.asarray(img)
        elif mode.startswith("I;16"):
            a = np.asarray(img).astype(np.uint16)             # 16-bit grayscale (any byte order)
        elif mode == "I":
            a = np.asarray(img)
            if a.size and (a.min() < 0 or a.max() > 65535):
                raise ImageError(f"{source}: 32-bit integer image with values outside 0..65535")
            a = a.astype(np.uint16)                           # how Pillow opens 16-bit PNGs
        elif mode == "F":
            a = np.asarray(img).astype(np.float32)            # float image: must be in [0, 1]
        elif mode == "LA":
            a = np.asarray(img.convert("L"))
        else:                                                 # P, PA, 1, CMYK, YCbCr, LAB, HSV...
            a = np.asarray(img.convert("RGB"))
    except ImageError:
        raise
    except (OSError, ValueError) as e:
        raise ImageError(f"{source}: cannot convert image of mode {mode!r} to RGB: {e}") from None
    return to_rgb_uint8(a, source)


# ----------------------------------------------------------------------------------------------
# Crop and resize to the model's resolution
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class CropResize:
    """A centre crop followed by a resize, as done by ``fit_to_model``.

    Source pixels ``[y0:y0+crop_h, x0:x0+crop_w]`` are resized to ``out_h x out_w``. With pixel
    centres at (j + 0.5, i + 0.5), a source point (u, v) maps to
    ``((u - x0) * scale_x, (v - y0) * scale_y)``.
    """

    src_h: int
    src_w: int
    x0: int
    y0: int
    crop_w: int
    crop_h: int
    out_h: int
    out_w: int

    @property
    def scale_x(self) -> float:
        return self.out_w / self.crop_w

    @property
    def scale_y(self) -> float:
        return self.out_h / self.crop_h

    @property
    def matrix(self) -> np.ndarray:
        """``[3, 3]`` affine map from source pixel coordinates to output pixel coordinates."""
        return np.array([[self.scale_x, 0.0, -self.x0 * self.scale_x],
                         [0.0, self.scale_y, -self.y0 * self.scale_y],
                         [0.0, 0.0, 1.0]])

    def adjust_intrinsics(self, K: np.ndarray) -> np.ndarray:
        """``K [3, 3]`` in source pixels -> ``K [3, 3]`` in output pixels (float64).

        The crop shifts the principal point by (-x0, -y0); the resize scales fx, cx by
        ``out_w / crop_w`` and fy, cy by ``out_h / crop_h`` (skew scales with x).
        """
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise ImageError(f"K: expected a finite [3, 3] intrinsics matrix, got shape {K.shape}")
        return self.matrix @ K

    def to_output(self, uv: np.ndarray) -> np.ndarray:
        """Source pixel coordinates ``[..., 2]`` (u, v) -> output pixel coordinates ``[..., 2]``."""
        uv = np.asarray(uv, dtype=np.float64)
        return np.stack([(uv[..., 0] - self.x0) * self.scale_x,
                         (uv[..., 1] - self.y0) * self.scale_y], axis=-1)

    def to_source(self, uv: np.ndarray) -> np.ndarray:
        """Output pixel coordinates ``[..., 2]`` -> source pixel coordinates ``[..., 2]``."""
        uv = np.asarray(uv, dtype=np.float64)
        return np.stack([uv[..., 0] / self.scale_x + self.x0,
                         uv[..., 1] / self.scale_y + self.y0], axis=-1)


def plan_crop_resize(src_h: int, src_w: int, height: int, width: int) -> CropResize:
    """The centre crop (largest box of the target aspect ratio) and resize for one image size."""
    for arg, v in (("src_h", src_h), ("src_w", src_w), ("height", height), ("width", width)):
        check_integer(v, arg, error=ImageError)
    # Keep the full height when the source is wider than the target, else the full width.
    if src_w * height >= src_h * width:
        crop_h = src_h
        crop_w = min(src_w, max(1, int(round(src_h * width / height))))
    else:
        crop_w = src_w
        crop_h = min(src_h, max(1, int(round(src_w * height / width))))
    x0 = (src_w - crop_w) // 2
    y0 = (src_h - crop_h) // 2
    return CropResize(int(src_h), int(src_w), int(x0), int(y0), int(crop_w), int(crop_h),
                      int(height), int(width))


def fit_to_model(image: np.ndarray, height: int, width: int) -> tuple[np.ndarray, CropResize]:
    """Centre-crop ``image uint8 [H, W, 3]`` to the aspect of ``height x width``, then resize.

    Returns ``(out uint8 [height, width, 3], CropResize)``. Shrinking uses ``cv2.INTER_AREA``,
    enlarging ``cv2.INTER_LINEAR``; an image already of the right size is returned unchanged (a copy).
    """
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 \
            or image.shape[2] != 3:
        got = (f"{image.dtype} array of shape {tuple(image.shape)}" if isinstance(image, np.ndarray)
               else type(image).__name__)
        raise ImageError(f"image: expected a uint8 [H, W, 3] array (use load_image first), got {got}")
    if image.shape[0] == 0 or image.shape[1] == 0:
        raise ImageError(f"image: image is empty (shape {tuple(image.shape)})")
    plan = plan_crop_resize(image.shape[0], image.shape[1], height, width)
    crop = image[plan.y0:plan.y0 + plan.crop_h, plan.x0:plan.x0 + plan.crop_w]
    if (plan.crop_h, plan.crop_w) == (height, width):
        return np.array(crop, copy=True, order="C"), plan
    shrinking = plan.crop_w >= width and plan.crop_h >= height
    interp = cv2.INTER_AREA if shrinking else cv2.INTER_LINEAR
    out = cv2.resize(np.ascontiguousarray(crop), (width, height), interpolation=interp)
    return out, plan


def fit_to_working_size(image: np.ndarray, max_side: int = CAMERA_WORKING_SIZE
                        ) -> tuple[np.ndarray, CropResize]:
    """``image uint8 [H, W, 3]`` no longer than ``max_side`` on either side: shrunk as a whole
    (no crop, ``cv2.INTER_AREA``, each side rounded to whole pixels), or a copy when it already
    fits. Returns ``(out, CropResize)`` (its crop is the whole image)."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 \
            or image.shape[2] != 3 or min(image.shape[:2]) == 0:
        raise ImageError(f"image: expected a non-empty uint8 [H, W, 3] array, got "
                         f"{getattr(image, 'dtype', type(image).__name__)} "
                         f"{getattr(image, 'shape', '')}")
    if isinstance(max_side, bool) or not isinstance(max_side, (int, np.integer)) or max_side < 1:
        raise ImageError(f"max_side: expected a positive integer, got {max_side!r}")
    H, W = image.shape[:2]
    s = min(1.0, max_side / max(H, W))
    h, w = max(1, int(round(H * s))), max(1, int(round(W * s)))
    plan = CropResize(H, W, 0, 0, W, H, h, w)
    if (h, w) == (H, W):
        return np.array(image, copy=True, order="C"), plan
    return cv2.resize(np.ascontiguousarray(image), (w, h), interpolation=cv2.INTER_AREA), plan


def camera_copies(photos: list[np.ndarray], model_size: tuple[int, int],
                  max_side: int = CAMERA_WORKING_SIZE) -> tuple[list[np.ndarray], np.ndarray]:
    """The copies of ``photos`` (uint8 [H, W, 3] each) the camera solve works on, and
    ``model_from_camera [3, 3]``: the affine map from their pixel coordinates to those of the
    model's images (``fit_to_model`` of the same photos to ``model_size`` (H, W)), so that the
    solved ``K`` becomes the model's ``model_from_camera @ K``.

    Photos of one size are shrunk as a whole (``fit_to_working_size``: the solve sees their
    full field of view). Photos of different sizes are first centre-cropped to the model's
    aspect, as ``fit_to_model`` does, at one size (longer side ``max_side`` or the smallest
    photo's crop, whichever is smaller), so that one camera can explain them all; the map is
    then photo 0's (the others differ by the rounding of their crop, under a pixel)."""
    H, W = model_size
    if all(p.shape == photos[0].shape for p in photos):
        copies = [fit_to_working_size(p, max_side) for p in photos]
    else:
        crops = [plan_crop_resize(p.shape[0], p.shape[1], H, W) for p in photos]
        side = min(max_side, min(max(c.crop_h, c.crop_w) for c in crops))
        s = side / max(H, W)
        size = (max(1, int(round(H * s))), max(1, int(round(W * s))))
        copies = [fit_to_model(p, *size) for p in photos]
    model = plan_crop_resize(photos[0].shape[0], photos[0].shape[1], H, W)
    return [c for c, _ in copies], model.matrix @ np.linalg.inv(copies[0][1].matrix)
