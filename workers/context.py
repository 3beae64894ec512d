"""What every job takes from the RQ job it runs in: the dispatcher on the Redis the job came from."""

from __future__ import annotations

from rq import get_current_job

from service.queue import RedisDispatcher
from service.settings import Settings


def current_dispatcher(settings: Settings) -> RedisDispatcher:
    """The dispatcher on the Redis this job came from (else the configured one, for direct calls and tests)."""
    job = get_current_job()
    if job is not None:
        return RedisDispatcher(job.connection)
    return RedisDispatcher.from_settings(settings)
