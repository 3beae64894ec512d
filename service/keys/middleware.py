"""Requests with a body are authenticated before anything reads the body.

The route dependency (`require_key`) runs only after the body has been read: FastAPI parses JSON bodies before
it solves dependencies, and BodyGuard buffers every body (images up to `max_image_bytes`) before the app sees
it. Without this gate a caller without a key could make the service read and hold 20 MB per request, and would
learn from a 413, 415 or 400 what it may not know. So POST, PUT and PATCH to every non-public path are checked
here, before BodyGuard; the Principal found is left in the request state for `require_key` (which still runs,
and still enforces camera scope). Other methods carry no body and are left to the dependency alone.

Camera scope needs the route's path parameters, which exist only after routing, so for a valid key the body
checks (413, 415, malformed JSON) may answer before a 403 for a camera outside its scope; nothing is stored.
"""

from __future__ import annotations

from starlette.types import ASGIApp, Receive, Scope, Send

from service.http.problems import ProblemError, problem_response

from .authenticator import Authenticator

BODY_METHODS = frozenset({"POST", "PUT", "PATCH"})
# Key in the ASGI scope's "state" (request.state) under which the gate leaves the Principal.
PRINCIPAL_STATE = "posemetry_principal"


class AuthenticateBeforeBody:
    """Pure ASGI middleware: 401 for a body-carrying request without a valid key, before the body is read."""

    def __init__(self, app: ASGIApp, authenticator: Authenticator, public_paths: frozenset[str]) -> None:
        self.app = app
        self.authenticator = authenticator
        self.public_paths = public_paths

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] not in BODY_METHODS or scope["path"] in self.public_paths:
            await self.app(scope, receive, send)
            return
        authorization = next(
            (value.decode("latin-1") for name, value in scope["headers"] if name.lower() == b"authorization"), None
        )
        try:
            principal = await self.authenticator.authenticate(authorization)
        except ProblemError as exc:
            response = problem_response(exc.status, exc.kind, exc.detail, scope["path"], headers=exc.headers)
            await response(scope, receive, send)
            return
        scope.setdefault("state", {})[PRINCIPAL_STATE] = principal
        await self.app(scope, receive, send)
