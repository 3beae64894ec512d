"""The worker process: `posemetry worker --queue frames --queue calibration` (or `python -m workers.main`).

On start, before taking any job, a worker asks for every camera with pending frames to be measured and for a
solve of every camera whose evidence calls for one. The API stores first and enqueues second, so anything
accepted while Redis was down (or lost with a Redis that was wiped) is still in SQL; this start-up pass hands it
to the queues again. Requests are deduplicated per camera, so every worker may do it and several workers starting
together do not multiply work.
"""

from __future__ import annotations

import argparse
import logging
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from rq import Queue

from service.observability.logs import LOG_FORMATS, configure_logging
from service.observability.multiprocess import multiprocess_dir, use_directory
from service.queue import POSE_QUEUE, QUEUES, RedisDispatcher, connect, redis_url, wait_for_redis
from service.settings import Settings, get_settings
from service.store.repository import calibration_due, cameras_with_pending_frames, frames_detecting, list_cameras
from workers import jobs

log = logging.getLogger(__name__)

# Cameras are read a page at a time.
_PAGE = 1000
REDIS_START_TIMEOUT_S = 30.0


@dataclass(frozen=True)
class Requeued:
    """What the start-up pass handed to the queues."""

    frames: int
    """Cameras whose pending frames were queued for measuring."""
    images: int
    """Image frames whose pose job was queued."""
    calibrations: int


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
    return Requeued(frames=frames, images=images, calibrations=calibrations)


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
    from workers.instrumented import InstrumentedSimpleWorker, InstrumentedWorker

    settings = settings or get_settings()
    jobs.preload()
    if POSE_QUEUE in queues:
        jobs.preload_pose(settings)
    connection = connect(redis_url(settings))
    wait_for_redis(connection, timeout_s=REDIS_START_TIMEOUT_S)
    requeued = requeue_pending(settings, RedisDispatcher(connection))
    log.info(
        "requested measuring for %d cameras, pose for %d image frames and %d due calibrations",
        requeued.frames,
        requeued.images,
        requeued.calibrations,
    )
    # Forked children must open their own database connections, never inherit the parent's.
    jobs.dispose_engines()
    worker_class = InstrumentedWorker if fork else InstrumentedSimpleWorker
    worker = worker_class([Queue(queue, connection=connection) for queue in queues], connection=connection, name=name)
    worker.work(burst=burst, logging_level=settings.log_level.upper())
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
