"""The API's request telemetry: a request id, latency metrics and one log line per request, as pure ASGI.

It sits outermost among the app's middleware, so what the body guard refuses is measured and logged too. Pure
ASGI rather than Starlette's BaseHTTPMiddleware: the ingest path must stay cheap (≥ 300 frames/s on 2 cores),
and BaseHTTPMiddleware runs the app in a separate task and re-streams the response through memory streams,
which costs more than everything this middleware does.

Per request: take the client's `X-Request-ID` if well-formed or make one; make it current (logs, problem bodies
and queued jobs pick it up) and visible to handlers as `request.state.request_id`; add it to the response's
headers; time the request; then observe the latency histogram under the route *template* (the matched route's
path, `/v1/cameras/{camera_id}/keypoints`, never the raw path, so the series count stays bounded) and write the
access line. Probe and scrape routes log at DEBUG, so a 10 s health check does not drown the log.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable, Iterable
from typing import Any

from starlette.routing import compile_path
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.observability.metrics import HTTP_REQUEST_DURATION, HTTP_REQUESTS_IN_PROGRESS
from service.observability.request_id import HEADER_KEY, accepted_request_id, new_request_id, request_id_context

log = logging.getLogger("posemetry.access")

METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})
UNMATCHED_ROUTE = "unmatched"
QUIET_ROUTES = frozenset({"/healthz", "/readyz", "/metrics"})


class RequestTelemetry:
    """Pure ASGI middleware. `route_templates` gives the app's path templates, read once when first needed, to
    name the route of a request refused before routing (the router names the others)."""

    def __init__(self, app: ASGIApp, route_templates: Callable[[], Iterable[str]]) -> None:
        self.app = app
        self.route_templates = route_templates
        self._templates: list[tuple[re.Pattern[str], str]] | None = None
        self._histograms: dict[tuple[str, str, str], Any] = {}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        request_id = None
        for key, value in scope["headers"]:
            if key == HEADER_KEY:
                request_id = accepted_request_id(value)
                break
        if request_id is None:
            request_id = new_request_id()
        scope.setdefault("state", {})["request_id"] = request_id
        id_header = (HEADER_KEY, request_id.encode("ascii"))
        status = 500  # what the client gets if the app raises before answering (the error middleware's 500)

        async def send_with_id(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
                message["headers"] = [*message.get("headers", ()), id_header]
            await send(message)

        HTTP_REQUESTS_IN_PROGRESS.inc()
        try:
            with request_id_context(request_id):
                await self.app(scope, receive, send_with_id)
        finally:
            HTTP_REQUESTS_IN_PROGRESS.dec()
            duration_s = time.perf_counter() - started
            method = scope["method"] if scope["method"] in METHODS else "OTHER"
            route = self._route(scope)
            self._histogram(method, route, status).observe(duration_s)
            level = logging.DEBUG if route in QUIET_ROUTES else logging.INFO
            if log.isEnabledFor(level):
                self._log(level, scope, method, route, status, duration_s, request_id)

    def _histogram(self, method: str, route: str, status: int) -> Any:
        """The histogram child for these labels, cached: `labels()` costs more than the observation itself."""
        key = (method, route, f"{status // 100}xx")
        child = self._histograms.get(key)
        if child is None:
            child = self._histograms[key] = HTTP_REQUEST_DURATION.labels(*key)
        return child

    def _route(self, scope: Scope) -> str:
        """The matched route's template; requests refused before routing (body guard) are matched here."""
        # path_format: the template as documented, without Starlette convertors ("{key_id}", not "{key_id:key_id}").
        template = getattr(scope.get("route"), "path_format", None)
        if template:
            return str(template)
        if self._templates is None:
            self._templates = [(compile_path(path)[0], path) for path in self.route_templates()]
        return next((path for pattern, path in self._templates if pattern.match(scope["path"])), UNMATCHED_ROUTE)

    @staticmethod
    def _log(
        level: int, scope: Scope, method: str, route: str, status: int, duration_s: float, request_id: str
    ) -> None:
        fields: dict[str, Any] = {
            "method": method,
            "path": scope["path"],
            "route": route,
            "status": status,
            "duration_ms": round(duration_s * 1000, 2),
            "request_id": request_id,
        }
        camera_id = scope.get("path_params", {}).get("camera_id")
        if camera_id is not None:
            fields["camera_id"] = camera_id
        log.log(level, "%s %s %d %.1f ms", method, scope["path"], status, duration_s * 1000, extra=fields)
