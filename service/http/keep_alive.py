"""Keep-alive connections closed after a number of requests, so that clients reconnect and the API processes share
them again (nginx's `keepalive_requests` does the same, 1 000 by default).

Each API process listens on a socket of its own and the kernel places each new connection (service.cli.listeners),
but a camera's keep-alive connection stays with the process it first reached. After a restart, cameras that
reconnect at once all reach whichever process listens first: 40 connections made as soon as `posemetry serve`
accepted them all went to one of its two API processes, and would have stayed there for as long as the cameras
posted. Closing each connection after `max_requests` responses (`Connection: close`, which every HTTP/1.1 client
honours by reconnecting for its next request) lets the kernel place it again, among every process then listening.
"""

from __future__ import annotations

from typing import Any

from starlette.types import ASGIApp, Message, Receive, Scope, Send

# Connections remembered per process. Least recently used first, so the ones that closed on their own age out.
TRACKED_CONNECTIONS = 10_000
_CLOSE = (b"connection", b"close")


class RecycleConnections:
    """Pure ASGI middleware: `Connection: close` on the `max_requests`-th response of a connection (0: never).

    A connection is known by its client address (host, port), unique among a process's open connections; one that
    closed and whose port a new connection reuses is merely recycled early.
    """

    def __init__(self, app: ASGIApp, max_requests: int) -> None:
        self.app = app
        self.max_requests = max_requests
        self._served: dict[Any, int] = {}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        client = scope.get("client")
        if scope["type"] != "http" or not self.max_requests or client is None:
            await self.app(scope, receive, send)
            return
        key = tuple(client)
        served = self._served.pop(key, 0) + 1
        if served < self.max_requests:
            self._served[key] = served  # re-inserted last: the dict stays in order of use
            if len(self._served) > TRACKED_CONNECTIONS:
                del self._served[next(iter(self._served))]
            await self.app(scope, receive, send)
            return

        async def send_closing(message: Message) -> None:
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", ()), _CLOSE]}
            await send(message)

        await self.app(scope, receive, send_closing)
