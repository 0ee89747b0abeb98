"""What the service records about each request, in one ASGI middleware: a request id, the
request body limit, one JSON access-log line and the request metrics; and the JSON-lines log
format of every logger (uvicorn's included), so one parser reads the whole log.

An access line: ``{"ts", "level", "logger": "iris.access", "message": "request", "request_id",
"method", "path", "route", "status", "duration_ms", "bytes_in", "bytes_out", "client"}``. The query
string and the headers are never logged (a bearer token travels in a header).
"""
from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import re
import time
import uuid
from datetime import datetime, timezone
from typing import Callable

from .errors import PayloadTooLarge, error_response
from .metrics import Metrics

__all__ = ["JsonFormatter", "log_config", "RequestObserver"]

access_log = logging.getLogger("iris.access")
log = logging.getLogger("iris.serve")
_REQUEST_ID = re.compile(r"[A-Za-z0-9._-]{1,64}")


class JsonFormatter(logging.Formatter):
    """One JSON object per line; structured fields come in ``extra={"fields": {...}}``."""

    def format(self, record: logging.LogRecord) -> str:
        doc = {"ts": datetime.fromtimestamp(record.created, timezone.utc)
               .isoformat(timespec="milliseconds").replace("+00:00", "Z"),
               "level": record.levelname.lower(), "logger": record.name,
               "message": record.getMessage()}
        doc.update(getattr(record, "fields", {}))
        if record.exc_info:
            doc["exception"] = self.formatException(record.exc_info)
        return json.dumps(doc, default=str)


def log_config(level: str = "info") -> dict:
    """A ``logging.config.dictConfig`` (uvicorn's ``log_config``): every logger as JSON lines on
    stderr; uvicorn's own access log is off (``RequestObserver`` writes a richer one)."""
    level = level.upper()
    return {
        "version": 1, "disable_existing_loggers": False,
        "formatters": {"json": {"()": f"{__name__}.JsonFormatter"}},
        "handlers": {"stderr": {"class": "logging.StreamHandler", "formatter": "json",
                                "stream": "ext://sys.stderr"}},
        "loggers": {name: {"handlers": ["stderr"], "level": level, "propagate": False}
                    for name in ("uvicorn", "uvicorn.error", "iris")}
        | {"uvicorn.access": {"handlers": [], "level": "WARNING", "propagate": False}},
    }


class RequestObserver:
    """ASGI middleware around the app (see the module docstring). ``max_body_bytes``: a body
    streamed past it is cut off with 413, a net under the routes' own limits (the routes check a
    body's declared Content-Length against their limit before reading it: ``routing``);
    ``retry_after()``: the ``Retry-After`` seconds of a request cut off by the shutdown."""

    def __init__(self, app, *, metrics: Metrics, max_body_bytes: int,
                 retry_after: Callable[[], int] = lambda: 1):
        self.app = app
        self.metrics = metrics
        self.max_body_bytes = int(max_body_bytes)
        self.retry_after = retry_after

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        t0 = time.perf_counter()
        headers = dict(scope.get("headers") or [])
        given = headers.get(b"x-request-id", b"").decode("latin-1")
        request_id = given if _REQUEST_ID.fullmatch(given) else uuid.uuid4().hex
        state = {"status": None, "in": 0, "out": 0}        # status None: no response started
        limit = self.max_body_bytes

        async def receive_limited():
            message = await receive()
            if message["type"] == "http.request":
                state["in"] += len(message.get("body", b""))
                if state["in"] > limit:
                    raise PayloadTooLarge(f"request body: more than {limit} bytes, at most "
                                          f"{limit} (iris-serve --max-upload-mb)")
            return message

        async def send_observed(message):
            if message["type"] == "http.response.start":
                state["status"] = message["status"]
                message = {**message, "headers": [*message.get("headers", []),
                                                  (b"x-request-id", request_id.encode())]}
            elif message["type"] == "http.response.body":
                state["out"] += len(message.get("body", b""))
            await send(message)

        try:
            length = headers.get(b"content-length")
            if length is not None and not length.isdigit():
                await error_response(400, "bad_request", "Content-Length: expected a byte "
                                     "count")(scope, receive, send_observed)
            else:
                await self.app(scope, receive_limited, send_observed)
        except asyncio.CancelledError:
            # uvicorn cancels what outlives --shutdown-timeout: say so rather than a bare 500,
            # and end the request there (a cancellation that was answered is no error to log).
            if state["status"] is not None:
                raise
            with contextlib.suppress(Exception):
                await error_response(503, "unavailable", "the server shut down before this "
                                     "request finished (iris-serve --shutdown-timeout); retry "
                                     "after the Retry-After seconds",
                                     {"Retry-After": str(self.retry_after())})(
                    scope, receive, send_observed)
            log.warning("request cut off by the shutdown", extra={"fields": {
                "request_id": request_id, "path": scope["path"]}})
        finally:
            status = state["status"] or 500                 # nothing sent: the server failed
            seconds = time.perf_counter() - t0
            route = scope.get("route")
            template = getattr(route, "path", None) or "<unmatched>"
            self.metrics.observe_request(scope["method"], template, status, seconds)
            client = scope.get("client")
            access_log.info("request", extra={"fields": {
                "request_id": request_id, "method": scope["method"], "path": scope["path"],
                "route": template, "status": status,
                "duration_ms": round(seconds * 1000.0, 2), "bytes_in": state["in"],
                "bytes_out": state["out"], "client": client[0] if client else None}})
