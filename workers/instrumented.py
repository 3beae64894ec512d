"""RQ workers that measure every job and log under its context, whatever the queue (frames, pose, calibration,
webhooks, or one added later): the job metrics are keyed by the queue a job came from, not by job function.

The measurement wraps `execute_job`, which runs in the worker process itself for both worker kinds: around the
job for SimpleWorker, around the fork and the wait for the forking Worker. So a job whose process is killed, or
that times out, is still counted, by the process that saw it die. The outcome is read from the job afterwards:
a forked job's status lives in Redis only, and a job that succeeded with `result_ttl=0` is already deleted then.
"""

from __future__ import annotations

import time

from rq import SimpleWorker, Worker
from rq.exceptions import InvalidJobOperation, NoSuchJobError
from rq.job import Job, JobStatus
from rq.queue import Queue

from service.observability.logs import log_context
from service.observability.metrics import JOB_DURATION, JOB_FAILURES, JOBS_IN_PROGRESS, share_files_with_forked_jobs
from service.observability.request_id import JOB_META_KEY, request_id_context

_OUTCOMES = {
    JobStatus.FINISHED: "succeeded",
    JobStatus.FAILED: "failed",
    JobStatus.STOPPED: "stopped",
    JobStatus.QUEUED: "retried",
    JobStatus.SCHEDULED: "retried",
    JobStatus.DEFERRED: "retried",
}


def job_outcome(job: Job) -> str:
    """succeeded, failed, retried or stopped, for a job its worker has just finished with."""
    status = job.get_status(refresh=False)  # set in this process when the job ran here
    if status not in _OUTCOMES or status == JobStatus.QUEUED:
        try:
            status = job.get_status(refresh=True)
        except (InvalidJobOperation, NoSuchJobError):
            return "succeeded"  # deleted on success: its result was not to be kept
    return _OUTCOMES.get(status, "failed")  # still `started`: its process died before it could say otherwise


class _Instrumented:
    """Mixin for RQ worker classes: job duration, outcome, failures and in-progress count; log context."""

    def execute_job(self, job: Job, queue: Queue) -> None:
        in_progress = JOBS_IN_PROGRESS.labels(queue=queue.name)
        failures = JOB_FAILURES.labels(queue=queue.name)  # exported from the first job on, as 0 until one fails
        started = time.perf_counter()
        in_progress.inc()
        try:
            with log_context(job_id=job.id, queue=queue.name), request_id_context(job.meta.get(JOB_META_KEY)):
                super().execute_job(job, queue)  # type: ignore[misc]
        finally:
            in_progress.dec()
            outcome = job_outcome(job)
            JOB_DURATION.labels(queue=queue.name, outcome=outcome).observe(time.perf_counter() - started)
            if outcome in ("failed", "retried"):
                failures.inc()


class InstrumentedSimpleWorker(_Instrumented, SimpleWorker):
    """Jobs run in the worker process (the default: a frame job takes milliseconds, a fork ~10 ms)."""


class InstrumentedWorker(_Instrumented, Worker):
    """Each job runs in a forked child; the children's metrics share one set of files (see metrics)."""

    def fork_work_horse(self, job: Job, queue: Queue) -> None:
        share_files_with_forked_jobs()
        super().fork_work_horse(job, queue)
