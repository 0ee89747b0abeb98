"""The routers of ``iris-serve``, one per concern: ``health`` (/healthz, /metrics), ``scenes``
(encode, read, delete, the cameras' picture), ``render`` (a view, the orbit's poses, the orbit
video), ``locate`` (a photo's pose) and ``viewer`` (the page and its files). Each route is a call
of the runtime's public API through the ``Service`` (``service.py``); its body is declared with the
Pydantic models of ``models.py``, from which FastAPI validates it and writes the OpenAPI schema.
"""
from __future__ import annotations

from typing import Annotated

from fastapi import Depends

from ..models import ErrorOut
from ..service import Service, get_service
from ..store import StoredScene

__all__ = ["ServiceDep", "SceneDep", "errors", "scene_entry"]

ServiceDep = Annotated[Service, Depends(get_service)]

_WHAT = {400: "unreadable body or photo", 401: "token missing or wrong",
         404: "no such scene", 409: "superseded by a newer request of the render stream",
         413: "over a limit of the server", 415: "wrong Content-Type",
         422: "a value refused", 429: "worker pool and queue full (Retry-After)",
         501: "not supported by this server", 503: "queue timeout or shutdown (Retry-After)"}


def errors(*statuses: int) -> dict:
    """OpenAPI ``responses`` for error ``statuses``, each the one error body (``ErrorOut``), and
    ``default`` for the others a route may give (docs/SERVING.md, "Errors"), so that FastAPI
    adds no response of its own (its 422 body is not this service's)."""
    return {"default": {"model": ErrorOut, "description": "an error: docs/SERVING.md, 'Errors'"},
            **{s: {"model": ErrorOut, "description": _WHAT[s]} for s in statuses}}


def scene_entry(scene_id: str, service: ServiceDep) -> StoredScene:
    """The stored scene of the path's ``scene_id`` (404 when there is none)."""
    return service.store.get(scene_id)


SceneDep = Annotated[StoredScene, Depends(scene_entry)]
