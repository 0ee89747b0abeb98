"""What the routes of ``iris-serve`` share: the runtime, the operating limits (``ServeConfig``),
the worker pool, the scene store, the render streams and the metrics, and the checks of a request
that the runtime does not make itself (the server's own limits, each stated with the flag that
sets it).

One limit per thing: where the service has a lower limit than the runtime (output pixels, photos
per request, pixels per photo), the service checks its own first, so a client is only ever told
the limit that applies to it.
"""
from __future__ import annotations

import hmac
import io
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np
from PIL import Image
from starlette.datastructures import UploadFile
from starlette.requests import Request

from ..errors import InputError
from ..limits import MAX_OUTPUT_PIXELS, output_size
from ..quality import PRECISIONS, QUALITY_PRESETS
from ..runtime import IrisRuntime
from .errors import PayloadTooLarge, Unauthorized, Unprocessable
from .metrics import Metrics
from .pool import WorkerPool
from .store import SceneStore, StoredScene
from .streams import Streams

__all__ = ["ServeConfig", "Service", "MAX_JSON_BYTES", "MAX_TEXT_FIELDS", "MAX_TEXT_BYTES",
           "DECODER_MAX_PIXELS", "png", "photo_size", "get_service"]

#: A render or orbit request is a few numbers: a JSON body over this is not one.
MAX_JSON_BYTES = 64 * 1024
#: Text fields of a multipart request (the routes take at most one, ``cameras``), and bytes each.
MAX_TEXT_FIELDS = 16
MAX_TEXT_BYTES = 64 * 1024
#: Pillow refuses to decode an image of more pixels than this (a decompression bomb): the runtime's
#: decoder would answer such a photo 400, so ``--max-photo-pixels`` may not exceed it (the
#: service's 413 then always comes first).
DECODER_MAX_PIXELS = (2 * Image.MAX_IMAGE_PIXELS if Image.MAX_IMAGE_PIXELS is not None
                      else 2**63)


@dataclass(frozen=True)
class ServeConfig:
    """Operating limits of the service (iris-serve's flags; docs/SERVING.md)."""
    workers: int = 1                     # jobs (encode/render/locate) running at once
    queue: int = 8                       # jobs waiting for a worker before 429
    queue_timeout: float = 30.0          # seconds a job may wait before 503
    store_bytes: int = 512 * 2**20       # scene store bound (LRU)
    max_scenes: int = 256
    max_photos: int = 16                 # per POST /scenes (and at most the model's max_views)
    max_upload_bytes: int = 64 * 2**20   # request body
    max_photo_pixels: int = 40_000_000   # per photo, read from its header before decoding
    max_output_pixels: int = 1024 * 1024  # per rendered view (<= limits.MAX_OUTPUT_PIXELS)
    max_orbit_frames: int = 120
    token: str | None = None             # bearer token for /scenes (None: open)

    def __post_init__(self):
        if not 1 <= self.max_output_pixels <= MAX_OUTPUT_PIXELS:
            raise ValueError(f"max_output_pixels: expected 1..{MAX_OUTPUT_PIXELS}")
        if not 1 <= self.max_photo_pixels <= DECODER_MAX_PIXELS:
            raise ValueError(f"max_photo_pixels: expected 1..{DECODER_MAX_PIXELS} (Pillow's "
                             f"decompression-bomb limit, which the runtime's decoder applies)")
        for name in ("workers", "store_bytes", "max_scenes", "max_photos", "max_upload_bytes",
                     "max_orbit_frames"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected a positive number")

    def public(self) -> dict:
        """The limits a client may know (never the token)."""
        return {k: v for k, v in asdict(self).items() if k != "token"}


def png(image: np.ndarray) -> bytes:
    """Lossless PNG of uint8 RGB [H, W, 3] or uint16 [H, W] (fast compression)."""
    if image.ndim == 3:
        image = image[..., ::-1]                          # OpenCV wants BGR
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise RuntimeError("cv2.imencode failed to write a PNG")
    return buf.tobytes()


def photo_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) that the photo's header declares, read without decoding and without
    Pillow's decompression-bomb check (which would hide the size of a bomb); None when no
    format Pillow reads recognises it (the runtime's decoder then says what is wrong). Tries
    the formats as ``Image.open`` does."""
    Image.init()
    prefix = data[:16]
    for fmt in Image.ID:
        factory, accept = Image.OPEN[fmt]
        try:
            result = not accept or accept(prefix)
            if isinstance(result, str) or not result:   # a str: "looks like it, unsupported"
                continue
            with factory(io.BytesIO(data), "") as im:
                return im.size
        except Exception:                                 # not this format (or broken)
            continue
    return None


class Service:
    """The shared state of one app over ``runtime`` with ``config``'s limits."""

    def __init__(self, runtime: IrisRuntime, config: ServeConfig):
        self.rt, self.config = runtime, config
        self.metrics = Metrics()
        self.pool = WorkerPool(config.workers, config.queue, config.queue_timeout,
                               on_job=self.metrics.observe_job,
                               on_reject=self.metrics.observe_reject)
        self.store = SceneStore(config.store_bytes, config.max_scenes,
                                on_evict=self.metrics.evictions.inc)
        self.streams = Streams(on_reject=self.metrics.observe_reject)
        self.metrics.bind(self.pool, self.store)
        rt = runtime
        # Photos per POST /scenes: the lower of the flag and the model's encoder limit, and
        # messages name the one that applies.
        self.max_photos = min(config.max_photos, rt.max_views)
        self.max_photos_source = ("iris-serve --max-photos" if config.max_photos <= rt.max_views
                                  else f"the model's max_views, {rt.max_views}: its encoder's "
                                       f"memory grows with the square of the views")
        self.max_json_bytes = min(MAX_JSON_BYTES, config.max_upload_bytes)
        self.precisions = [p for p, graph in PRECISIONS.items() if graph in rt.manifest.graphs]
        # Every preset renders on every model (two scales apply to explicit-colour models only).
        self.presets = list(QUALITY_PRESETS)
        source = rt.manifest.raw.get("source") or {}
        self.model_name = Path(str(source.get("checkpoint") or rt.model_dir.name)).stem

    # -- what /healthz says ------------------------------------------------------------------
    def health(self) -> dict:
        rt = self.rt
        H, W = rt.image_size
        return {"status": "ok",
                "model": {"name": self.model_name, "format": rt.manifest.raw.get("format"),
                          "version": rt.manifest.version, "image_size": [H, W],
                          "default_cameras": rt.default_cameras, "max_views": rt.max_views,
                          "explicit_rgb": rt.manifest.explicit_rgb,
                          "precisions": self.precisions, "quality_presets": self.presets,
                          "default_quality": rt.default_quality,
                          "providers": list(rt.providers)},
                "limits": {**self.config.public(), "max_photos": self.max_photos},
                "auth": self.config.token is not None, "scenes": len(self.store)}

    # -- checks ------------------------------------------------------------------------------
    def check_token(self, request: Request) -> None:
        """``Unauthorized`` unless the request carries the server's bearer token (if it has
        one); compared in constant time."""
        token = self.config.token
        if token is None:
            return
        scheme, _, given = request.headers.get("authorization", "").partition(" ")
        if scheme.lower() != "bearer" or not hmac.compare_digest(
                given.strip().encode("utf-8", "replace"), token.encode("utf-8")):
            raise Unauthorized("Authorization: expected the header 'Bearer <token>' with the "
                               "token of iris-serve --token-file")

    def output_size(self, height: int | None, width: int | None) -> tuple[int, int]:
        """The output's (height, width) (``limits.output_size``), or ``PayloadTooLarge`` over
        ``--max-output-pixels`` (never above the runtime's limit, so the only one that applies)."""
        h, w = output_size(self.rt.image_size, height, width)
        limit = self.config.max_output_pixels
        if h * w > limit:
            raise PayloadTooLarge(f"height, width: {h}x{w} = {h * w} output pixels, at most "
                                  f"{limit} (iris-serve --max-output-pixels)")
        return h, w

    @staticmethod
    def check_video_size(h: int, w: int) -> None:
        """mp4v frames have even sides of at least 2: OpenCV's writer refuses a side of 1 and
        silently drops the last row or column of an odd side, so such a size is refused."""
        if h < 2 or w < 2 or h % 2 or w % 2:
            raise Unprocessable(f"height, width: {h}x{w}; an mp4v video needs even sides of at "
                                f"least 2 (its encoder refuses a side of 1 and drops the last "
                                f"row or column of an odd one)")

    def check_precision(self, precision: str | None) -> None:
        if precision is not None and precision not in self.precisions:
            raise Unprocessable(f"precision: this model has the renderers {self.precisions}, "
                                f"not {precision!r} (export with --quantize int8 for int8)")

    def check_frames(self, frames: int, given: bool) -> None:
        """``PayloadTooLarge`` over ``--max-orbit-frames`` (the request models make frames
        positive); ``given``: the client sent it (else it is the default, and said so)."""
        if frames > self.config.max_orbit_frames:
            what = "" if given else " (the default when none is given)"
            raise PayloadTooLarge(f"frames: {frames}{what}, at most "
                                  f"{self.config.max_orbit_frames} (iris-serve "
                                  f"--max-orbit-frames)")

    async def read_photo(self, part: UploadFile, name: str) -> bytes:
        """The bytes of one uploaded photo, or ``PayloadTooLarge`` when its header declares more
        than ``--max-photo-pixels`` (read before decoding; a file that is no image is left to
        the runtime's decoder, which says so)."""
        data = await part.read()
        size = photo_size(data)
        limit = self.config.max_photo_pixels
        if size is not None and size[0] * size[1] > limit:
            w, h = size
            raise PayloadTooLarge(f"{name}: {w}x{h} = {w * h} pixels, at most {limit} per photo "
                                  f"(iris-serve --max-photo-pixels)")
        return data

    def scene_json(self, entry: StoredScene) -> dict:
        """The scene as the API returns it (cameras in the convention of docs/ARCHITECTURE.md)."""
        s = entry.scene
        return {"scene_id": entry.scene_id, "views": s.num_views,
                "image_size": list(s.image_size), "world_from_cam": s.world_from_cam.tolist(),
                "intrinsics": s.K.tolist(), "focal": s.focal.tolist(),
                "camera_source": s.camera_source, "cameras": entry.cameras,
                "bytes": entry.nbytes}


def get_service(request: Request) -> Service:
    """The ``Service`` of the app serving ``request`` (a FastAPI dependency)."""
    return request.app.state.service
