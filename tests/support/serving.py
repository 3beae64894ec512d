"""`posemetry serve` as a subprocess, driven over HTTP exactly as a user's camera system or dashboard would."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import psutil

REPO = Path(__file__).resolve().parents[2]
DEADLINE_S = 60.0
STOP_TIMEOUT_S = 30.0


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


# The admin key the served API is started with (POSEMETRY_ADMIN_KEY); `Served.http` sends it.
ADMIN_KEY = "serve-test-admin-key-0123456789abcdefghijklmnop"


def clean_environment(**settings: str) -> dict[str, str]:
    """This process's environment without any POSEMETRY_* setting (nor a PROMETHEUS_MULTIPROC_DIR), plus the admin
    key and `settings` (names without the prefix)."""
    env = {key: value for key, value in os.environ.items() if not key.startswith(("POSEMETRY_", "PROMETHEUS_"))}
    env["POSEMETRY_ADMIN_KEY"] = ADMIN_KEY
    env.update({f"POSEMETRY_{name.upper()}": value for name, value in settings.items()})
    return env


@dataclass
class Served:
    """A running `posemetry serve` and an HTTP client for it."""

    process: subprocess.Popen[bytes]
    base: str
    api_key: str | None = None
    """Sent as `Authorization: Bearer` on every request unless a call passes its own token."""

    def http(
        self,
        method: str,
        path: str,
        body: Any = None,
        token: str | None = None,
        headers: dict[str, str] | None = None,
    ) -> tuple[int, Any]:
        """(status, decoded JSON body or None) of a JSON request; 4xx/5xx are returned, not raised.

        `token` replaces the admin key ("" sends no Authorization header).
        """
        data = None if body is None else json.dumps(body).encode()
        status, content, _type = self.raw(method, path, data, "application/json", token, headers)
        return status, json.loads(content) if content else None

    def raw(
        self,
        method: str,
        path: str,
        data: bytes | None = None,
        content_type: str | None = None,
        token: str | None = None,
        headers: dict[str, str] | None = None,
    ) -> tuple[int, bytes, str]:
        """(status, body bytes, content type) of any request."""
        token = self.api_key if token is None else token
        headers = dict(headers or {})
        if token:
            headers["Authorization"] = f"Bearer {token}"
        if data is not None and content_type is not None:
            headers["content-type"] = content_type
        request = urllib.request.Request(f"{self.base}{path}", data=data, method=method, headers=headers)
        try:
            with urllib.request.urlopen(request, timeout=30) as response:
                return response.status, response.read(), response.headers.get("content-type", "")
        except urllib.error.HTTPError as exc:
            return exc.code, exc.read(), exc.headers.get("content-type", "")

    def wait_for(self, condition: Callable[[], bool], what: str, timeout_s: float = DEADLINE_S) -> None:
        wait_for(self.process, condition, what, timeout_s)

    def ready(self) -> bool:
        try:
            return self.http("GET", "/readyz")[0] == 200
        except OSError:
            return False

    def stop(self) -> int:
        return stop(self.process)

    def children(self, marker: str) -> set[int]:
        """Live child processes of serve whose command line contains `marker` (`workers.main` for the workers,
        `spawn_main` for uvicorn's API processes)."""
        pids = set()
        for child in psutil.Process(self.process.pid).children():
            try:
                if child.status() != psutil.STATUS_ZOMBIE and marker in " ".join(child.cmdline()):
                    pids.add(child.pid)
            except psutil.Error:
                pass  # exited between listing and inspection
        return pids


def wait_for(
    process: subprocess.Popen[bytes], condition: Callable[[], bool], what: str, timeout_s: float = DEADLINE_S
) -> None:
    """Poll `condition` until it holds; fail at once if `process` exits meanwhile."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if process.poll() is not None:
            raise AssertionError(f"{process.args[3:5]} exited with {process.returncode} waiting for {what}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(0.2)


def stop(process: subprocess.Popen[bytes]) -> int:
    """SIGTERM, as Ctrl-C would; returns the exit code (the process is killed if it does not stop). Idempotent."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
    try:
        return process.wait(timeout=STOP_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
        raise


@contextmanager
def serve(
    data_dir: Path, env: dict[str, str], args: Sequence[str] = (), output: Path | None = None, port: int | None = None
) -> Iterator[Served]:
    """Start `posemetry serve` (the command's own code path), wait until it is ready, stop it afterwards.

    `output` collects the process's stdout and stderr. The exit code is checked by callers that care
    (`served.stop()` is idempotent).
    """
    port = port or free_port()
    command = [sys.executable, "-m", "service.cli", "serve", "--data-dir", str(data_dir), "--port", str(port)]
    log = None if output is None else output.open("wb")
    try:
        process = subprocess.Popen([*command, *args], cwd=REPO, env=env, stdout=log, stderr=log)
    finally:
        if log is not None:
            log.close()
    served = Served(process, f"http://127.0.0.1:{port}", env.get("POSEMETRY_ADMIN_KEY"))
    try:
        served.wait_for(served.ready, "the API to be ready")
        yield served
    finally:
        served.stop()
