"""The route class of the service: what is checked before FastAPI reads a request's body.

FastAPI parses a route's declared body (a JSON model, multipart files and fields) before it
solves the route's dependencies, so the checks that need no body would otherwise come after it:
an unauthenticated client could make the server parse a 64 MB upload before its 401. So every
route of the service is a ``ServiceRoute`` whose handler first runs, in this order:

1. the bearer token (``ScenesRoute``, the routes under ``/scenes``): 401;
2. the scene named by the path (``{scene_id}``): 404;
3. the body, as the route declares it (FastAPI's own validation then runs on what is read here,
   and FastAPI writes the OpenAPI schema from the same declarations):

   - a JSON body (a Pydantic model): Content-Type ``application/json`` (415), at most
     ``Service.max_json_bytes`` (413, from Content-Length before reading, else while reading),
     valid JSON (400);
   - a multipart body (``File`` / ``Form`` parameters): Content-Type ``multipart/form-data``
     (415), at most ``--max-upload-mb`` (413), parsed with limits on files (413: at most
     ``--max-photos`` for a list of photos, one for a single photo), text fields and their size
     (413), complete (400: a body cut short before its closing boundary is not a multipart
     body), no unknown field and files where files are expected (422).

The body read here is handed on to FastAPI (a ``Request`` over what was read: nothing is read
twice).
"""
from __future__ import annotations

import typing

from fastapi import params
from fastapi.routing import APIRoute
from python_multipart.multipart import parse_options_header
from starlette.datastructures import UploadFile
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import Request

from .errors import BadRequest, PayloadTooLarge, Unprocessable, UnsupportedMediaType
from .service import MAX_TEXT_BYTES, MAX_TEXT_FIELDS, Service

__all__ = ["ServiceRoute", "ScenesRoute"]


def _media_type(request: Request) -> str:
    return request.headers.get("content-type", "").split(";")[0].strip().lower()


def _declared_length(request: Request) -> int | None:
    length = request.headers.get("content-length")
    return int(length) if length is not None and length.isdigit() else None


class _Replay:
    """An ASGI ``receive`` that gives ``body`` as the request's body, then defers to ``receive``
    (which then reports a disconnect)."""

    def __init__(self, body: bytes, receive):
        self.body, self.receive, self.sent = body, receive, False

    async def __call__(self):
        if not self.sent:
            self.sent = True
            return {"type": "http.request", "body": self.body, "more_body": False}
        return await self.receive()


class _CloseWatch:
    """An ASGI ``receive`` that notes whether the body held the multipart close delimiter
    (``--boundary--``): python-multipart ends quietly on a body cut short, with its last part
    missing."""

    def __init__(self, receive, boundary: bytes):
        self.receive = receive
        self.mark = b"--" + boundary + b"--"
        self.tail = b""
        self.closed = False

    async def __call__(self):
        message = await self.receive()
        if message["type"] == "http.request" and not self.closed:
            data = self.tail + message.get("body", b"")
            self.closed = self.mark in data
            self.tail = data[-(len(self.mark) - 1):]
        return message


class _Multipart(typing.NamedTuple):
    files: dict[str, bool]      # file field -> takes several files
    texts: tuple[str, ...]      # text fields

    def expected(self) -> str:
        names = [f"'{f}' files" if many else f"one '{f}' file" for f, many in self.files.items()]
        return " and ".join(names + [f"'{t}'" for t in self.texts])


def _body_kind(route: APIRoute):
    """``"json"``, a ``_Multipart`` or None, from the route's declared body parameters."""
    fields = route.dependant.body_params
    if not fields:
        return None
    if not any(isinstance(f.field_info, params.Form) for f in fields):
        return "json"
    files, texts = {}, []
    for f in fields:
        if isinstance(f.field_info, params.File):
            files[f.alias] = typing.get_origin(f.field_info.annotation) is list or \
                list in typing.get_args(f.field_info.annotation)
        else:
            texts.append(f.alias)
    return _Multipart(files, tuple(texts))


class ServiceRoute(APIRoute):
    """A route whose checks that need no body run before its body is read (module docstring)."""
    needs_token = False

    def get_route_handler(self):
        handler = super().get_route_handler()
        kind = _body_kind(self)
        needs_token = self.needs_token

        async def checked(request: Request):
            service: Service = request.app.state.service
            if needs_token:
                service.check_token(request)
            scene_id = request.path_params.get("scene_id")
            if scene_id is not None:
                service.store.get(scene_id)                     # 404 before the body
            if kind == "json":
                request = await _read_json(request, service)
            elif kind is not None:
                request = await _read_multipart(request, service, kind)
            return await handler(request)

        return checked


class ScenesRoute(ServiceRoute):
    """A route under ``/scenes``: the bearer token first, when the server has one."""
    needs_token = True


async def _read_json(request: Request, service: Service) -> Request:
    ctype = _media_type(request)
    if ctype != "application/json":
        raise UnsupportedMediaType(f"body: expected Content-Type application/json, got "
                                   f"{ctype or 'none'}")
    limit = service.max_json_bytes
    declared = _declared_length(request)
    if declared is not None and declared > limit:
        raise PayloadTooLarge(f"body: {declared} bytes of JSON, at most {limit}")
    body = bytearray()
    async for chunk in request.stream():
        body += chunk
        if len(body) > limit:
            raise PayloadTooLarge(f"body: more than {limit} bytes of JSON, at most {limit}")
    replay = Request(request.scope, _Replay(bytes(body), request.receive))
    try:
        await replay.json()                                   # parsed once, kept for FastAPI
    except (ValueError, UnicodeDecodeError) as exc:
        raise BadRequest(f"body: not valid JSON ({exc})") from None
    return replay


async def _read_multipart(request: Request, service: Service, kind: _Multipart) -> Request:
    ctype = _media_type(request)
    field = next(iter(kind.files))
    if ctype != "multipart/form-data":
        raise UnsupportedMediaType(f"body: expected multipart/form-data with photos in "
                                   f"'{field}', got {ctype or 'none'}")
    limit = service.config.max_upload_bytes
    declared = _declared_length(request)
    if declared is not None and declared > limit:
        raise PayloadTooLarge(f"request body: {declared} bytes, at most {limit} (iris-serve "
                              f"--max-upload-mb)")
    _, options = parse_options_header(request.headers.get("content-type", ""))
    boundary = options.get(b"boundary", b"")
    boundary = boundary.encode("latin-1") if isinstance(boundary, str) else boundary
    watch = _CloseWatch(request.receive, boundary)
    request = Request(request.scope, watch)
    many = kind.files[field]
    max_files = service.max_photos if many else 1
    try:
        form = await request.form(max_files=max_files, max_fields=MAX_TEXT_FIELDS,
                                  max_part_size=MAX_TEXT_BYTES)
    except StarletteHTTPException as exc:
        raise _form_error(str(exc.detail), field, max_files, many, service) from None
    try:
        if boundary and not watch.closed:
            raise BadRequest(f"body: the multipart body ends before its closing boundary "
                             f"'--{boundary.decode('latin-1')}--' (cut short?)")
        _check_fields(form, kind)
    except BaseException:
        await form.close()
        raise
    return request


def _form_error(detail: str, field: str, max_files: int, many: bool, service: Service):
    """Starlette's multipart refusal as the service's error."""
    if detail.startswith("Too many files"):
        why = service.max_photos_source if many else "this route takes one photo"
        return PayloadTooLarge(f"{field}: more than {max_files} file(s) in one request, at most "
                               f"{max_files} ({why})")
    if detail.startswith("Too many fields"):
        return PayloadTooLarge(f"body: more than {MAX_TEXT_FIELDS} text fields, at most "
                               f"{MAX_TEXT_FIELDS}")
    if detail.startswith(("Part exceeded", "Field exceeded")):
        return PayloadTooLarge(f"body: a text field of more than {MAX_TEXT_BYTES} bytes, at "
                               f"most {MAX_TEXT_BYTES}")
    return BadRequest(f"body: {detail}")


def _check_fields(form, kind: _Multipart) -> None:
    """422 for an unknown field, a text field where files are expected, or the reverse."""
    known = {*kind.files, *kind.texts}
    unknown = [name for name in form.keys() if name not in known]
    if unknown:
        raise Unprocessable(f"{unknown[0]}: unknown form field (expected {kind.expected()})")
    for name in kind.files:
        if any(not isinstance(p, UploadFile) for p in form.getlist(name)):
            raise Unprocessable(f"{name}: expected files (parts with a filename), got a text "
                                f"field")
    for name in kind.texts:
        values = form.getlist(name)
        if any(isinstance(v, UploadFile) for v in values):
            raise Unprocessable(f"{name}: expected a text field, got a file")
        if len(values) > 1:
            raise Unprocessable(f"{name}: given {len(values)} times, expected once")
