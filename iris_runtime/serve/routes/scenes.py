"""Scenes: ``POST /scenes`` (encode photos, 201 + ``Location``), ``GET`` / ``DELETE
/scenes/{id}`` and ``GET /scenes/{id}/cameras.png`` (the solved cameras' picture)."""
from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, File, Form, UploadFile
from fastapi.responses import Response

from ...camera_plot import draw_cameras
from ..models import SceneOut
from ..routing import ScenesRoute
from ..service import png
from . import SceneDep, ServiceDep, errors

__all__ = ["router"]

router = APIRouter(prefix="/scenes", route_class=ScenesRoute, tags=["scenes"],
                   responses=errors(401))


@router.post("", status_code=201, response_model=SceneOut,
             responses=errors(400, 413, 415, 422, 429, 503))
async def create_scene(
        images: Annotated[list[UploadFile], File(
            min_length=2, description="2 or more photos (PNG, JPEG, ...: any size), at most "
                                      "/healthz's limits.max_photos")],
        service: ServiceDep, response: Response,
        cameras: Annotated[str | None, Form(
            description="model, solve or refined (default: /healthz's "
                        "model.default_cameras)")] = None) -> dict:
    photos = [await service.read_photo(part, f"images[{i}]") for i, part in enumerate(images)]
    cameras = cameras or service.rt.default_cameras
    scene = await service.pool.run("encode", service.rt.encode, photos, cameras)
    entry = service.store.put(scene, cameras)
    response.headers["Location"] = f"/scenes/{entry.scene_id}"
    return service.scene_json(entry)


@router.get("/{scene_id}", response_model=SceneOut, responses=errors(404))
async def get_scene(entry: SceneDep, service: ServiceDep) -> dict:
    return service.scene_json(entry)


@router.delete("/{scene_id}", status_code=204, response_class=Response, responses=errors(404))
async def delete_scene(scene_id: str, service: ServiceDep) -> Response:
    service.store.delete(scene_id)
    return Response(status_code=204)


@router.get("/{scene_id}/cameras.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}, "description": "the cameras seen "
                             "from above (camera_plot.draw_cameras)"}, **errors(404, 429, 503)})
async def cameras_png(entry: SceneDep, service: ServiceDep) -> Response:
    s = entry.scene
    what = "predicted" if s.camera_source == "model" else s.camera_source
    picture = await service.pool.run("cameras", lambda: png(draw_cameras(
        s.world_from_cam, s.K, size=(480, 640),
        title=f"{what} cameras of the {s.num_views} input(s)")))
    return Response(picture, media_type="image/png")
