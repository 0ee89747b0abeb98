"""Rendering: ``POST /scenes/{id}/render`` (one view as PNG, or its 16-bit depth), ``GET
/scenes/{id}/orbit`` (``iris-render --orbit N``'s poses and the point they look at) and ``POST
/scenes/{id}/orbit.mp4`` (that orbit as an mp4v video)."""
from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Query, Request
from fastapi.responses import Response

from ... import render_job
from ...errors import InputError
from ...orbit import orbit_poses, scene_centre
from ...runtime import IrisRuntime
from ...scene import Scene
from ...validation import snap_world_from_cam
from ..errors import Unprocessable, Unsupported
from ..models import OrbitOut, OrbitRequest, RenderRequest
from ..routing import ScenesRoute
from ..service import png
from . import SceneDep, ServiceDep, errors

__all__ = ["router"]

router = APIRouter(prefix="/scenes", route_class=ScenesRoute, tags=["render"],
                   responses=errors(401, 404))


def _as_request_field(exc: InputError) -> InputError:
    """The runtime names a render's pose ``pose``; the request's field is ``world_from_cam``."""
    text = str(exc)
    return InputError("world_from_cam:" + text[5:]) if text.startswith("pose:") else exc


def _render_png(rt: IrisRuntime, scene: Scene, pose: np.ndarray, req: RenderRequest, h: int,
                w: int) -> tuple[bytes, float]:
    """The PNG of one view and its ``coverage``; a view that sees none of the scene is refused
    (422), not answered with a frame of the renderer's empty-ray colour."""
    try:
        result = rt.render(scene, pose, height=h, width=w, quality=req.quality,
                           precision=req.precision, depth=True)
    except InputError as exc:
        raise _as_request_field(exc) from None
    if result.coverage == 0:
        raise Unprocessable("world_from_cam: the camera sees none of the scene (no ray of the "
                            "view passes through a reference photo's field of view); aim it at "
                            "the scene or move it toward the photos' cameras")
    image = render_job.depth_uint16(result.depth, rt.far) if req.depth else result.image
    return png(image), result.coverage


@router.post("/{scene_id}/render", response_class=Response,
             responses={200: {"content": {"image/png": {}}, "description": "8-bit RGB, or with "
                              "depth a 16-bit depth PNG (X-Iris-Depth-Far); X-Iris-Coverage: "
                              "the fraction of pixels whose ray meets a reference photo's view "
                              "(422 when none does)"},
                        **errors(400, 409, 413, 415, 422, 429, 503)})
async def render(req: RenderRequest, entry: SceneDep, service: ServiceDep) -> Response:
    pose = snap_world_from_cam(req.world_from_cam, "world_from_cam")
    h, w = service.output_size(req.height, req.width)
    service.check_precision(req.precision)
    if (req.stream is None) != (req.seq is None):
        given, missing = ("stream", "seq") if req.seq is None else ("seq", "stream")
        raise Unprocessable(f"{missing}: required with {given} (a render stream is named by "
                            f"both)")
    with service.streams.ticket(req.stream, req.seq) as ticket:
        image, coverage = await service.pool.run(
            "render", _render_png, service.rt, entry.scene, pose, req, h, w,
            superseded=None if ticket is None else ticket.superseded)
    headers = {"X-Iris-Coverage": f"{coverage:.4f}"}
    if req.depth:
        headers["X-Iris-Depth-Far"] = f"{service.rt.far:g}"
    if req.seq is not None:
        headers["X-Iris-Seq"] = str(req.seq)
    return Response(image, media_type="image/png", headers=headers)


@router.get("/{scene_id}/orbit", response_model=OrbitOut, responses=errors(413, 422))
async def orbit(request: Request, entry: SceneDep, service: ServiceDep,
                frames: Annotated[int, Query(ge=1, description="at most iris-serve "
                                                               "--max-orbit-frames")] = 24) -> dict:
    service.check_frames(frames, given="frames" in request.query_params)
    s = entry.scene
    near, far = service.rt.unit_range          # where the cameras' unit puts the scene
    poses = orbit_poses(s.world_from_cam, frames, near=near, far=far)
    centre = scene_centre(s.world_from_cam, near, far)
    return {"world_from_cam": poses.tolist(), "centre": centre.tolist()}


def _orbit_video(rt: IrisRuntime, scene: Scene, req: OrbitRequest, h: int, w: int) -> bytes:
    near, far = rt.unit_range
    poses = orbit_poses(scene.world_from_cam, req.frames, near=near, far=far)
    with tempfile.TemporaryDirectory(prefix="iris-orbit-") as tmp:
        path = Path(tmp) / "orbit.mp4"
        writer = render_job.open_video(path, req.fps, (h, w))
        if writer is None:
            raise Unsupported("orbit.mp4: this server's OpenCV has no mp4v encoder")
        try:
            for T in poses:
                image = rt.render(scene, T, height=h, width=w, quality=req.quality)
                writer.write(np.ascontiguousarray(image[..., ::-1]))
        finally:
            writer.release()
        return path.read_bytes()


@router.post("/{scene_id}/orbit.mp4", response_class=Response,
             responses={200: {"content": {"video/mp4": {}}, "description": "mp4v, as "
                              "iris-render --orbit's orbit.mp4"},
                        **errors(400, 413, 415, 422, 429, 501, 503)})
async def orbit_mp4(req: OrbitRequest, entry: SceneDep, service: ServiceDep) -> Response:
    service.check_frames(req.frames, given="frames" in req.model_fields_set)
    h, w = service.output_size(req.height, req.width)
    service.check_video_size(h, w)
    video = await service.pool.run("orbit", _orbit_video, service.rt, entry.scene, req, h, w)
    return Response(video, media_type="video/mp4",
                    headers={"Content-Disposition": 'attachment; filename="orbit.mp4"'})
