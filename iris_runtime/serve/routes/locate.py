"""``POST /scenes/{id}/locate``: the pose of one new photo in the scene's frame
(``IrisRuntime.locate``; the scene is not changed)."""
from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, File, UploadFile

from ..models import LocateOut
from ..routing import ScenesRoute
from . import SceneDep, ServiceDep, errors

__all__ = ["router"]

router = APIRouter(prefix="/scenes", route_class=ScenesRoute, tags=["locate"],
                   responses=errors(401, 404))


@router.post("/{scene_id}/locate", response_model=LocateOut,
             responses=errors(400, 413, 415, 422, 429, 503))
async def locate(image: Annotated[UploadFile, File(description="one photo (any size)")],
                 entry: SceneDep, service: ServiceDep) -> dict:
    data = await service.read_photo(image, "image")
    pose = await service.pool.run("locate", service.rt.locate, entry.scene, data)
    return {"world_from_cam": pose.tolist()}
