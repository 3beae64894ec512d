"""Proof of life for running jobs, so that a job whose process died is noticed in seconds, not minutes.

RQ learns that a job's process died only when the job's entry in the StartedJobRegistry expires. A forking worker
renews that entry from the parent while the child works; a SimpleWorker (ours by default: jobs run in the worker
process) sets it once, for the job's whole timeout plus a minute, so a killed worker's pose job looked alive for 6
minutes and a solve for 11. Here the process that runs a job renews its claims from a background thread every
JOB_HEARTBEAT_S, each for JOB_LIVENESS_TTL_S: RQ's execution entry (through RQ's own `maintain_heartbeats`) and,
for gated jobs, the camera's running slot (workers.jobs). The thread lives in the process doing the work, so a
forked child that outlives its parent keeps its job alive, and a frozen or killed one stops at once.

One thread per process serves every job of that process (`PACEMAKER`): starting a thread per job would cost more
than the millisecond frame jobs themselves.
"""

from __future__ import annotations

import itertools
import logging
import os
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import redis
from rq.executions import Execution, ExecutionRegistry
from rq.job import Job
from rq.queue import Queue
from rq.registry import StartedJobRegistry
from rq.utils import as_text, current_timestamp, parse_composite_key

from service.queue import JOB_HEARTBEAT_S, JOB_LIVENESS_TTL_S

log = logging.getLogger(__name__)


class Pacemaker:
    """Calls every registered beat every `interval_s` from one daemon thread per process (restarted in a fork)."""

    def __init__(self, interval_s: float) -> None:
        self.interval_s = interval_s
        self._beats: dict[int, Callable[[], object]] = {}
        self._keys = itertools.count()
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        os.register_at_fork(after_in_child=self._forget_parent)

    def _forget_parent(self) -> None:
        """In a forked child: the parent's thread and beats are not this process's (and its lock may be held)."""
        self._beats = {}
        self._lock = threading.Lock()
        self._thread = None

    @contextmanager
    def beating(self, beat: Callable[[], object]) -> Iterator[None]:
        """Call `beat` every interval while the block runs (its first call comes within one interval)."""
        with self._lock:
            self._ensure_thread()
            key = next(self._keys)
            self._beats[key] = beat
        try:
            yield
        finally:
            with self._lock:
                self._beats.pop(key, None)

    def _ensure_thread(self) -> None:
        if self._thread is not None and self._thread.is_alive():
            return
        self._thread = threading.Thread(target=self._run, name="job-heartbeat", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        wake = threading.Event()  # never set: a sleep that the interpreter's shutdown does not wait for
        while not wake.wait(self.interval_s):
            with self._lock:
                beats = list(self._beats.values())
            for beat in beats:
                try:
                    beat()
                except Exception as exc:  # Redis unreachable for a moment: the next beat tries again
                    log.warning("job heartbeat failed: %s", exc)


PACEMAKER = Pacemaker(JOB_HEARTBEAT_S)


class ProvesLiveness:
    """Mixin for RQ worker classes: a running job's StartedJobRegistry entry lives JOB_LIVENESS_TTL_S at a time and
    is renewed every JOB_HEARTBEAT_S by the process running the job, so RQ's registry maintenance finds a dead
    job's entry expired within seconds and retries the job (see service.queue)."""

    def get_heartbeat_ttl(self, job: Job, working_time: float = 0.0) -> int:
        return JOB_LIVENESS_TTL_S

    def perform_job(self, job: Job, queue: Queue, execution: Execution) -> bool:
        # maintain_heartbeats renews the worker, the execution (its StartedJobRegistry entry) and the job, and
        # copes with a job deleted under it (result_ttl=0) by a last beat racing the job's end.
        with PACEMAKER.beating(lambda: self.maintain_heartbeats(job, execution)):  # type: ignore[attr-defined]
            return bool(super().perform_job(job, queue, execution))  # type: ignore[misc]


def forget_dead_executions(connection: redis.Redis, queues: list[Queue]) -> None:
    """Drop executions whose heartbeat lapsed from their job's own execution registry, before RQ's maintenance
    retries those jobs.

    RQ 3.0 keeps an execution in the job's registry a minute longer than the execution itself; a retried job
    that succeeds within that minute (ours do, in seconds) is deleted (result_ttl=0), which reads every execution
    of the registry and fails on the dead one ("Execution ... not found in Redis"), so the job is failed and run
    again although it succeeded.
    """
    now = current_timestamp()
    for queue in queues:
        started = StartedJobRegistry(queue.name, connection=connection)
        for entry in connection.zrangebyscore(started.key, 0, now):
            job_id, execution_id = parse_composite_key(as_text(entry))
            connection.zrem(ExecutionRegistry(job_id, connection=connection).key, execution_id)
