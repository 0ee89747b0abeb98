"""``GET /healthz`` (the model, the limits, the scene count) and ``GET /metrics`` (Prometheus):
open to probes and scrapers, with or without a token."""
from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import Response

from ..models import HealthOut
from ..routing import ServiceRoute
from . import ServiceDep

__all__ = ["router"]

router = APIRouter(route_class=ServiceRoute, tags=["health"])


@router.get("/healthz", response_model=HealthOut)
async def healthz(service: ServiceDep) -> dict:
    return service.health()


@router.get("/metrics", include_in_schema=False)
async def metrics(service: ServiceDep) -> Response:
    body, ctype = service.metrics.exposition()
    return Response(body, media_type=ctype)
