"""The request and response bodies of ``iris-serve`` as Pydantic models: FastAPI validates the
requests with them and writes the OpenAPI schema (``/openapi.json``) from them and from the
routes' declarations; nothing of the schema is written by hand.

Request models are strict (``"height": 4.0`` is not an integer) and forbid unknown fields, so a
typo is a 422 naming it rather than a silently ignored knob.
"""
from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field

from ..manifest import CAMERAS
from ..quality import PRECISIONS, QUALITY_PRESETS

__all__ = ["RenderRequest", "OrbitRequest", "SceneOut", "LocateOut", "OrbitOut", "HealthOut",
           "ModelOut", "LimitsOut", "ErrorOut", "ErrorDetail", "MAX_SEQ", "Camera",
           "Quality", "Precision"]

#: ``seq`` of a render stream: an integer a browser holds exactly (2**53 - 1).
MAX_SEQ = 2**53 - 1

Quality = Literal[tuple(QUALITY_PRESETS)]          # type: ignore[valid-type]
Precision = Literal[tuple(PRECISIONS)]             # type: ignore[valid-type]
Camera = Literal[tuple(CAMERAS)]                   # type: ignore[valid-type]
Pixels = Annotated[int, Field(gt=0, description="pixels (None: the model's; one side alone "
                                                "keeps the model's aspect)")]
StreamId = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9._~-]+$")]
Seq = Annotated[int, Field(ge=0, le=MAX_SEQ)]
Matrix = list[list[float]]


class RenderRequest(BaseModel):
    """``POST /scenes/{id}/render``: ``IrisRuntime.render``'s arguments as JSON."""
    model_config = ConfigDict(extra="forbid", strict=True)
    world_from_cam: Matrix = Field(description="4x4 camera-to-world, the scene's frame (view 0 = "
                                               "identity), OpenCV axes")
    height: Pixels | None = None
    width: Pixels | None = None
    quality: Quality | None = Field(None, description="a preset of /healthz's quality_presets "
                                                      "(None: its default_quality)")
    precision: Precision | None = None
    depth: bool = Field(False, description="a 16-bit depth PNG instead of the colour image")
    # A moving camera: the client's stream token and the request's number in it (only grows).
    # A request still waiting for a worker when a larger seq of its stream arrives gets 409.
    stream: StreamId | None = Field(None, description="render stream token (with seq)")
    seq: Seq | None = Field(None, description="request number in the stream (with stream)")


class OrbitRequest(BaseModel):
    """``POST /scenes/{id}/orbit.mp4``: ``iris-render --orbit N`` as one request."""
    model_config = ConfigDict(extra="forbid", strict=True)
    frames: Annotated[int, Field(ge=1, description="at most iris-serve --max-orbit-frames")] = 24
    fps: Annotated[int, Field(ge=1, le=120)] = 24
    height: Pixels | None = None
    width: Pixels | None = None
    quality: Quality | None = None


class _Out(BaseModel):
    model_config = ConfigDict(protected_namespaces=())


class SceneOut(_Out):
    """An encoded scene (cameras in the convention of docs/ARCHITECTURE.md)."""
    scene_id: str
    views: int
    image_size: list[int] = Field(description="[H, W], the model's resolution")
    world_from_cam: list[Matrix] = Field(description="[V, 4, 4]")
    intrinsics: Matrix = Field(description="[3, 3], pixels of the model's resolution")
    focal: list[float] = Field(description="[fx / W, fy / H]")
    camera_source: str = Field(description="model, solve, refined or mixed")
    cameras: str = Field(description="the cameras asked for")
    bytes: int = Field(description="held in the scene store")


class LocateOut(_Out):
    world_from_cam: Matrix


class OrbitOut(_Out):
    world_from_cam: list[Matrix] = Field(description="[N, 4, 4], iris-render --orbit N's poses")
    centre: list[float] = Field(description="[3], the point the orbit looks at")


class ModelOut(_Out):
    name: str
    format: str | None
    version: int | str | None
    image_size: list[int]
    default_cameras: str
    max_views: int
    explicit_rgb: bool
    precisions: list[str]
    quality_presets: list[str]
    default_quality: str
    providers: list[str]


class LimitsOut(_Out):
    """``ServeConfig.public()`` with ``max_photos`` as it applies (at most the model's)."""
    workers: int
    queue: int
    queue_timeout: float
    store_bytes: int
    max_scenes: int
    max_photos: int
    max_upload_bytes: int
    max_photo_pixels: int
    max_output_pixels: int
    max_orbit_frames: int


class HealthOut(_Out):
    status: Literal["ok"]
    model: ModelOut
    limits: LimitsOut
    auth: bool
    scenes: int


class ErrorDetail(_Out):
    type: str
    message: str


class ErrorOut(_Out):
    """Every error of the service (iris_runtime/serve/errors.py)."""
    error: ErrorDetail
