"""The shared metrics directory of prometheus-client's multiprocess mode, and its lifecycle.

Deliberately free of prometheus_client imports: the library chooses between in-memory and file-backed values
when it is first imported, from `PROMETHEUS_MULTIPROC_DIR`, so the commands that start processes must be able
to set the directory up before anything imports it (see service.observability.metrics for the design).

Lifecycle, per the library's documentation: the directory is emptied when the process tree that owns it starts
(`posemetry serve`, `posemetry api --processes N`), since values left by an earlier run would be added to this
run's; a process that dies has its live-gauge files removed (`mark_process_dead`), while its counters and
histograms stay, because their totals must not go backwards.
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path

ENV = "PROMETHEUS_MULTIPROC_DIR"
DIR_NAME = "metrics"
# A forking worker's job processes share one set of files (see metrics._process_identifier).
HORSE_SUFFIX = "-horse"
_LIVE_FILE = re.compile(rf"gauge_live[a-z]+_(\d+)(?:{re.escape(HORSE_SUFFIX)})?\.db")


def multiprocess_dir() -> Path | None:
    """The shared directory when this process runs in multiprocess mode, else None."""
    value = os.environ.get(ENV)
    return Path(value) if value else None


def use_directory(path: Path, *, clear: bool) -> Path:
    """Make `path` this process's (and its future children's) metrics directory, emptied if `clear`.

    Must run before prometheus_client is imported in this process, or this process would keep its values in
    memory where no scrape sees them; that mistake raises instead of silently losing metrics.
    """
    if "prometheus_client" in sys.modules and os.environ.get(ENV) != str(path):
        raise RuntimeError(f"{ENV} must be set before prometheus_client is imported")
    path.mkdir(parents=True, exist_ok=True)
    if clear:
        for stale in path.glob("*.db"):
            stale.unlink(missing_ok=True)
    os.environ[ENV] = str(path)
    return path


def mark_process_dead(pid: int, path: Path | None = None) -> None:
    """Forget a dead process's live gauges (its requests or jobs in progress), and those of its job processes."""
    path = path or multiprocess_dir()
    if path is None:
        return
    from prometheus_client import multiprocess

    multiprocess.mark_process_dead(pid, str(path))
    multiprocess.mark_process_dead(f"{pid}{HORSE_SUFFIX}", str(path))


def sweep_dead_processes(path: Path) -> list[int]:
    """Mark dead every process that left live-gauge files but no longer runs; returns their pids.

    `posemetry serve` marks the workers it restarts itself, but uvicorn restarts API processes without telling
    anyone, so a scrape sweeps. Processes sharing a directory share a host and a PID namespace, so a pid that
    does not exist here is dead.
    """
    dead = set()
    for file in path.glob("gauge_live*.db"):
        match = _LIVE_FILE.fullmatch(file.name)
        if match and not _running(int(match.group(1))):
            dead.add(int(match.group(1)))
    for pid in dead:
        mark_process_dead(pid, path)
    return sorted(dead)


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # exists, owned by someone else
    return True
