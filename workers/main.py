"""The worker process: `posemetry worker --queue frames --queue calibration` (or `python -m workers.main`).

On start, before taking any job, a worker asks for every camera with pending frames to be measured, for a
solve of every camera whose evidence calls for one, and for the next attempt of every pending webhook delivery
(at its time). The API stores first and enqueues second, so anything accepted while Redis was down (or lost with
a Redis that was wiped) is still in SQL; this start-up pass hands it to the queues again. Requests are
deduplicated per camera, and delivery attempts by job id, so every worker may do it and several workers starting
together do not multiply work.

A worker serving the `webhooks` queue also runs RQ's scheduler (retries wait in its scheduled-job registry;
RQ elects one scheduler per queue among the workers). Every worker, with RQ's maintenance every ten minutes,
sweeps SQL for deliveries whose attempt is overdue because queuing it failed (Redis down when a retry was due).
"""

from __future__ import annotations

import argparse
import logging
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any

from rq import Queue

from service.observability.logs import LOG_FORMATS, configure_logging
from service.observability.multiprocess import multiprocess_dir, use_directory
from service.queue import POSE_QUEUE, QUEUES, WEBHOOKS_QUEUE, RedisDispatcher, connect, redis_url, wait_for_redis
from service.settings import Settings, get_settings
from service.store.models import utc_now
from service.store.repository import calibration_due, cameras_with_pending_frames, frames_detecting, list_cameras
from service.store.webhooks import pending_deliveries
from workers import jobs
from workers.instrumented import InstrumentedSimpleWorker, InstrumentedWorker

log = logging.getLogger(__name__)

# Cameras are read a page at a time.
_PAGE = 1000
REDIS_START_TIMEOUT_S = 30.0
# The sweep leaves alone deliveries whose attempt is due less than this long ago (their job is on its way).
SWEEP_GRACE_S = 60.0


@dataclass(frozen=True)
class Requeued:
    """What the start-up pass handed to the queues."""

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
    factory = jobs.read_session_factory(settings)
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


def requeue_pending(settings: Settings, dispatcher: RedisDispatcher) -> Requeued:
    """Request measuring for cameras with pending frames, and due calibrations (see the module docstring)."""
    factory = jobs.read_session_factory(settings)
    with factory() as session:
        frames = dispatcher.measure_requested(cameras_with_pending_frames(session))
        images = dispatcher.images_pending(frames_detecting(session))
    calibrations = 0
    after: str | None = None
    while True:
        with factory() as session:
            cameras = list_cameras(session, limit=_PAGE, after=after)
            due = [
                camera.id
                for camera in cameras
                if calibration_due(
                    camera,
                    min_people=settings.calibration_min_people,
                    growth_factor=settings.calibration_growth_factor,
                )
            ]
        for camera_id in due:
            dispatcher.calibration_requested(camera_id, False)
            calibrations += 1
        if len(cameras) < _PAGE:
            break
        after = cameras[-1].id
    deliveries = requeue_deliveries(settings, dispatcher)
    return Requeued(frames=frames, images=images, calibrations=calibrations, deliveries=deliveries)


class _SweepsDeliveries:
    """Adds the webhook sweep to RQ's periodic maintenance (which runs in the worker, between jobs)."""

    connection: Any

    def __init__(self, *args: Any, settings: Settings | None = None, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.settings = settings or get_settings()

    def run_maintenance_tasks(self) -> None:
        super().run_maintenance_tasks()  # type: ignore[misc]
        try:
            queued = requeue_deliveries(self.settings, RedisDispatcher(self.connection), overdue_only=True)
        except Exception:  # a failed sweep must not stop the worker; the next one tries again
            log.exception("webhook delivery sweep failed")
            return
        if queued:
            log.warning("sweep: queued %d overdue webhook delivery attempts", queued)


class SweepingSimpleWorker(_SweepsDeliveries, InstrumentedSimpleWorker):
    """Jobs in the worker process, measured (workers.instrumented), with the webhook sweep."""


class SweepingWorker(_SweepsDeliveries, InstrumentedWorker):
    """A forked child per job, measured (workers.instrumented), with the webhook sweep."""


def run_worker(
    queues: Sequence[str] = QUEUES,
    *,
    settings: Settings | None = None,
    burst: bool = False,
    fork: bool = False,
    name: str | None = None,
) -> Requeued:
    """Re-enqueue pending work, then serve `queues` (in priority order) until stopped (or drained, if burst).

    Without `fork`, jobs run in the worker process itself (rq's SimpleWorker): a frame job takes milliseconds,
    and forking a child per job would cost more than the job. `fork` isolates each job in a child process (a
    crash or leak in one job cannot take the worker down) at that price. Either way every job is measured
    (workers.instrumented).
    """
    settings = settings or get_settings()
    jobs.preload()
    if POSE_QUEUE in queues:
        jobs.preload_pose(settings)
    connection = connect(redis_url(settings))
    wait_for_redis(connection, timeout_s=REDIS_START_TIMEOUT_S)
    requeued = requeue_pending(settings, RedisDispatcher(connection))
    log.info(
        "requested measuring for %d cameras, pose for %d image frames, %d due calibrations and %d webhook attempts",
        requeued.frames,
        requeued.images,
        requeued.calibrations,
        requeued.deliveries,
    )
    # Forked children (jobs, RQ's scheduler) must open their own database connections, never inherit the parent's.
    jobs.dispose_engines()
    worker_class = SweepingWorker if fork else SweepingSimpleWorker
    worker = worker_class(
        [Queue(queue, connection=connection) for queue in queues], connection=connection, name=name, settings=settings
    )
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
    configure_logging(args.log_format or settings.log_format, settings.log_level)
    port = args.metrics_port if args.metrics_port is not None else settings.worker_metrics_port
    private_dir = None
    if port is not None and multiprocess_dir() is None:
        # A forking worker's job processes must reach the port too: they write to files in a private directory.
        private_dir = use_directory(Path(tempfile.mkdtemp(prefix="posemetry-worker-metrics-")), clear=False)
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
