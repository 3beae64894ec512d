"""The API processes' own sockets (service.cli.listeners): the kernel, not a race between processes, places each
connection, the supervisor's placeholder never takes one, and a process uvicorn restarts listens again."""

from __future__ import annotations

import json
import os
import pickle
import selectors
import signal
import socket
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import pytest

from service.cli import listeners
from tests.support.serving import Served, clean_environment, free_port, serve

pytestmark = pytest.mark.skipif(not listeners.BALANCES, reason="SO_REUSEPORT balances connections on Linux only")

CONNECTIONS = 64


def test_each_process_gets_its_own_listener_and_the_kernel_spreads_connections() -> None:
    reserved, own = listeners.reserve("127.0.0.1", 0)
    port = own.address[1]
    assert port != 0 and reserved.getsockname() == ("127.0.0.1", port)
    # What each API process does: unpickle the stand-in (spawn), then listen on the socket it became.
    first, second = (pickle.loads(pickle.dumps(own)) for _ in range(2))
    clients: list[socket.socket] = []
    try:
        assert isinstance(first, socket.socket) and first.fileno() != second.fileno()
        assert first.getsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT) == 1
        for listener in (first, second):
            listener.listen(CONNECTIONS)
            listener.setblocking(False)
        # Each client is a new connection from a new source port, as a camera's would be.
        clients = [socket.create_connection(("127.0.0.1", port), timeout=5) for _ in range(CONNECTIONS)]
        accepted = {first.fileno(): 0, second.fileno(): 0}
        with selectors.DefaultSelector() as selector:
            for listener in (first, second):
                selector.register(listener, selectors.EVENT_READ)
            deadline = time.monotonic() + 10
            while sum(accepted.values()) < CONNECTIONS and time.monotonic() < deadline:
                for key, _ in selector.select(timeout=0.5):
                    conn, _ = key.fileobj.accept()  # type: ignore[union-attr]
                    conn.close()
                    accepted[key.fd] += 1
        # Every connection reached a listening process (none queued on the placeholder), and both processes got a
        # share: a binomial split of 64 leaves either side under 16 with a probability of about 1e-5.
        assert sum(accepted.values()) == CONNECTIONS
        assert min(accepted.values()) >= 16, accepted
    finally:
        for sock in (*clients, first, second, reserved):
            sock.close()


def test_the_placeholder_holds_the_port() -> None:
    reserved, own = listeners.reserve("127.0.0.1", 0)
    try:
        with socket.socket() as other, pytest.raises(OSError):
            other.bind(own.address)  # a process without SO_REUSEPORT cannot take the API's port
    finally:
        reserved.close()


def _listening(port: int) -> int:
    """TCP sockets listening on `port` (/proc/net/tcp: one line per socket, state 0A is LISTEN)."""
    lines = Path("/proc/net/tcp").read_text().splitlines()[1:]
    return sum(1 for fields in map(str.split, lines) if int(fields[1].split(":")[1], 16) == port and fields[3] == "0A")


def _api_processes(app: Served) -> set[int]:
    """serve's uvicorn processes (spawned by multiprocessing; the workers and Redis are started otherwise)."""
    return app.children("spawn_main")


def _served_by(log_path: Path, prefix: str) -> Counter[int]:
    """How many requests whose id starts with `prefix` each process logged."""
    records = (json.loads(line) for line in log_path.read_text().splitlines() if line.startswith("{"))
    return Counter(r["pid"] for r in records if str(r.get("request_id", "")).startswith(prefix))


def test_serve_s_api_processes_listen_each_and_share_new_connections(tmp_path: Path) -> None:
    port, log_path = free_port(), tmp_path / "serve.log"
    args = ["--api-processes", "2", "--workers", "1", "--log-format", "json"]
    with serve(tmp_path / "serve", clean_environment(), args, output=log_path, port=port) as app:
        app.wait_for(lambda: len(_api_processes(app)) == 2 and _listening(port) == 2, "a socket per API process")
        apis = _api_processes(app)
        # urllib opens a new connection for each request, as a camera does when it (re)connects.
        for index in range(40):
            assert app.http("GET", "/readyz", headers={"X-Request-ID": f"spread-{index}"})[0] == 200
        app.wait_for(lambda: sum(_served_by(log_path, "spread-").values()) == 40, "the 40 requests' log lines")
        served = _served_by(log_path, "spread-")
        assert set(served) == apis and min(served.values()) >= 5, served  # binomial(40): P(< 5) ~ 1e-7

        # uvicorn's supervisor replaces a dead API process; the new one opens its own socket again.
        victim = min(apis)
        os.kill(victim, signal.SIGKILL)
        app.wait_for(
            lambda: victim not in _api_processes(app) and len(_api_processes(app)) == 2 and _listening(port) == 2,
            "a replacement API process listening",
        )
        for index in range(40):
            assert app.http("GET", "/readyz", headers={"X-Request-ID": f"again-{index}"})[0] == 200
        app.wait_for(lambda: sum(_served_by(log_path, "again-").values()) == 40, "the 40 requests' log lines")
        assert set(_served_by(log_path, "again-")) == _api_processes(app)
        assert app.stop() == 0


def _get(sock: socket.socket, request_id: str) -> bool:
    """GET /healthz on `sock`; whether the answer closes the connection."""
    sock.sendall(f"GET /healthz HTTP/1.1\r\nHost: test\r\nX-Request-ID: {request_id}\r\n\r\n".encode())
    data = b""
    while b"\r\n\r\n" not in data or not data.rstrip().endswith(b"}"):
        chunk = sock.recv(4096)
        assert chunk, "closed before the answer"
        data += chunk
    return b"\r\nconnection: close\r\n" in data.lower()


def _request_all(cameras: list[socket.socket], port: int, prefix: str) -> None:
    """One request on each camera's connection; a camera whose answer closes its connection connects again."""
    for index, camera in enumerate(cameras):
        if _get(camera, f"{prefix}{index}"):
            camera.close()
            cameras[index] = socket.create_connection(("127.0.0.1", port), timeout=30)


def _post_while(cameras: list[socket.socket], port: int, condition: Callable[[], bool], what: str) -> None:
    """Wait for `condition` with every camera requesting twice a second: a camera posts on, and a connection left
    idle is closed by uvicorn after 5 s (which on a loaded machine outlasted the replacement of a killed process
    and failed the test below)."""
    deadline = time.monotonic() + 60.0
    sent = 0
    while not condition():
        assert time.monotonic() < deadline, f"timed out after 60 s waiting for {what}"
        _request_all(cameras, port, f"meanwhile-{sent}-")
        sent += 1
        time.sleep(0.5)


def test_connections_that_all_reached_one_process_spread_once_recycled(tmp_path: Path) -> None:
    """While uvicorn replaces a killed API process, the cameras that reconnect all reach the other one; closing
    each connection after a few requests (keep_alive_max_requests) lets the kernel place them again."""
    port, log_path = free_port(), tmp_path / "serve.log"
    args = ["--api-processes", "2", "--workers", "1", "--log-format", "json"]
    env = clean_environment(keep_alive_max_requests="4")
    with serve(tmp_path / "serve", env, args, output=log_path, port=port) as app:
        app.wait_for(lambda: len(_api_processes(app)) == 2 and _listening(port) == 2, "a socket per API process")
        survivor, victim = sorted(_api_processes(app))
        os.kill(victim, signal.SIGKILL)
        app.wait_for(lambda: _listening(port) == 1, "the killed process's socket gone")
        cameras = [socket.create_connection(("127.0.0.1", port), timeout=30) for _ in range(40)]
        try:
            for index, camera in enumerate(cameras):
                assert not _get(camera, f"first-{index}")
            _post_while(cameras, port, lambda: _served_by(log_path, "first-") == Counter({survivor: 40}), "40 lines")
            _post_while(cameras, port, lambda: len(_api_processes(app)) == 2 and _listening(port) == 2, "a replacement")
            for round_ in range(4):  # each connection's 4th answer closes it; the camera reconnects
                _request_all(cameras, port, f"round{round_}-")
            for index, camera in enumerate(cameras):
                _get(camera, f"last-{index}")
            app.wait_for(lambda: sum(_served_by(log_path, "last-").values()) == 40, "the last requests' log lines")
            last = _served_by(log_path, "last-")
            assert set(last) == _api_processes(app) and min(last.values()) >= 5, last  # binomial(40): P ~ 1e-7
        finally:
            for camera in cameras:
                camera.close()
        assert app.stop() == 0
