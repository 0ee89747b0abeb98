"""The ASGI app of ``iris-serve``: a thin HTTP layer over one ``IrisRuntime``.

Every route calls the runtime's own public API (``encode``, ``render``, ``locate``) on the
worker pool, and the runtime's checks decide what is valid; the service adds only what a shared
server needs: a scene store, request limits, backpressure, a bearer token, metrics and logs.
The contract (statuses, bodies, limits) is documented in docs/SERVING.md.

    POST   /scenes                 multipart ``images`` (2+ photos), optional ``cameras`` -> 201 scene
    GET    /scenes/{id}            the scene JSON          DELETE /scenes/{id} -> 204
    POST   /scenes/{id}/render     JSON RenderRequest -> image/png (16-bit depth PNG with depth);
                                   with ``stream`` + ``seq``: 409 when a newer request of the
                                   stream made it stale before a worker took it (streams.py)
    POST   /scenes/{id}/locate     multipart ``image`` -> {"world_from_cam": 4x4}
    GET    /scenes/{id}/cameras.png  the solved cameras' picture (``camera_plot.draw_cameras``)
    GET    /scenes/{id}/orbit?frames=N  the orbit's poses (``orbit.orbit_poses``) and centre
    POST   /scenes/{id}/orbit.mp4  JSON OrbitRequest -> video/mp4 (iris-render --orbit's video)
    GET    /healthz, /metrics, / (the viewer), /static/...
"""
from __future__ import annotations

import contextlib
import hmac
import io
import json
import logging
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated, Literal

import cv2
import numpy as np
from fastapi import APIRouter, Depends, FastAPI, Request
from fastapi.responses import HTMLResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from PIL import Image
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException

from .. import cli as render_cli
from ..camera_plot import draw_cameras
from ..errors import InputError
from ..limits import MAX_OUTPUT_PIXELS
from ..orbit import orbit_poses, scene_centre
from ..quality import PRECISIONS, QUALITY_PRESETS
from ..runtime import IrisRuntime
from ..validation import snap_world_from_cam
from .errors import (BadRequest, PayloadTooLarge, Unauthorized, UnsupportedMediaType,
                     Unprocessable, Unsupported, field_message, install_handlers)
from .metrics import Metrics
from .observe import RequestObserver
from .pool import WorkerPool
from .store import SceneStore, StoredScene
from .streams import Streams

__all__ = ["ServeConfig", "RenderRequest", "OrbitRequest", "create_app", "warm_up"]

log = logging.getLogger("iris.serve")
STATIC = Path(__file__).resolve().parent / "static"
#: A render or orbit request is a few numbers: a JSON body over this is not one.
MAX_JSON_BYTES = 64 * 1024
#: ``seq`` of a render stream: an integer a browser holds exactly (2**53 - 1).
MAX_SEQ = 2**53 - 1


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
        for name in ("workers", "store_bytes", "max_scenes", "max_photos", "max_upload_bytes",
                     "max_photo_pixels", "max_orbit_frames"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected a positive number")

    def public(self) -> dict:
        """The limits a client may know (never the token)."""
        return {k: v for k, v in asdict(self).items() if k != "token"}


Quality = Literal[tuple(QUALITY_PRESETS)]          # type: ignore[valid-type]
Precision = Literal[tuple(PRECISIONS)]             # type: ignore[valid-type]
Pixels = Annotated[int, Field(gt=0)]
StreamId = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9._~-]+$")]
Seq = Annotated[int, Field(ge=0, le=MAX_SEQ)]


class RenderRequest(BaseModel):
    """``POST /scenes/{id}/render``: ``IrisRuntime.render``'s arguments as JSON."""
    model_config = ConfigDict(extra="forbid", strict=True)
    world_from_cam: list[list[float]]      # 4x4, the scene's frame (view 0 = identity), OpenCV axes
    height: Pixels | None = None           # None: the model's (one side alone keeps its aspect)
    width: Pixels | None = None
    quality: Quality | None = None         # type: ignore[valid-type]
    precision: Precision | None = None     # type: ignore[valid-type]
    depth: bool = False                    # a 16-bit depth PNG instead of the colour image
    # A moving camera: the client's stream token and the request's number in it (only grows).
    # A request still waiting for a worker when a larger seq of its stream arrives gets 409.
    stream: StreamId | None = None
    seq: Seq | None = None


class OrbitRequest(BaseModel):
    """``POST /scenes/{id}/orbit.mp4``: ``iris-render --orbit N`` as one request."""
    model_config = ConfigDict(extra="forbid", strict=True)
    frames: int = 24
    fps: int = 24
    height: Pixels | None = None
    width: Pixels | None = None
    quality: Quality | None = None         # type: ignore[valid-type]


def _json_body(model: type[BaseModel]) -> dict:
    """OpenAPI request body of a route that reads ``model`` itself (``read_json``)."""
    return {"requestBody": {"required": True, "content": {
        "application/json": {"schema": model.model_json_schema()}}}}


def _multipart(field: str, what: str, options: tuple[str, ...] = ()) -> dict:
    """OpenAPI request body of a route that reads photos itself (``read_photos``)."""
    props = {field: {"type": "array", "items": {"type": "string", "format": "binary"},
                     "description": what}} | {o: {"type": "string"} for o in options}
    return {"requestBody": {"required": True, "content": {"multipart/form-data": {
        "schema": {"type": "object", "properties": props, "required": [field]}}}}}


def _png(image: np.ndarray) -> bytes:
    """Lossless PNG of uint8 RGB [H, W, 3] or uint16 [H, W] (fast compression)."""
    if image.ndim == 3:
        image = image[..., ::-1]                          # OpenCV wants BGR
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(image), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise RuntimeError("cv2.imencode failed to write a PNG")
    return buf.tobytes()


def _photo_pixels(data: bytes, name: str, limit: int) -> None:
    """``PayloadTooLarge`` when the photo's header says more than ``limit`` pixels (read before
    decoding); an unreadable header is left to the runtime's decoder to report."""
    try:
        with Image.open(io.BytesIO(data)) as im:
            w, h = im.size
    except Image.DecompressionBombError:
        w = h = limit + 1
    except Exception:                                     # not an image: the runtime says so
        return
    if w * h > limit:
        raise PayloadTooLarge(f"{name}: {w}x{h} = {w * h} pixels, at most {limit} per photo "
                              f"(iris-serve --max-photo-pixels)")


def scene_json(entry: StoredScene) -> dict:
    """The scene as the API returns it (cameras in the convention of docs/ARCHITECTURE.md)."""
    s = entry.scene
    return {"scene_id": entry.scene_id, "views": s.num_views, "image_size": list(s.image_size),
            "world_from_cam": s.world_from_cam.tolist(), "intrinsics": s.K.tolist(),
            "focal": s.focal.tolist(), "camera_source": s.camera_source,
            "cameras": entry.cameras, "bytes": entry.nbytes}


def warm_up(rt: IrisRuntime) -> None:
    """Run both graphs once on blank photos: the sessions exist (and the graphs are checked)
    before the first request, so a broken model stops the server at start-up, not a client."""
    H, W = rt.image_size
    blank = [np.full((H, W, 3), 127, np.uint8)] * 2
    rt.render(rt.encode(blank, cameras="model"), 0, height=2, width=2)


def create_app(runtime: IrisRuntime, config: ServeConfig = ServeConfig()) -> FastAPI:
    """The service over ``runtime`` with ``config``'s limits (see the module docstring)."""
    rt = runtime
    metrics = Metrics()
    pool = WorkerPool(config.workers, config.queue, config.queue_timeout,
                      on_job=metrics.observe_job, on_reject=metrics.observe_reject)
    store = SceneStore(config.store_bytes, config.max_scenes, on_evict=metrics.evictions.inc)
    streams = Streams(on_reject=metrics.observe_reject)
    metrics.bind(pool, store)
    max_photos = min(config.max_photos, rt.max_views)
    precisions = [p for p, graph in PRECISIONS.items() if graph in rt.manifest.graphs]
    # Every preset renders on every model (two scales apply to explicit-colour models only).
    presets = list(QUALITY_PRESETS)
    source = rt.manifest.raw.get("source") or {}
    model_name = Path(str(source.get("checkpoint") or rt.model_dir.name)).stem

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        log.info("ready", extra={"fields": {"model": model_name, "model_dir": str(rt.model_dir),
                                            **config.public()}})
        yield
        log.info("shutting down: refusing new jobs, waiting for running ones")
        pool.shutdown()
        log.info("stopped")

    # The schema is at /openapi.json; FastAPI's /docs page would load its scripts from a CDN.
    app = FastAPI(title="iris-serve", version="1", lifespan=lifespan, docs_url=None,
                  redoc_url=None)
    install_handlers(app)
    app.add_middleware(RequestObserver, metrics=metrics, max_body_bytes=config.max_upload_bytes)
    app.state.pool, app.state.store, app.state.metrics = pool, store, metrics
    app.state.streams = streams

    async def require_token(request: Request) -> None:
        if config.token is None:
            return
        scheme, _, given = request.headers.get("authorization", "").partition(" ")
        if scheme.lower() != "bearer" or not hmac.compare_digest(
                given.strip().encode("utf-8", "replace"), config.token.encode("utf-8")):
            raise Unauthorized("Authorization: expected the header 'Bearer <token>' with the "
                               "token of iris-serve --token-file")

    async def read_json(request: Request, model: type[BaseModel]):
        ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
        if ctype != "application/json":
            raise UnsupportedMediaType(f"body: expected Content-Type application/json, got "
                                       f"{ctype or 'none'}")
        raw = await request.body()
        if len(raw) > MAX_JSON_BYTES:
            raise PayloadTooLarge(f"body: {len(raw)} bytes of JSON, at most {MAX_JSON_BYTES}")
        try:
            doc = json.loads(raw)
        except (ValueError, UnicodeDecodeError) as exc:
            raise BadRequest(f"body: not valid JSON ({exc})") from None
        try:
            return model.model_validate(doc)
        except ValidationError as exc:
            raise Unprocessable(field_message(exc.errors())) from None

    async def read_photos(request: Request, field: str, at_least: int, at_most: int,
                          options: tuple[str, ...] = ()):
        """The files of multipart ``field`` (bytes each) and the text fields ``options``."""
        ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
        if ctype != "multipart/form-data":
            raise UnsupportedMediaType(f"body: expected multipart/form-data with photos in "
                                       f"'{field}', got {ctype or 'none'}")
        try:
            form = await request.form(max_files=at_most, max_fields=16, max_part_size=64 * 1024)
        except StarletteHTTPException as exc:
            if "Too many files" in str(exc.detail):
                raise PayloadTooLarge(f"{field}: more than {at_most} photo(s) in one request "
                                      f"(iris-serve --max-photos, at most the model's "
                                      f"max_views {rt.max_views})") from None
            raise BadRequest(f"body: {exc.detail}") from None
        try:
            unknown = sorted(set(form.keys()) - {field, *options})
            if unknown:
                expected = " and ".join([f"'{field}' files", *(f"'{o}'" for o in options)])
                raise Unprocessable(f"{unknown[0]}: unknown form field (expected {expected})")
            parts = form.getlist(field)
            if any(not isinstance(p, UploadFile) for p in parts):
                raise Unprocessable(f"{field}: expected files (parts with a filename), got a "
                                    f"text field")
            if len(parts) < at_least:
                raise Unprocessable(f"{field}: expected at least {at_least} photo(s) in the "
                                    f"multipart field '{field}', got {len(parts)}")
            if len(parts) > at_most:
                raise PayloadTooLarge(f"{field}: {len(parts)} photos, at most {at_most}")
            photos = []
            for i, part in enumerate(parts):
                name = f"{field}[{i}]" if at_most > 1 else field
                data = await part.read()
                _photo_pixels(data, name, config.max_photo_pixels)
                photos.append(data)
            fields = {}
            for name in options:
                value = form.get(name)
                if value is not None and not isinstance(value, str):
                    raise Unprocessable(f"{name}: expected a text field, got a file")
                fields[name] = value
            return photos, fields
        finally:
            await form.close()

    def render_png(scene, pose, req: RenderRequest, h: int, w: int) -> bytes:
        if not req.depth:
            return _png(rt.render(scene, pose, height=h, width=w, quality=req.quality,
                                  precision=req.precision))
        result = rt.render(scene, pose, height=h, width=w, quality=req.quality,
                           precision=req.precision, depth=True)
        return _png(render_cli.depth_uint16(result.depth, rt.far))

    def check_size(height, width) -> tuple[int, int]:
        try:                # the request model made them positive: only the runtime's limit is left
            h, w = rt.check_output_size(height, width)
        except InputError as exc:
            raise PayloadTooLarge(str(exc)) from None
        if h * w > config.max_output_pixels:
            raise PayloadTooLarge(f"height, width: {h}x{w} = {h * w} output pixels, at most "
                                  f"{config.max_output_pixels} (iris-serve --max-output-pixels)")
        return h, w

    def check_precision(precision) -> None:
        if precision is not None and precision not in precisions:
            raise Unprocessable(f"precision: this model has the renderers {precisions}, not "
                                f"{precision!r} (export with --quantize int8 for int8)")

    def orbit_video(scene, req: OrbitRequest, h: int, w: int) -> bytes:
        poses = orbit_poses(scene.world_from_cam, req.frames, near=rt.near, far=rt.far)
        with tempfile.TemporaryDirectory(prefix="iris-orbit-") as tmp:
            path = Path(tmp) / "orbit.mp4"
            writer = render_cli.open_video(path, req.fps, (h, w))
            if writer is None:
                raise Unsupported("orbit.mp4: this server's OpenCV has no mp4v encoder")
            try:
                for T in poses:
                    image = rt.render(scene, T, height=h, width=w, quality=req.quality)
                    writer.write(np.ascontiguousarray(image[..., ::-1]))
            finally:
                writer.release()
            return path.read_bytes()

    # -- public routes ---------------------------------------------------------------------
    @app.get("/", include_in_schema=False)
    async def viewer():
        return HTMLResponse((STATIC / "index.html").read_text(encoding="utf-8"))

    @app.get("/favicon.ico", include_in_schema=False)
    async def favicon():
        return Response((STATIC / "favicon.ico").read_bytes(), media_type="image/x-icon",
                        headers={"Cache-Control": "public, max-age=86400"})

    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    @app.get("/healthz")
    async def healthz():
        H, W = rt.image_size
        return {"status": "ok",
                "model": {"name": model_name, "format": rt.manifest.raw.get("format"),
                          "version": rt.manifest.version, "image_size": [H, W],
                          "default_cameras": rt.default_cameras, "max_views": rt.max_views,
                          "explicit_rgb": rt.manifest.explicit_rgb, "precisions": precisions,
                          "quality_presets": presets, "default_quality": rt.default_quality,
                          "providers": list(rt.providers)},
                "limits": {**config.public(), "max_photos": max_photos},
                "auth": config.token is not None, "scenes": len(store)}

    @app.get("/metrics", include_in_schema=False)
    async def metrics_route():
        body, ctype = metrics.exposition()
        return Response(body, media_type=ctype)

    # -- scenes (bearer token when configured) ---------------------------------------------
    scenes = APIRouter(prefix="/scenes", dependencies=[Depends(require_token)])

    @scenes.post("", status_code=201, openapi_extra=_multipart("images", "2 or more photos",
                                                               ("cameras",)))
    async def create_scene(request: Request):
        photos, fields = await read_photos(request, "images", 2, max_photos, ("cameras",))
        cameras = fields["cameras"] or rt.default_cameras
        scene = await pool.run("encode", rt.encode, photos, cameras)
        entry = store.put(scene, cameras)
        return JSONResponse(scene_json(entry), status_code=201,
                            headers={"Location": f"/scenes/{entry.scene_id}"})

    @scenes.get("/{scene_id}")
    async def get_scene(scene_id: str):
        return scene_json(store.get(scene_id))

    @scenes.delete("/{scene_id}", status_code=204)
    async def delete_scene(scene_id: str):
        store.delete(scene_id)
        return Response(status_code=204)

    @scenes.post("/{scene_id}/render", openapi_extra=_json_body(RenderRequest),
                 response_class=Response, responses={200: {"content": {"image/png": {}}}})
    async def render(scene_id: str, request: Request):
        entry = store.get(scene_id)
        req = await read_json(request, RenderRequest)
        pose = snap_world_from_cam(req.world_from_cam, "world_from_cam")
        h, w = check_size(req.height, req.width)
        check_precision(req.precision)
        if (req.stream is None) != (req.seq is None):
            given, missing = ("stream", "seq") if req.seq is None else ("seq", "stream")
            raise Unprocessable(f"{missing}: required with {given} (a render stream is named by "
                                f"both)")
        with streams.ticket(req.stream, req.seq) as ticket:
            png = await pool.run("render", render_png, entry.scene, pose, req, h, w,
                                 superseded=None if ticket is None else ticket.superseded)
        headers = {"X-Iris-Depth-Far": f"{rt.far:g}"} if req.depth else {}
        if req.seq is not None:
            headers["X-Iris-Seq"] = str(req.seq)
        return Response(png, media_type="image/png", headers=headers)

    @scenes.post("/{scene_id}/locate", openapi_extra=_multipart("image", "one photo"))
    async def locate(scene_id: str, request: Request):
        entry = store.get(scene_id)
        photos, _ = await read_photos(request, "image", 1, 1)
        pose = await pool.run("locate", rt.locate, entry.scene, photos[0])
        return {"world_from_cam": pose.tolist()}

    @scenes.get("/{scene_id}/cameras.png")
    async def cameras_png(scene_id: str):
        s = store.get(scene_id).scene
        what = "predicted" if s.camera_source == "model" else s.camera_source
        picture = await pool.run("cameras", lambda: _png(draw_cameras(
            s.world_from_cam, s.K, size=(480, 640),
            title=f"{what} cameras of the {s.num_views} input(s)")))
        return Response(picture, media_type="image/png")

    def check_frames(frames: int) -> None:
        if frames < 1:
            raise Unprocessable(f"frames: expected a positive integer, got {frames}")
        if frames > config.max_orbit_frames:
            raise PayloadTooLarge(f"frames: {frames}, at most {config.max_orbit_frames} "
                                  f"(iris-serve --max-orbit-frames)")

    @scenes.get("/{scene_id}/orbit")
    async def orbit(scene_id: str, frames: int = 24):
        s = store.get(scene_id).scene
        check_frames(frames)
        poses = orbit_poses(s.world_from_cam, frames, near=rt.near, far=rt.far)
        centre = scene_centre(s.world_from_cam, rt.near, rt.far)
        return {"world_from_cam": poses.tolist(), "centre": centre.tolist()}

    @scenes.post("/{scene_id}/orbit.mp4", openapi_extra=_json_body(OrbitRequest),
                 response_class=Response, responses={200: {"content": {"video/mp4": {}}}})
    async def orbit_mp4(scene_id: str, request: Request):
        entry = store.get(scene_id)
        req = await read_json(request, OrbitRequest)
        check_frames(req.frames)
        if not 1 <= req.fps <= 120:
            raise Unprocessable(f"fps: expected 1..120, got {req.fps}")
        h, w = check_size(req.height, req.width)
        video = await pool.run("orbit", orbit_video, entry.scene, req, h, w)
        return Response(video, media_type="video/mp4",
                        headers={"Content-Disposition": 'attachment; filename="orbit.mp4"'})

    app.include_router(scenes)
    return app

