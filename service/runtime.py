"""CPython's cyclic garbage collector, tuned for the long-running processes (the API and the workers)."""

from __future__ import annotations

import gc


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
