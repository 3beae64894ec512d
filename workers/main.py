"""The worker process: `posemetry worker --queue frames --queue calibration` (or `python -m workers.main`).

On start, before taking any job, and then again from time to time (workers.recovery), a worker runs the recovery
pass: it asks for every calibrated camera with pending frames to be measured, for pose on every image frame
still waiting for it, for a solve of every camera whose evidence calls for one, and for the next attempt of every
pending webhook delivery (at its time). The API stores first and enqueues second, so anything accepted while
Redis was down (or lost with a Redis that was wiped, or left behind by a job that failed while the database was
down) is still in SQL; this pass hands it to the queues again. Requests are deduplicated per camera, and pose and
delivery attempts by job id, so every worker may do it and several workers starting together do not multiply work.

Every few seconds (MAINTENANCE_INTERVAL_S) a worker also runs RQ's registry maintenance, which retries jobs
whose process died (their heartbeat stopped: workers.liveness), and the recovery pass when it is due.

A worker serving the `webhooks` queue also runs RQ's scheduler (retries wait in its scheduled-job registry;
RQ elects one scheduler per queue among the workers).
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any

import redis
from rq import Queue
from rq.job import Job
from rq.timeouts import JobTimeoutException
from rq.utils import now as rq_now
from rq.utils import utcparse
from sqlalchemy.exc import SQLAlchemyError

from service.calibration.service import solve_due
from service.cameras.repository import list_cameras
from service.dispatch import DispatchUnavailableError
from service.frames.repository import cameras_with_pending_frames, frames_detecting
from service.observability.logs import LOG_FORMATS, configure_logging
from service.observability.multiprocess import ENV as METRICS_DIR_ENV
from service.observability.multiprocess import multiprocess_dir
from service.queue import (
    CALIBRATION_QUEUE,
    FRAMES_QUEUE,
    JOB_HEARTBEAT_S,
    POSE_QUEUE,
    QUEUES,
    WEBHOOKS_QUEUE,
    RedisDispatcher,
    connect,
    redis_url,
    wait_for_redis,
)
from service.runtime import quiet_garbage_collector
from service.settings import Settings, get_settings
from service.store import sessions
from service.store.models import utc_now
from service.webhooks.repository import pending_deliveries
from workers import jobs
from workers.instrumented import InstrumentedSimpleWorker, InstrumentedWorker
from workers.liveness import ProvesLiveness, forget_dead_executions
from workers.recovery import RecoverySchedule, postpone_recovery, request_recovery

log = logging.getLogger(__name__)

# Cameras are read a page at a time.
_PAGE = 1000
REDIS_START_TIMEOUT_S = 30.0
# The periodic pass leaves alone deliveries whose attempt is due less than this long ago (their job is on its way).
SWEEP_GRACE_S = 60.0
# RQ's registry maintenance (abandoned jobs retried, expired entries dropped) every few seconds rather than RQ's
# ten minutes: a job whose process died is retried this long after its heartbeat lapsed, at most. It costs a few
# Redis commands per queue. An idle worker blocks on its queues for WORKER_TTL_S - 15 s at a time (RQ's rule),
# so that sets how soon an idle worker gets to its maintenance.
MAINTENANCE_INTERVAL_S = 5
WORKER_TTL_S = 20
# RQ's lock that keeps workers from cleaning one queue's registries at once; held for milliseconds, it expires
# after RQ's 15 minutes if its holder is killed mid-clean, which would stall the retries of dead jobs that long.
MAINTENANCE_LOCK_TTL_S = 60
# Names the metrics directory this worker made for itself (and removes when it stops).
PRIVATE_METRICS_DIR_ENV = "POSEMETRY_WORKER_PRIVATE_METRICS_DIR"


@dataclass(frozen=True)
class Requeued:
    """What a recovery pass handed to the queues."""

    frames: int
    """Cameras whose pending frames were queued for measuring."""
    images: int
    """Image frames whose pose job was queued."""
    calibrations: int
    deliveries: int = 0
    """Webhook delivery attempts queued (now or at their time)."""


def requeue_deliveries(settings: Settings, dispatcher: RedisDispatcher, *, overdue_only: bool = False) -> int:
    """Queue the next attempt of every pending webhook delivery; with `overdue_only`, only of those due more
    than SWEEP_GRACE_S ago (the periodic sweep). Returns how many jobs were queued."""
    factory = sessions.read_session_factory(settings)
    due_before = utc_now() - timedelta(seconds=SWEEP_GRACE_S) if overdue_only else None
    queued = 0
    after = None
    while True:
        with factory() as session:
            due = pending_deliveries(session, limit=_PAGE, after=after, due_before=due_before)
        queued += dispatcher.deliveries_due((d.delivery_id, d.attempt, d.at) for d in due)
        if len(due) < _PAGE:
            return queued
        after = due[-1].delivery_id


def requeue_pending(settings: Settings, dispatcher: RedisDispatcher, *, periodic: bool = False) -> Requeued:
    """The recovery pass (see the module docstring); `periodic` leaves alone deliveries that are only just due."""
    factory = sessions.read_session_factory(settings)
    with factory() as session:
        pending = cameras_with_pending_frames(session, calibrated_only=True)
        dispatcher.release_lost_claims(FRAMES_QUEUE, pending)
        frames = dispatcher.measure_requested(pending)
        images = dispatcher.images_pending(frames_detecting(session))
    calibrations = 0
    after: str | None = None
    while True:
        with factory() as session:
            cameras = list_cameras(session, limit=_PAGE, after=after)
            due = [camera.id for camera in cameras if solve_due(session, camera, settings)]
        # A forced solve that has not completed (its job failed, or was lost) is asked for again: the gate still
        # holds the forced flag, so the new job is forced too.
        due += [
            camera_id for camera_id in dispatcher.forced_calibrations([c.id for c in cameras]) if camera_id not in due
        ]
        dispatcher.release_lost_claims(CALIBRATION_QUEUE, due)
        for camera_id in due:
            dispatcher.calibration_requested(camera_id, False)
            calibrations += 1
        if len(cameras) < _PAGE:
            break
        after = cameras[-1].id
    deliveries = requeue_deliveries(settings, dispatcher, overdue_only=periodic)
    return Requeued(frames=frames, images=images, calibrations=calibrations, deliveries=deliveries)


def _log_requeued(requeued: Requeued, when: str) -> None:
    counts = (requeued.frames, requeued.images, requeued.calibrations, requeued.deliveries)
    if when == "start" or any(counts):
        log.info(
            "%s: requested measuring for %d cameras, pose for %d image frames, %d due calibrations and %d webhook "
            "attempts",
            when,
            *counts,
        )


def recover(settings: Settings, dispatcher: RedisDispatcher, *, periodic: bool) -> Requeued:
    requeued = requeue_pending(settings, dispatcher, periodic=periodic)
    _log_requeued(requeued, "recovery pass" if periodic else "start")
    return requeued


class MaintainedQueue(Queue):
    """RQ's queue with a maintenance lock that a killed worker cannot hold for 15 minutes (MAINTENANCE_LOCK_TTL_S)."""

    def acquire_maintenance_lock(self) -> bool:
        return bool(self.connection.set(self.registry_cleaning_key, 1, nx=True, ex=MAINTENANCE_LOCK_TTL_S))


class _Recovers:
    """Adds the recovery pass to RQ's maintenance (which runs in the worker, between jobs), and keeps a Redis
    outage during maintenance from stopping the worker: the dequeue loop then waits for Redis to come back."""

    connection: Any

    def __init__(self, *args: Any, settings: Settings | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.settings = settings or get_settings()
        dispatcher = RedisDispatcher(self.connection)
        self.recovery = RecoverySchedule(
            self.connection,
            lambda: recover(self.settings, dispatcher, periodic=True),
            lambda: recover(self.settings, dispatcher, periodic=False),
        )

    def run_maintenance_tasks(self) -> None:
        try:
            forget_dead_executions(self.connection, self.queues)  # type: ignore[attr-defined]
            super().run_maintenance_tasks()  # type: ignore[misc]
            self.recovery.run_if_due()
        except (redis.ConnectionError, redis.TimeoutError) as exc:
            log.warning("maintenance skipped, Redis unavailable: %s", exc)


# Shares of a busy worker's time (webhooks always come first). Measuring gets as much as pose: it is what keypoint
# cameras wait for and a frames job measures all its camera's pending frames, so it keeps up with fewer turns. Pose
# gets more than its usual demand (0.6 images/s x 0.4 s under `posemetry bench load` is a quarter of the worker),
# which keeps it first in line whenever an image arrives; its demand is bounded by the images posted, and a flood of
# images still leaves the others 2/3. Solves get as much too: their demand is bounded as well (a camera is due once
# per 1.5-fold growth of its evidence, then once per four-fold growth), and they have a deadline, which measuring
# has not. With half the others' share, fifty cameras falling due together (`posemetry bench load`) waited 9-10 s
# (p50) and up to 13 s; with an equal one 6.5-7 s and under 9 s, while measuring kept up as before (keypoint frames
# answered 12-13 s after their post, p50).
# The memory is short: a burst (the seed images of a new camera) must not leave its queue behind the others for long.
QUEUE_SHARES: dict[str, float] = {FRAMES_QUEUE: 2.0, POSE_QUEUE: 2.0, CALIBRATION_QUEUE: 2.0}
SHARE_HALF_LIFE_S = 10.0
# Aging: a queue's share grows with its oldest job's wait, from 1x when fresh to MAX_AGING x at its target wait (and
# stays there): a deadline is met by raising a job's priority before it passes, not after. Solves are due within
# 10 s of a camera's evidence calling for one and an image frame is answered within 2 s (issue 17); measuring has no
# such target, as a frames job answers every frame its camera has waiting however long it waited, so it keeps its
# share and gives the others up to MAX_AGING x theirs. At 4x, fifty cameras falling due together under `posemetry
# bench load` waited 10.6-15.7 s (p99) for their solves; at 8x, in the same four pairs of runs alternating, 8.4-12.1 s
# (p50 7.2-9.9 s against 9.2-11.9), with image frames still answered in 0.5-0.8 s (p50) and measuring no later. A
# wave of solves takes the worker for seconds, and measuring, which keeps its own share, catches up after it.
WAIT_TARGET_S: dict[str, float] = {CALIBRATION_QUEUE: 10.0, POSE_QUEUE: 2.0}
MAX_AGING = 8.0


class _SharesTime:
    """Webhooks first; the other queues share the worker's time by QUEUE_SHARES (aged by their waits), so none
    starves another.

    RQ's default serves its queues in strict order, and under load the frames queue is never empty (cameras post
    faster than one worker measures, so there is always a camera with pending frames): image frames waited 37 s
    (p50) for pose and 50 solves were still queued at the end of `posemetry bench load`. Here the worker keeps the
    time its jobs took per queue (decaying with SHARE_HALF_LIFE_S) and, before each dequeue, orders the queues by
    time used per share: the queue furthest behind its share is served first when it has work, and a queue with
    none leaves its share to the others. Time, not turns, because a solve or a pose job takes ten times a frames
    job. Webhooks keep their place at the front: an alert is what users wait for, and a delivery is one short HTTP
    request.

    Fixed shares left solves waiting a minute and more under that load (the solves of fifty cameras fall due
    together, and one in five of the worker's seconds clears a few per second): a queue whose oldest job has waited
    gets a larger share while it waits, MAX_AGING x by its WAIT_TARGET_S, and its usual one once it has caught up.
    Measuring, which has no target, keeps its own share whatever the others wait, so it is slowed, never stopped.
    """

    _ordered_queues: list[Queue]
    clock = staticmethod(time.monotonic)
    wall_clock = staticmethod(rq_now)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.used_s: dict[str, float] = dict.fromkeys(QUEUE_SHARES, 0.0)
        self._decayed_at = self.clock()

    def execute_job(self, job: Job, queue: Queue) -> None:
        started = self.clock()
        try:
            super().execute_job(job, queue)  # type: ignore[misc]
        finally:
            if queue.name in self.used_s:
                self.used_s[queue.name] += self.clock() - started
            self._share_order()

    def oldest_wait_s(self, queue: Queue) -> float:
        """How long the job at the head of `queue` has waited (0 when none, its enqueue time is unknown, or Redis
        cannot say: the worker's own loop deals with an outage, the order of its queues must not)."""
        try:
            job_id = queue.connection.lindex(queue.key, 0)
            if job_id is None:
                return 0.0
            stamp = queue.connection.hget(queue.job_class.key_for(job_id.decode()), "enqueued_at")
        except (redis.ConnectionError, redis.TimeoutError):
            return 0.0
        if not stamp:
            return 0.0
        return max(0.0, (self.wall_clock() - utcparse(stamp.decode())).total_seconds())

    def share(self, queue: Queue) -> float | None:
        """The queue's share of the worker now: QUEUE_SHARES, aged by its oldest job's wait towards WAIT_TARGET_S."""
        share = QUEUE_SHARES.get(queue.name)
        target = WAIT_TARGET_S.get(queue.name)
        if share is None or target is None:
            return share
        return share * (1.0 + (MAX_AGING - 1.0) * min(self.oldest_wait_s(queue) / target, 1.0))

    def _share_order(self) -> None:
        now = self.clock()
        decay = 0.5 ** ((now - self._decayed_at) / SHARE_HALF_LIFE_S)
        self._decayed_at = now
        for name in self.used_s:
            self.used_s[name] *= decay

        def behind(queue: Queue) -> tuple[bool, float]:
            share = self.share(queue)
            return queue.name != WEBHOOKS_QUEUE, 0.0 if share is None else self.used_s[queue.name] / share

        self._ordered_queues = sorted(self._ordered_queues, key=behind)  # stable: ties keep their order


# Exit status of a worker that left after a job overran its timeout (EX_TEMPFAIL: `serve` and Compose start another).
OVERRUN_EXIT_STATUS = 75


class _LeavesAfterAnOverrun:
    """Ends the worker process once a job that overran its timeout has been failed (and retried, if it may be).

    A job run in the worker's own process is stopped at its timeout by an exception in the worker's thread; the
    threads it left working go on. A pose job's crop threads once deadlocked inside OpenVINO for good (see
    service.pose.sessions): the job timed out after POSE_JOB_TIMEOUT_S, and every later pose job waited on the
    same dead threads until it timed out too, while the worker went on looking healthy. Nothing can stop a thread,
    so the process goes (at once: an interpreter exit would wait for the stuck threads) and its supervisor starts a
    fresh one; the overrun job's retry runs there. A forking worker needs none of this (the overrun job's child is
    killed).
    """

    _overran: Job | None = None

    def handle_exception(self, job: Job, *exc_info: Any) -> None:
        super().handle_exception(job, *exc_info)  # type: ignore[misc]
        if exc_info and isinstance(exc_info[0], type) and issubclass(exc_info[0], JobTimeoutException):
            self._overran = job

    def execute_job(self, job: Job, queue: Queue) -> None:
        super().execute_job(job, queue)  # type: ignore[misc]
        if self._overran is not None:
            log.error(
                "job %s (%s) overran its %s s timeout; leaving, so that what it left running cannot block later jobs",
                job.id,
                job.description,
                job.timeout,
            )
            logging.shutdown()
            os._exit(OVERRUN_EXIT_STATUS)


class RecoveringSimpleWorker(_LeavesAfterAnOverrun, _SharesTime, _Recovers, ProvesLiveness, InstrumentedSimpleWorker):
    """Jobs in the worker process, measured (workers.instrumented) and kept alive (workers.liveness)."""


class RecoveringWorker(_SharesTime, _Recovers, ProvesLiveness, InstrumentedWorker):
    """A forked child per job, measured (workers.instrumented) and kept alive (workers.liveness)."""


class _QuietMaintenance(logging.Filter):
    """RQ logs each registry cleaning at INFO; every few seconds that would drown the job lines. Kept at DEBUG."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Worker %s: cleaning") or logging.getLogger("rq.worker").isEnabledFor(
            logging.DEBUG
        )


_QUIET_MAINTENANCE = _QuietMaintenance()


def run_worker(
    queues: Sequence[str] = QUEUES,
    *,
    settings: Settings | None = None,
    burst: bool = False,
    fork: bool = False,
    name: str | None = None,
) -> Requeued:
    """Re-enqueue pending work, then serve `queues` (webhooks first, the others by their share of the worker's
    time) until stopped (or drained, if burst).

    Without `fork`, jobs run in the worker process itself (rq's SimpleWorker): a frame job takes milliseconds,
    and forking a child per job would cost more than the job. `fork` isolates each job in a child process (a
    crash or leak in one job cannot take the worker down) at that price. Either way every job is measured
    (workers.instrumented).
    """
    settings = settings or get_settings()
    jobs.preload()
    if fork:
        from service.pose.sessions import serve_forked_jobs

        serve_forked_jobs()
    if POSE_QUEUE in queues:
        jobs.preload_pose(settings)
    connection = connect(redis_url(settings))
    wait_for_redis(connection, timeout_s=REDIS_START_TIMEOUT_S)
    try:
        requeued = recover(settings, RedisDispatcher(connection), periodic=False)
        postpone_recovery(connection)
    except (SQLAlchemyError, DispatchUnavailableError) as exc:
        # The database (or Redis) is down: start anyway, and let maintenance run the pass once it is back.
        log.error("start-up recovery pass failed, maintenance will retry it: %s", exc)
        request_recovery(connection)
        requeued = Requeued(frames=0, images=0, calibrations=0)
    # Forked children (jobs, RQ's scheduler) must open their own database connections, never inherit the parent's.
    sessions.dispose_engines()
    worker_class = RecoveringWorker if fork else RecoveringSimpleWorker
    worker = worker_class(
        [MaintainedQueue(queue, connection=connection) for queue in queues],
        connection=connection,
        name=name,
        settings=settings,
        worker_ttl=WORKER_TTL_S,
        maintenance_interval=MAINTENANCE_INTERVAL_S,
        job_monitoring_interval=JOB_HEARTBEAT_S,
    )
    logging.getLogger("rq.worker").addFilter(_QUIET_MAINTENANCE)
    quiet_garbage_collector()
    worker.work(burst=burst, logging_level=settings.log_level.upper(), with_scheduler=WEBHOOKS_QUEUE in queues)
    return requeued


def main(argv: Sequence[str] | None = None) -> None:
    """`python -m workers.main`: the same as `posemetry worker`, for images that run modules rather than scripts."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--queue", action="append", choices=QUEUES, help="queue to serve (repeatable; default all)")
    parser.add_argument("--burst", action="store_true", help="exit once the queues are empty")
    parser.add_argument("--fork", action="store_true", help="run each job in a forked child process")
    parser.add_argument("--log-format", choices=LOG_FORMATS, help="json or text (default: setting log_format)")
    parser.add_argument(
        "--metrics-port", type=int, help="serve Prometheus metrics on this port (default: worker_metrics_port)"
    )
    args = parser.parse_args(argv)
    settings = get_settings()
    port = args.metrics_port if args.metrics_port is not None else settings.worker_metrics_port
    if port is not None and multiprocess_dir() is None:
        # A forking worker's job processes must reach the port too, so values go to files in a private directory.
        # prometheus_client chose in-memory values when this module's imports loaded it: start again with the
        # directory set from the first line.
        private = tempfile.mkdtemp(prefix="posemetry-worker-metrics-")
        environment = {**os.environ, METRICS_DIR_ENV: private, PRIVATE_METRICS_DIR_ENV: private}
        arguments = sys.argv[1:] if argv is None else list(argv)
        os.execve(sys.executable, [sys.executable, "-m", "workers.main", *arguments], environment)
    configure_logging(args.log_format or settings.log_format, settings.log_level, secrets=settings.logged_secrets())
    private = os.environ.get(PRIVATE_METRICS_DIR_ENV)
    private_dir = Path(private) if private and private == os.environ.get(METRICS_DIR_ENV) else None
    try:
        if port is not None:
            from service.observability.metrics import start_metrics_server

            start_metrics_server(port, settings.worker_metrics_host)
            log.info("metrics on http://%s:%d/metrics", settings.worker_metrics_host, port)
        run_worker(args.queue or QUEUES, settings=settings, burst=args.burst, fork=args.fork)
    finally:
        if private_dir is not None:
            shutil.rmtree(private_dir, ignore_errors=True)


if __name__ == "__main__":
    main()
