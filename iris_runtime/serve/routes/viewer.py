"""The viewer page (``GET /``), its icon and its files (``/static/...``): plain HTML, CSS and JS
from the package, no CDN; a client of the API and nothing else."""
from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, FastAPI
from fastapi.responses import HTMLResponse, Response
from fastapi.staticfiles import StaticFiles

from ..routing import ServiceRoute

__all__ = ["router", "STATIC", "mount_static"]

STATIC = Path(__file__).resolve().parents[1] / "static"
router = APIRouter(route_class=ServiceRoute, include_in_schema=False)


@router.get("/")
async def viewer() -> HTMLResponse:
    return HTMLResponse((STATIC / "index.html").read_text(encoding="utf-8"))


@router.get("/favicon.ico")
async def favicon() -> Response:
    return Response((STATIC / "favicon.ico").read_bytes(), media_type="image/x-icon",
                    headers={"Cache-Control": "public, max-age=86400"})


def mount_static(app: FastAPI) -> None:
    app.mount("/static", StaticFiles(directory=STATIC), name="static")
