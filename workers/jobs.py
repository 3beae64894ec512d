"""The RQ jobs, as thin adapters over the service: find the people in an image frame (`detect_people`), measure a
camera's pending frames (`measure_frames`) and solve a camera (`calibrate_camera`).

The work itself is the service's (service.frames.detection, service.frames.service.measure_pending,
service.calibration.service.solve_camera); what is left here is what belongs to running under RQ. Measuring and
solving are gated per camera (service.queue.CameraGate), with a heartbeat that keeps the camera's slot while the
job runs (workers.liveness). All three are safe to run more than once (RQ retries a job whose process died, see
service.queue). A job that meets an unavailable database fails (RQ retries it at once, in case it was a blip) and
asks for the workers' recovery pass, which queues the work again once the database answers (workers.recovery).
"""

from __future__ import annotations

import functools
import logging
import uuid
from collections.abc import Callable
from typing import ParamSpec, TypeVar

from rq import get_current_job
from sqlalchemy.exc import SQLAlchemyError

from service.calibration.service import solve_camera
from service.domain import DONE, SKIPPED
from service.frames import detection
from service.frames.service import measure_pending
from service.observability.logs import log_context
from service.queue import CALIBRATION_QUEUE, FRAMES_QUEUE, RedisDispatcher, new_job_id
from service.settings import Settings, get_settings
from service.store.db import is_database_unavailable
from workers.context import current_dispatcher
from workers.liveness import PACEMAKER
from workers.recovery import request_recovery

log = logging.getLogger(__name__)

_P = ParamSpec("_P")
_R = TypeVar("_R")


def preload() -> None:
    """Import the geometry now, so forked job processes inherit it instead of each importing scipy again."""
    import service.frames.measure
    import service.geometry  # noqa: F401


def preload_pose(settings: Settings) -> None:
    """Load the pose models now (a pose worker's first job should not pay ~0.5 s), and say loudly if they are
    missing; the worker still serves its other queues, and image frames fail with the same message."""
    from service.pose.model_files import ModelFilesError
    from service.pose.pipeline import load_pose_estimator

    try:
        estimator = load_pose_estimator(settings)
    except ModelFilesError as exc:
        if set(exc.problems.values()) == {"missing"}:
            # None installed: a keypoint-only deployment, which is normal; say it once, quietly.
            log.info(
                "no pose models in %s: keypoint frames are unaffected; image frames will fail until the models are "
                "installed (posemetry models fetch --dir %s)",
                exc.model_dir,
                exc.model_dir,
            )
        else:
            log.error("pose models unavailable, image frames will fail until they are installed: %s", exc)
        return
    log.info("pose estimator %s loaded", estimator.name)


def _recovers_from_outages(job_function: Callable[_P, _R]) -> Callable[_P, _R]:
    """A job that meets an unavailable database asks for the workers' recovery pass before it fails, so its work
    is queued again once the database answers (its own retries come too soon for an outage)."""

    @functools.wraps(job_function)
    def run(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        try:
            return job_function(*args, **kwargs)
        except SQLAlchemyError as exc:
            if is_database_unavailable(exc):
                log.warning("database unavailable (%s): the recovery pass will queue this work again", exc)
                request_recovery(current_dispatcher(get_settings()).connection)
            raise

    return run


def _gated(
    kind: str, camera_id: str, work: Callable[[RedisDispatcher, bool], str], *, job_id: str | None = None
) -> str:
    """Run `work(dispatcher, forced)` in the camera's slot for `kind`, then queue the re-run it owes.

    The gate guarantees one job of a kind per camera at a time; requests that arrived while this one ran become
    exactly one re-run, queued when this one finishes (whatever the outcome, hence `finally`). While the work
    runs, the process's heartbeat renews the slot (workers.liveness): if the process dies, the slot lapses within
    seconds and RQ's retry of this job takes it again.
    """
    dispatcher = current_dispatcher(get_settings())
    if job_id is None:
        job = get_current_job()
        job_id = job.id if job is not None else new_job_id(kind, camera_id)
    gate = dispatcher.gates[kind]
    ticket = gate.start(camera_id, job_id)
    if not ticket.run:
        return SKIPPED  # another job of this kind runs for the camera; the gate has scheduled a re-run after it
    completed = False
    try:
        with log_context(camera_id=camera_id), PACEMAKER.beating(lambda: gate.refresh(camera_id, job_id)):
            outcome = work(dispatcher, ticket.forced)
        completed = True
        return outcome
    finally:
        next_job_id = new_job_id(kind, camera_id)
        if gate.finish(camera_id, job_id, next_job_id, completed=completed):
            dispatcher.enqueue(kind, camera_id, next_job_id)


@_recovers_from_outages
def detect_people(frame_id: str) -> str:
    """Find the people in an image frame and store them (service.frames.detection), then measure the camera's
    pending frames in this job, in the camera's measuring slot.

    A frames job would wait its turn behind every keypoint camera's (a FIFO of 50 cameras under `posemetry bench
    load`: image frames were answered 20 s after their pose). Measuring an image camera's frame or two costs
    milliseconds, so the pose capacity answers its own frames. If a frames job of the camera is running, the gate
    makes that one run again instead; if this job dies before measuring, its retry (or the recovery pass) finds
    the frame pending and asks for a frames job."""
    settings = get_settings()
    frame_uuid = uuid.UUID(frame_id)
    outcome = detection.detect_people(settings, current_dispatcher(settings), frame_uuid, measure=False)
    if outcome == DONE:
        camera_id = detection.camera_of(settings, frame_uuid)
        if camera_id is not None:
            _measure(settings, camera_id, job_id=new_job_id(FRAMES_QUEUE, camera_id))
    return outcome


def _measure(settings: Settings, camera_id: str, *, job_id: str | None = None) -> str:
    return _gated(
        FRAMES_QUEUE, camera_id, lambda dispatcher, _: measure_pending(settings, dispatcher, camera_id), job_id=job_id
    )


@_recovers_from_outages
def measure_frames(camera_id: str) -> str:
    """Answer the camera's pending frames with its current calibration (service.frames.service)."""
    return _measure(get_settings(), camera_id)


@_recovers_from_outages
def calibrate_camera(camera_id: str, forced: bool = False) -> str:
    """Solve a camera on a capped, spatially balanced sample of its evidence (service.calibration.service)."""
    settings = get_settings()
    return _gated(
        CALIBRATION_QUEUE,
        camera_id,
        lambda dispatcher, ticket_forced: solve_camera(settings, dispatcher, camera_id, forced=forced or ticket_forced),
    )
