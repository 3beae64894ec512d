"""A lean asyncio HTTP/1.1 client and server for the load benchmark: keep-alive connections, one request at a time
each, requests written as one pre-assembled buffer and responses parsed by httptools (uvicorn's C parser).

Why not a general client: the benchmark shares two cores with the service it measures, so every microsecond the
client spends is taken from the server. A general async client (httpx) costs several hundred µs of CPU per
request; this one costs tens, so the load generator stays a small, measured share of the machine. It speaks just
enough HTTP for a loopback benchmark: no TLS, no redirects, no proxies, no pipelining.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass

import httptools


@dataclass(frozen=True)
class Response:
    status: int
    body: bytes


class HttpError(Exception):
    """The connection failed or closed before a whole response arrived."""


class _ClientProtocol(asyncio.Protocol):
    def __init__(self) -> None:
        self.transport: asyncio.Transport | None = None
        self.parser = httptools.HttpResponseParser(self)
        self.body: list[bytes] = []
        self.waiter: asyncio.Future[Response] | None = None
        self.closed = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def data_received(self, data: bytes) -> None:
        try:
            self.parser.feed_data(data)
        except httptools.HttpParserError as exc:
            self._fail(HttpError(f"bad response: {exc}"))

    def connection_lost(self, exc: Exception | None) -> None:
        self.closed = True
        self._fail(HttpError(f"connection closed: {exc or 'by the server'}"))

    # httptools callbacks
    def on_body(self, body: bytes) -> None:
        self.body.append(body)

    def on_message_complete(self) -> None:
        waiter, self.waiter = self.waiter, None
        body, self.body = b"".join(self.body), []
        if waiter is not None and not waiter.done():
            waiter.set_result(Response(self.parser.get_status_code(), body))
        if not self.parser.should_keep_alive() and self.transport is not None:
            self.transport.close()

    def _fail(self, exc: Exception) -> None:
        waiter, self.waiter = self.waiter, None
        if waiter is not None and not waiter.done():
            waiter.set_exception(exc)


class Connection:
    """One keep-alive connection to `host:port`, reopened after a failure; `request` is not concurrent-safe."""

    def __init__(self, host: str, port: int, *, token: str | None = None, timeout_s: float = 30.0) -> None:
        self.host = host
        self.port = port
        self.timeout_s = timeout_s
        self._common = f"host: {host}:{port}\r\n".encode()
        if token is not None:
            self._common += f"authorization: Bearer {token}\r\n".encode()
        self._protocol: _ClientProtocol | None = None

    async def _open(self) -> _ClientProtocol:
        if self._protocol is None or self._protocol.closed:
            loop = asyncio.get_running_loop()
            _transport, protocol = await loop.create_connection(_ClientProtocol, self.host, self.port)
            self._protocol = protocol
        return self._protocol

    async def request(
        self, method: str, path: str, body: bytes | None = None, content_type: bytes = b"application/json"
    ) -> Response:
        """Send one request and wait for its whole response; raises HttpError or TimeoutError."""
        protocol = await self._open()
        head = f"{method} {path} HTTP/1.1\r\n".encode() + self._common
        if body is None:
            message = head + b"\r\n"
        else:
            message = b"%scontent-type: %s\r\ncontent-length: %d\r\n\r\n%s" % (head, content_type, len(body), body)
        waiter: asyncio.Future[Response] = asyncio.get_running_loop().create_future()
        protocol.waiter = waiter
        assert protocol.transport is not None
        protocol.transport.write(message)
        try:
            return await asyncio.wait_for(waiter, self.timeout_s)
        except BaseException:
            self.close()  # a half-read response would confuse the next request on this connection
            raise

    def close(self) -> None:
        if self._protocol is not None and self._protocol.transport is not None:
            self._protocol.transport.close()
        self._protocol = None


# --------------------------------------------------------------------------------------------------- server

# (method, path, headers with lower-case names, body) -> (status, body)
Handler = Callable[[str, str, dict[str, str], bytes], tuple[int, bytes]]
_REASONS = {200: b"OK", 204: b"No Content", 404: b"Not Found", 500: b"Internal Server Error"}


class _ServerProtocol(asyncio.Protocol):
    def __init__(self, handler: Handler) -> None:
        self.handler = handler
        self.parser = httptools.HttpRequestParser(self)
        self.transport: asyncio.Transport | None = None
        self.url = b""
        self.headers: dict[str, str] = {}
        self.body: list[bytes] = []

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def data_received(self, data: bytes) -> None:
        try:
            self.parser.feed_data(data)
        except httptools.HttpParserError:
            if self.transport is not None:
                self.transport.close()

    def on_url(self, url: bytes) -> None:
        self.url += url

    def on_header(self, name: bytes, value: bytes) -> None:
        self.headers[name.decode("latin-1").lower()] = value.decode("latin-1")

    def on_body(self, body: bytes) -> None:
        self.body.append(body)

    def on_message_complete(self) -> None:
        method = self.parser.get_method().decode()
        status, body = self.handler(method, self.url.decode("latin-1"), self.headers, b"".join(self.body))
        self.url, self.headers, self.body = b"", {}, []
        assert self.transport is not None
        reason = _REASONS.get(status, b"Unknown")
        self.transport.write(b"HTTP/1.1 %d %s\r\ncontent-length: %d\r\n\r\n%s" % (status, reason, len(body), body))
        if not self.parser.should_keep_alive():
            self.transport.close()


async def serve(handler: Handler, host: str = "127.0.0.1", port: int = 0) -> asyncio.Server:
    """A tiny HTTP/1.1 server on this event loop (the benchmark's webhook receiver); `handler` answers each
    request synchronously."""
    loop = asyncio.get_running_loop()
    return await loop.create_server(lambda: _ServerProtocol(handler), host, port)
