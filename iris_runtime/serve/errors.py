"""Every error of the service as one JSON shape, ``{"error": {"type", "message"}}``, and the one
table that maps what can go wrong to an HTTP status.

The runtime's typed errors (``iris_runtime.errors``) carry messages that already name the
argument; the service only chooses the status: an unreadable image is a 400, a value the runtime
refuses (a non-rigid pose, a bad size, too few views) a 422, a model file that broke after start-up
a 500. The service's own refusals are ``ApiError`` subclasses. Nothing sends a traceback to a
client: an unexpected exception is logged with its traceback and answered with a 500 that says
only that.
"""
from __future__ import annotations

import json
import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from ..errors import ImageError, InputError, IrisError, ModelFileError

__all__ = ["ApiError", "BadRequest", "Unauthorized", "NotFound", "PayloadTooLarge",
           "UnsupportedMediaType", "Unprocessable", "Unsupported", "Superseded", "Busy",
           "Unavailable", "RUNTIME_ERRORS",
           "error_response", "field_message", "install_handlers"]

log = logging.getLogger("iris.serve")


class ApiError(Exception):
    """A refusal of the service: ``status``, a short ``type`` and a message naming the field."""
    status = 400
    type = "bad_request"

    def __init__(self, message: str, headers: dict[str, str] | None = None):
        super().__init__(message)
        self.message = message
        self.headers = headers or {}


class BadRequest(ApiError):
    """The request cannot be parsed (not JSON, broken multipart, a missing part)."""


class Unauthorized(ApiError):
    status, type = 401, "unauthorized"

    def __init__(self, message: str):
        super().__init__(message, {"WWW-Authenticate": 'Bearer realm="iris"'})


class NotFound(ApiError):
    status, type = 404, "not_found"


class PayloadTooLarge(ApiError):
    """Over a request limit: bytes, photos, pixels of a photo, output pixels, orbit frames."""
    status, type = 413, "too_large"


class UnsupportedMediaType(ApiError):
    status, type = 415, "unsupported_media_type"


class Unprocessable(ApiError):
    """Well-formed, but a field's value is not one the service accepts."""
    status, type = 422, "invalid"


class Superseded(ApiError):
    """A render of a stream (``stream`` + ``seq``) that a newer request of the same stream made
    stale before a worker took it: nothing was rendered. ``X-Iris-Superseded-By`` names the newer
    ``seq``. Not an error of the client's: it asked for a newer view since."""
    status, type = 409, "superseded"

    def __init__(self, message: str, newer: int):
        super().__init__(message, {"X-Iris-Superseded-By": str(newer)})
        self.newer = newer


class Unsupported(ApiError):
    """This server cannot do it (e.g. its OpenCV has no video encoder): not the request's fault."""
    status, type = 501, "unsupported"


class _Overload(ApiError):
    """``retry_after``: whole seconds (``WorkerPool.retry_after``: the queue's measured wait)."""

    def __init__(self, message: str, retry_after: int):
        super().__init__(message, {"Retry-After": str(int(retry_after))})
        self.retry_after = int(retry_after)


class Busy(_Overload):
    """The worker pool and its queue are full: come back later (``Retry-After``)."""
    status, type = 429, "busy"


class Unavailable(_Overload):
    """Shutting down, or a job waited in the queue longer than the queue timeout."""
    status, type = 503, "unavailable"


#: The runtime's typed errors -> (status, type). First match wins (subclasses first).
RUNTIME_ERRORS: tuple[tuple[type[IrisError], int, str], ...] = (
    (ImageError, 400, "bad_image"),
    (InputError, 422, "invalid"),
    (ModelFileError, 500, "model_error"),      # the model broke after start-up: not the client's
    (IrisError, 422, "invalid"),
)

_STATUS_TYPES = {400: "bad_request", 401: "unauthorized", 404: "not_found",
                 405: "method_not_allowed", 409: "superseded", 413: "too_large",
                 415: "unsupported_media_type", 422: "invalid", 429: "busy", 501: "unsupported",
                 503: "unavailable"}


def error_response(status: int, type_: str, message: str,
                   headers: dict[str, str] | None = None) -> JSONResponse:
    """The one error body: ``{"error": {"type": type_, "message": message}}``."""
    return JSONResponse({"error": {"type": type_, "message": message}}, status_code=status,
                        headers=headers)


def _loc(loc) -> str:
    """A pydantic error location as a field path: ("world_from_cam", 1, 2) ->
    world_from_cam[1][2]."""
    out = ""
    for part in loc:
        if part in ("body", "query", "path") and not out:
            continue
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "body"


def _given(error: dict) -> str:
    """", got <value>" for an error about a value the client sent, so that the message states
    what was refused and not only the rule; nothing for a missing or an unknown field."""
    if error.get("type") in ("missing", "extra_forbidden", "too_short", "too_long") \
            or "input" not in error:                      # (a list's length is in the message)
        return ""
    value = error["input"]
    if value is None or isinstance(value, (bool, int, float, str)):
        text = json.dumps(value)
        return f", got {text if len(text) <= 40 else text[:40] + '...'}"
    kind = {list: "an array", dict: "an object"}.get(type(value), type(value).__name__)
    return f", got {kind}"


def field_message(errors) -> str:
    """pydantic's errors as one line naming each field and the value refused:
    ``height: Input should be greater than 0, got -4``."""
    parts = [f"{_loc(e.get('loc', ()))}: {e.get('msg', 'invalid')}{_given(e)}"
             for e in errors[:5]]
    more = f" (and {len(errors) - 5} more)" if len(errors) > 5 else ""
    return "; ".join(parts) + more


def install_handlers(app: FastAPI) -> None:
    """Route every exception to ``error_response`` (one place for the whole service)."""

    @app.exception_handler(ApiError)
    async def _api(request: Request, exc: ApiError):
        return error_response(exc.status, exc.type, exc.message, exc.headers)

    @app.exception_handler(IrisError)
    async def _runtime(request: Request, exc: IrisError):
        for cls, status, type_ in RUNTIME_ERRORS:
            if isinstance(exc, cls):
                if status >= 500:
                    log.error("model error on %s %s: %s", request.method, request.url.path, exc)
                    return error_response(status, type_, "the model failed on the server; the "
                                          "operator has been told (see the server log)")
                return error_response(status, type_, str(exc).splitlines()[0] if str(exc)
                                      else type(exc).__name__)
        raise exc                                            # unreachable: IrisError is last

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError):
        errors = exc.errors()
        if errors and errors[0].get("type") == "json_invalid":     # FastAPI's own JSON parse
            why = (errors[0].get("ctx") or {}).get("error", "JSON decode error")
            return error_response(400, "bad_request", f"body: not valid JSON ({why})")
        return error_response(422, "invalid", field_message(errors))

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        message = exc.detail if isinstance(exc.detail, str) else str(exc.detail)
        if exc.status_code == 404 and message == "Not Found":
            message = f"no such route: {request.method} {request.url.path}"
        elif exc.status_code == 405:
            message = f"method {request.method} is not allowed on {request.url.path}"
        return error_response(exc.status_code, _STATUS_TYPES.get(exc.status_code, "error"),
                              message, getattr(exc, "headers", None))

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception):
        log.exception("unexpected error on %s %s", request.method, request.url.path)
        return error_response(500, "internal", "internal server error (logged on the server)")
