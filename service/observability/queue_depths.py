"""Queue depths read from Redis at scrape time (the API's /metrics), one pipelined round trip per scrape."""

from __future__ import annotations

import time
from collections.abc import Sequence

import redis
from rq import Queue
from rq.registry import FailedJobRegistry, ScheduledJobRegistry, StartedJobRegistry

from service.dispatch import DispatchUnavailableError

QUEUE_STATES = ("queued", "started", "failed", "scheduled")


class QueueDepths:
    """Jobs per RQ queue and state: `queued` (waiting), `started` (running on a live worker), `failed` (kept for
    inspection until their failure TTL) and `scheduled` (waiting for a time, e.g. a retry's backoff).

    Every queue RQ knows is reported, so a queue added later (webhooks) appears without a change here; `known`
    names are reported as 0 before their first job. Started and failed registries are sorted sets scored by
    expiry, so entries already past it (a dead worker's job not yet cleaned up) are not counted.
    """

    def __init__(self, connection: redis.Redis, known: Sequence[str] = ()) -> None:
        self.connection = connection
        self.known = tuple(known)

    def read(self) -> dict[tuple[str, str], int]:
        """{(queue, state): jobs}; raises DispatchUnavailableError when Redis cannot be read."""
        try:
            return self._read()
        except (redis.RedisError, OSError) as exc:
            raise DispatchUnavailableError(f"job queue unavailable: {exc}") from exc

    def _read(self) -> dict[tuple[str, str], int]:
        names = sorted({*self.known, *(queue.name for queue in Queue.all(connection=self.connection))})
        now = time.time()
        with self.connection.pipeline(transaction=False) as pipe:
            for name in names:
                pipe.llen(Queue(name, connection=self.connection).key)
                pipe.zcount(StartedJobRegistry(name, connection=self.connection).key, now, "+inf")
                pipe.zcount(FailedJobRegistry(name, connection=self.connection).key, now, "+inf")
                pipe.zcard(ScheduledJobRegistry(name, connection=self.connection).key)
            counts = iter(pipe.execute())
        return {(name, state): int(next(counts)) for name in names for state in QUEUE_STATES}
