"""RFC 9457 problem details: every error the API returns is `application/problem+json` with a useful `detail`.

Clients are camera systems and scripts; they need a machine-readable status, a stable `type` to branch on, a
sentence a person can act on, and, for validation errors, the location of each bad field. Bad input must never
surface as a 500, so validation errors, malformed JSON, unknown routes and oversize or non-JSON bodies are all
turned into 4xx problems here, and the body guard rejects what should not be parsed at all before parsing.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from sqlalchemy.exc import SQLAlchemyError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.responses import JSONResponse
from starlette.routing import BaseRoute, Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.observability.redact import APP_SECRETS
from service.observability.request_id import HEADER, current_request_id
from service.store.db import is_database_unavailable

PROBLEM_MEDIA_TYPE = "application/problem+json"
TYPE_BASE = "https://posemetry.dev/problems/"
# Retry-After on 503s: the queue or the database is down; a client retrying sooner only adds load. A retry of a
# frame with its frame_id is safe whatever happened to the first attempt.
RETRY_AFTER_S = 5
UNAVAILABLE_HEADERS = {"Retry-After": str(RETRY_AFTER_S)}
log = logging.getLogger(__name__)


PROBLEM_SCHEMA = {
    "type": "object",
    "properties": {
        "type": {"type": "string", "format": "uri"},
        "title": {"type": "string"},
        "status": {"type": "integer"},
        "detail": {"type": "string"},
        "instance": {"type": "string"},
        "request_id": {"type": "string", "description": "The request's id, as in the X-Request-ID header."},
        "errors": {"type": "array", "items": {"type": "object"}},
    },
    "required": ["type", "title", "status", "detail"],
}


def problem_response_doc(description: str) -> dict[str, Any]:
    """An OpenAPI response entry for one status answered with a problem document."""
    return {"description": description, "content": {PROBLEM_MEDIA_TYPE: {"schema": PROBLEM_SCHEMA}}}


class ProblemError(Exception):
    """Raise from a handler to answer with a problem document (`kind` becomes the `type` URI's last segment).

    `headers` go on the response (401 needs `WWW-Authenticate`); `extensions` become extra body members.
    """

    def __init__(
        self, status: int, kind: str, detail: str, *, headers: dict[str, str] | None = None, **extensions: Any
    ) -> None:
        super().__init__(detail)
        self.status = status
        self.kind = kind
        self.detail = detail
        self.headers = headers
        self.extensions = extensions


def problem_body(status: int, kind: str, detail: str, instance: str | None = None, **extensions: Any) -> dict[str, Any]:
    """The problem document; it carries the request id (the current one unless given), so a client reporting an
    error hands over the key to its log lines."""
    body: dict[str, Any] = {
        "type": TYPE_BASE + kind,
        "title": HTTPStatus(status).phrase,
        "status": status,
        "detail": APP_SECRETS(detail),  # a detail may repeat the path, where a careless client may have put a key
    }
    if instance is not None:
        body["instance"] = APP_SECRETS(instance)
    request_id = current_request_id()
    if request_id is not None:
        body["request_id"] = request_id
    body.update(jsonable_encoder(extensions))
    return body


def problem_response(
    status: int,
    kind: str,
    detail: str,
    instance: str | None = None,
    headers: dict[str, str] | None = None,
    **extensions: Any,
) -> JSONResponse:
    return JSONResponse(
        problem_body(status, kind, detail, instance, **extensions),
        status_code=status,
        media_type=PROBLEM_MEDIA_TYPE,
        headers=headers,
    )


def _location(loc: Sequence[int | str]) -> str:
    """body.people[3].keypoints[16][2]: a path a person can find in their JSON."""
    text = ""
    for part in loc:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text


def field_errors(errors: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Pydantic errors reduced to what a client can use: where, what, and the error's type code."""
    return [
        {
            "loc": list(e.get("loc", ())),
            "field": _location(e.get("loc", ())),
            "msg": e.get("msg", ""),
            "type": e["type"],
        }
        for e in errors
    ]


def validation_problem(errors: Sequence[dict[str, Any]], instance: str) -> JSONResponse:
    """422 with every field error, or 400 when the body is not JSON at all."""
    malformed = [e for e in errors if e.get("type") == "json_invalid"]
    if malformed:
        ctx = malformed[0].get("ctx") or {}
        where = ", ".join(f"{k} {v}" for k, v in ctx.items() if k != "error")
        reason = ctx.get("error", "invalid JSON")
        detail = f"The request body is not valid JSON: {reason}" + (f" ({where})" if where else "")
        return problem_response(400, "malformed-json", detail, instance)
    fields = field_errors(errors)
    first = fields[0]
    more = f" (and {len(fields) - 1} more)" if len(fields) > 1 else ""
    detail = f"Invalid request: {first['field'] or 'body'}: {first['msg']}{more}"
    return problem_response(422, "validation-error", detail, instance, errors=fields)


def install_handlers(app: FastAPI) -> None:
    """Route every error through problem documents."""

    @app.exception_handler(ProblemError)
    async def _problem(request: Request, exc: ProblemError) -> JSONResponse:
        return problem_response(
            exc.status, exc.kind, exc.detail, request.url.path, headers=exc.headers, **exc.extensions
        )

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        return validation_problem(exc.errors(), request.url.path)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        kinds = {404: "not-found", 405: "method-not-allowed"}
        detail = exc.detail if isinstance(exc.detail, str) else json.dumps(exc.detail)
        if exc.status_code == 404 and detail == "Not Found":
            detail = f"No such resource: {request.url.path}"
        headers = exc.headers
        if exc.status_code == 405:
            allowed = allowed_methods(request.app.router.routes, request.scope)
            detail = f"{request.method} is not allowed on {request.url.path}; allowed: {', '.join(allowed)}"
            headers = {**(headers or {}), "Allow": ", ".join(allowed)}
        return problem_response(
            exc.status_code, kinds.get(exc.status_code, "http-error"), detail, request.url.path, headers=headers
        )

    @app.exception_handler(SQLAlchemyError)
    async def _database(request: Request, exc: SQLAlchemyError) -> JSONResponse:
        # The database down, restarting, locked past the busy timeout or read-only: the request can succeed later,
        # so 503, never 500. Anything else from the database is a bug, and goes to the handler below.
        if not is_database_unavailable(exc):
            raise exc
        log.warning("database unavailable on %s %s: %s", request.method, request.url.path, exc)
        cause = getattr(exc, "orig", None) or exc  # the driver's error; the pool's own timeout has none
        detail = f"The database is unavailable ({type(cause).__name__}); retry the request later."
        return problem_response(503, "database-unavailable", detail, request.url.path, headers=UNAVAILABLE_HEADERS)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        # Starlette answers this one outside the app's middleware, where the request id is no longer current
        # and no longer added to the headers: both are taken from the request's state instead.
        request_id = getattr(request.state, "request_id", None)
        log.exception("unhandled error on %s %s", request.method, request.url.path, extra={"request_id": request_id})
        extensions = {} if request_id is None else {"request_id": request_id}
        headers = None if request_id is None else {HEADER: request_id}
        return problem_response(
            500, "internal-error", "An unexpected error occurred; it has been logged.", headers=headers, **extensions
        )


def routes_to_endpoint(routes: Sequence[BaseRoute], scope: Scope) -> bool:
    """Whether some route takes this method on this path (so the request is not a 404 or 405)."""
    return any(route.matches(scope)[0] == Match.FULL for route in routes)


HTTP_METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")


def allowed_methods(routes: Sequence[BaseRoute], scope: Scope) -> list[str]:
    """Every method some route takes on this path. Starlette's 405 names only the first matching route's methods,
    but a path such as /v1/cameras/{camera_id} is served by three routes (GET, PUT, DELETE), and FastAPI nests
    included routers, so each method is tried against the whole routing table."""
    return [method for method in HTTP_METHODS if routes_to_endpoint(routes, {**scope, "method": method})]


def _is_json(content_type: str) -> bool:
    media = content_type.split(";", 1)[0].strip().lower()
    return media == "application/json" or (media.startswith("application/") and media.endswith("+json"))


@dataclass(frozen=True)
class UploadRoute:
    """POST paths that take something other than JSON (image uploads), with their own size limit."""

    path: re.Pattern[str]
    max_body_bytes: int
    media_types: frozenset[str]
    setting: str
    """The setting that sets the limit, named in the 413 message."""


def _media(content_type: str) -> str:
    return content_type.split(";", 1)[0].strip().lower()


class HeaderGuard:
    """Pure ASGI middleware: refuses a request whose header block exceeds `max_header_bytes` with 431.

    uvicorn's httptools parser (the one `uvicorn[standard]` installs) takes header blocks of any size, so without
    this a client could make every request carry megabytes of headers through authentication and logging.
    """

    def __init__(self, app: ASGIApp, max_header_bytes: int) -> None:
        self.app = app
        self.max_header_bytes = max_header_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            size = sum(len(name) + len(value) + 4 for name, value in scope["headers"])  # "name: value\r\n"
            if size > self.max_header_bytes:
                detail = (
                    f"The request's headers take {size} bytes, over the limit of {self.max_header_bytes} "
                    "(setting max_header_bytes)."
                )
                response = problem_response(
                    431, "headers-too-large", detail, scope.get("path"), headers={"Connection": "close"}
                )
                await response(scope, receive, send)
                return
        await self.app(scope, receive, send)


class BodyGuard:
    """Pure ASGI middleware: refuses oversize and wrongly typed bodies before anything parses them.

    Content-Length is checked first (cheap rejection of honest clients); the body is then read here, counting
    bytes as they stream, so a chunked or lying client is cut off at the limit too. The body is buffered (it is
    at most the limit) and replayed to the application. Bodies must be JSON, except on `uploads` routes, which
    accept their own media types up to their own limit.

    Requests that no route takes (given the app's `routes`) pass untouched, so an unknown path is a 404 and a method
    the path does not have a 405, whatever body they carry; their body is never read.
    """

    def __init__(
        self,
        app: ASGIApp,
        max_body_bytes: int,
        uploads: tuple[UploadRoute, ...] = (),
        routes: Sequence[BaseRoute] | None = None,
    ) -> None:
        self.app = app
        self.max_body_bytes = max_body_bytes
        self.uploads = uploads
        self.routes = routes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (
            scope["type"] != "http"
            or scope["method"] not in ("POST", "PUT", "PATCH")
            or (self.routes is not None and not routes_to_endpoint(self.routes, scope))
        ):
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        path = scope.get("path", "")
        upload = next((u for u in self.uploads if scope["method"] == "POST" and u.path.fullmatch(path)), None)
        limit = self.max_body_bytes if upload is None else upload.max_body_bytes
        setting = "max_body_bytes" if upload is None else upload.setting
        declared = headers.get("content-length")
        if declared is not None:
            try:
                declared_bytes = int(declared)
            except ValueError:
                await self._reply(scope, receive, send, 400, "bad-request", "Content-Length is not a number.")
                return
            if declared_bytes > limit:
                await self._too_large(scope, receive, send, limit, setting)
                return
        chunks: list[bytes] = []
        size = 0
        more = True
        while more:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > limit:
                await self._too_large(scope, receive, send, limit, setting)
                return
            chunks.append(chunk)
            more = message.get("more_body", False)
        body = b"".join(chunks)
        content_type = headers.get("content-type", "")
        given = content_type or "none"
        if upload is not None and _media(content_type) not in upload.media_types:
            accepted = ", ".join(sorted(upload.media_types))
            detail = f"{path} accepts {accepted}; got Content-Type {given}."
            await self._reply(scope, receive, send, 415, "unsupported-media-type", detail)
            return
        if upload is None and body and not _is_json(content_type):
            detail = f"Request bodies must be JSON (Content-Type: application/json); got {given} for {path}."
            await self._reply(scope, receive, send, 415, "unsupported-media-type", detail)
            return
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    async def _too_large(self, scope: Scope, receive: Receive, send: Send, limit: int, setting: str) -> None:
        detail = f"The request body exceeds the limit of {limit} bytes (setting {setting})."
        await self._reply(scope, receive, send, 413, "body-too-large", detail, headers={"Connection": "close"})

    @staticmethod
    async def _reply(
        scope: Scope,
        receive: Receive,
        send: Send,
        status: int,
        kind: str,
        detail: str,
        headers: dict[str, str] | None = None,
    ) -> None:
        response = problem_response(status, kind, detail, scope.get("path"), headers=headers)
        await response(scope, receive, send)
