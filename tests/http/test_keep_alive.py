"""Keep-alive connections recycled after `max_requests` responses (service.http.keep_alive), through a real uvicorn
server and a real HTTP/1.1 client."""

from __future__ import annotations

import asyncio
import socket
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import uvicorn
from starlette.types import Receive, Scope, Send

from service.http.keep_alive import RecycleConnections
from tests.support.serving import free_port


async def _hello(scope: Scope, receive: Receive, send: Send) -> None:
    headers = [(b"content-type", b"text/plain"), (b"content-length", b"5")]
    await send({"type": "http.response.start", "status": 200, "headers": headers})
    await send({"type": "http.response.body", "body": b"hello"})


@contextmanager
def _served(max_requests: int) -> Iterator[int]:
    port = free_port()
    config = uvicorn.Config(RecycleConnections(_hello, max_requests), port=port, log_config=None, lifespan="off")
    server = uvicorn.Server(config)
    thread = threading.Thread(target=lambda: asyncio.run(server.serve()), daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 10
        while not server.started:
            assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
            time.sleep(0.02)
        yield port
    finally:
        server.should_exit = True
        thread.join(10)


def _response(sock: socket.socket) -> bytes:
    """One whole response (its body is 5 bytes) from `sock`."""
    data = b""
    while not (b"\r\n\r\n" in data and data.endswith(b"hello")):
        chunk = sock.recv(4096)
        assert chunk, "the server closed the connection before answering"
        data += chunk
    return data


def _requests(port: int, count: int) -> list[tuple[int, bool]]:
    """(connection number, whether the response said `Connection: close`) of each of `count` requests sent one at a
    time by a keep-alive client that reconnects when told to, checking the server did close."""
    seen = []
    connection = 0
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    try:
        for _ in range(count):
            sock.sendall(b"GET / HTTP/1.1\r\nHost: test\r\n\r\n")
            closes = b"\r\nconnection: close\r\n" in _response(sock).lower()
            seen.append((connection, closes))
            if closes:
                assert sock.recv(1) == b"", "the server kept the connection open"
                sock.close()
                sock = socket.create_connection(("127.0.0.1", port), timeout=10)
                connection += 1
    finally:
        sock.close()
    return seen


def test_every_third_response_closes_its_connection_and_the_client_reconnects() -> None:
    with _served(max_requests=3) as port:
        seen = _requests(port, 7)
    assert seen == [(0, False), (0, False), (0, True), (1, False), (1, False), (1, True), (2, False)]


def test_zero_keeps_connections_open() -> None:
    with _served(max_requests=0) as port:
        assert _requests(port, 5) == [(0, False)] * 5
