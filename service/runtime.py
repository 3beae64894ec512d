"""How the long-running processes (the API and the workers) run: how `serve` splits the machine between them, and
CPython's cyclic garbage collector, tuned for them."""

from __future__ import annotations

import gc
import os


def quiet_garbage_collector(thresholds: tuple[int, int, int] | None = None) -> None:
    """Move everything built at start-up (modules, the app, pools) out of the collector's sight, then, if given,
    collect less often (`gc.set_threshold`).

    A full collection walks every tracked object, and after numpy, scipy, SQLAlchemy, pydantic and FastAPI are
    imported that is a few hundred thousand: passes of 73-100 ms in a worker under the load benchmark, each holding
    the process (and, inside a write transaction, the database's write lock). With start-up frozen they took
    7-48 ms. Start-up objects live as long as the process, so they are never garbage; what requests and jobs
    allocate is collected as before."""
    gc.collect()
    gc.freeze()
    if thresholds is not None:
        gc.set_threshold(*thresholds)


def default_process_split(cpus: int | None = None) -> tuple[int, int]:
    """(API processes, workers) for `serve` when not given: two API processes, the other cores' worth of workers
    (at least one).

    The API is bound by its GIL: one process stays near 0.9 of a core however many cores are free. Under
    `posemetry bench load` on 2 cores, one API process and two workers gave a keypoint p99 of 188-287 ms; two API
    processes and one worker 102-105 ms, the one worker measuring every frame (it takes more frames per job when
    it falls behind) and the frames' time to `done` unchanged."""
    cpus = cpus or os.cpu_count() or 1
    api_processes = min(2, cpus)
    return api_processes, max(1, cpus - api_processes)


SPLIT_HELP = "Default: two API processes and the rest of the CPUs as workers (at least one)."
