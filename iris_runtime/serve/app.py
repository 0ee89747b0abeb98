"""The ASGI app of ``iris-serve``: a thin HTTP layer over one ``IrisRuntime``.

Every route calls the runtime's own public API (``encode``, ``render``, ``locate``) on the
worker pool, and the runtime's checks decide what is valid; the service adds only what a shared
server needs: a scene store, request limits, backpressure, a bearer token, metrics and logs.
The contract (statuses, bodies, limits) is documented in docs/SERVING.md.

    POST   /scenes                 multipart ``images`` (2+ photos), optional ``cameras`` -> 201
    GET    /scenes/{id}            the scene JSON          DELETE /scenes/{id} -> 204
    POST   /scenes/{id}/render     JSON RenderRequest -> image/png (16-bit depth PNG with depth);
                                   with ``stream`` + ``seq``: 409 when a newer request of the
                                   stream made it stale before a worker took it (streams.py)
    POST   /scenes/{id}/locate     multipart ``image`` -> {"world_from_cam": 4x4}
    GET    /scenes/{id}/cameras.png  the solved cameras' picture (``camera_plot.draw_cameras``)
    GET    /scenes/{id}/orbit?frames=N  the orbit's poses (``orbit.orbit_poses``) and centre
    POST   /scenes/{id}/orbit.mp4  JSON OrbitRequest -> video/mp4 (iris-render --orbit's video)
    GET    /healthz, /metrics, / (the viewer), /static/...

Where each part lives: ``routes/`` (one router per concern), ``models`` (the request and response
bodies), ``routing`` (what is checked before a body is read), ``service`` (the shared state and the
server's own limits), ``errors`` (the one error body and status table), ``pool``, ``store``,
``streams``, ``metrics``, ``observe``.
"""
from __future__ import annotations

import contextlib
import logging

import numpy as np
from fastapi import FastAPI, Security
from fastapi.security import HTTPBearer

from ..runtime import IrisRuntime
from .errors import install_handlers
from .models import OrbitRequest, RenderRequest
from .observe import RequestObserver
from .routes import health, locate, render, scenes, viewer
from .service import ServeConfig, Service

__all__ = ["ServeConfig", "RenderRequest", "OrbitRequest", "create_app", "warm_up"]

log = logging.getLogger("iris.serve")


def warm_up(rt: IrisRuntime) -> None:
    """Run both graphs once on blank photos: the sessions exist (and the graphs are checked)
    before the first request, so a broken model stops the server at start-up, not a client."""
    H, W = rt.image_size
    blank = [np.full((H, W, 3), 127, np.uint8)] * 2
    rt.render(rt.encode(blank, cameras="model"), 0, height=2, width=2)


def create_app(runtime: IrisRuntime, config: ServeConfig = ServeConfig()) -> FastAPI:
    """The service over ``runtime`` with ``config``'s limits (see the module docstring)."""
    service = Service(runtime, config)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        log.info("ready", extra={"fields": {"model": service.model_name,
                                            "model_dir": str(runtime.model_dir),
                                            **config.public()}})
        yield
        log.info("shutting down: refusing new jobs, waiting for running ones")
        service.pool.shutdown()
        log.info("stopped")

    # The schema is at /openapi.json; FastAPI's /docs page would load its scripts from a CDN.
    app = FastAPI(title="iris-serve", version="1", lifespan=lifespan, docs_url=None,
                  redoc_url=None)
    install_handlers(app)
    app.add_middleware(RequestObserver, metrics=service.metrics,
                       max_body_bytes=config.max_upload_bytes,
                       retry_after=service.pool.retry_after)
    app.state.service = service
    app.state.pool, app.state.store = service.pool, service.store
    app.state.metrics, app.state.streams = service.metrics, service.streams

    # The token is checked before any body is read (routing.ScenesRoute); this dependency only
    # declares the scheme in the OpenAPI schema, on a server that has a token.
    bearer = [Security(HTTPBearer(auto_error=False))] if config.token is not None else []
    app.include_router(health.router)
    for router in (scenes.router, render.router, locate.router):
        app.include_router(router, dependencies=bearer)
    app.include_router(viewer.router)
    viewer.mount_static(app)
    return app
