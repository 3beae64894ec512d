"""The RQ jobs: answer a frame (`process_frame`) and solve a camera (`calibrate_camera`).

Both are safe to run more than once: a frame's result is overwritten and its violation events replaced, and a
solve appends a version whose promotion to current follows a rule (`at_least_as_supported`), not arrival order.
Database transactions are kept short and never span a solve: on SQLite every transaction holds the one write
lock, and the API must keep storing frames while a camera is being solved.
"""

from __future__ import annotations

import logging
import math
import os
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager

from rq import get_current_job
from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from service.queue import RedisDispatcher, new_calibration_job_id
from service.settings import Settings, get_settings
from service.store import CalibrationVersion, Camera, Frame, make_engine, make_session_factory
from service.store.models import REASON_MAX_LENGTH
from service.store.repository import (
    CalibrationValues,
    CameraNotFoundError,
    add_calibration,
    calibration_due,
    current_calibration,
    pending_frames,
    sample_evidence,
    set_frame_result,
)

log = logging.getLogger(__name__)

# Outcomes the jobs return: RQ keeps them in logs, tests assert on them.
DONE = "done"
PENDING = "pending"
FAILED = "failed"
GONE = "gone"
SKIPPED = "skipped"

_engines: dict[tuple[int, str], tuple[Engine, sessionmaker[Session]]] = {}


def session_factory(settings: Settings | None = None) -> sessionmaker[Session]:
    """Sessions on the configured database, one engine per process and URL.

    Keyed by pid: a forking worker's child must not reuse connections opened by its parent (SQLite and
    PostgreSQL connections are not fork-safe), so each process builds its own engine on first use.
    """
    settings = settings or get_settings()
    key = (os.getpid(), settings.database_url)
    if key not in _engines:
        engine = make_engine(settings.database_url, busy_timeout_s=settings.database_busy_timeout_s)
        _engines[key] = (engine, make_session_factory(engine))
    return _engines[key][1]


def dispose_engines() -> None:
    """Close this process's connections (before forking, and in tests that swap databases)."""
    for (pid, _url), (engine, _factory) in list(_engines.items()):
        if pid == os.getpid():
            engine.dispose()
    _engines.clear()


def preload() -> None:
    """Import the geometry now, so forked job processes inherit it instead of each importing scipy again."""
    import service.geometry
    import service.results  # noqa: F401


@contextmanager
def _transaction(settings: Settings) -> Iterator[Session]:
    with session_factory(settings)() as session, session.begin():
        yield session


def _dispatcher(settings: Settings) -> RedisDispatcher:
    """The dispatcher on the Redis this job came from (else the configured one, for direct calls)."""
    job = get_current_job()
    if job is not None:
        return RedisDispatcher(job.connection)
    return RedisDispatcher.from_settings(settings)


# --------------------------------------------------------------------------------------------------- frames


def process_frame(frame_id: str) -> str:
    """Answer one stored frame with the camera's current calibration, then nudge calibration if it is due.

    An uncalibrated camera leaves the frame pending: the first calibration re-enqueues every pending frame of
    its camera, so the frame is answered then (recomputed, not dropped). A frame already answered with the
    current version is left alone, which makes duplicate deliveries cheap.
    """
    settings = get_settings()
    frame_uuid = uuid.UUID(frame_id)
    with _transaction(settings) as session:
        frame = session.get(Frame, frame_uuid)
        if frame is None:
            return GONE  # its camera was deleted after the frame was queued
        camera = session.get(Camera, frame.camera_id)
        if camera is None:
            return GONE
        camera_id = camera.id
        due = calibration_due(
            camera, min_people=settings.calibration_min_people, growth_factor=settings.calibration_growth_factor
        )
        calibration = current_calibration(session, camera_id)
        if calibration is None:
            outcome = PENDING
        elif frame.status == "done" and frame.calibration_version == calibration.version:
            outcome = DONE
        else:
            outcome = _answer(session, frame, camera, calibration)
    if due:
        _dispatcher(settings).calibration_requested(camera_id, False)
    return outcome


def _answer(session: Session, frame: Frame, camera: Camera, calibration: CalibrationVersion) -> str:
    """Store the frame's result and its violation events in the caller's transaction (atomically)."""
    from service.results import process_frame as measure_frame

    try:
        with session.begin_nested():
            measure_frame(session, frame, camera, calibration)
    except (ValueError, ArithmeticError) as exc:
        # Bad stored data for this one frame must not fail the queue: the frame records why it has no answer.
        log.warning("frame %s of camera %s failed: %s", frame.id, camera.id, exc)
        set_frame_result(
            session, frame.id, status="failed", calibration_version=calibration.version, error=_reason(str(exc))
        )
        return FAILED
    return DONE


# --------------------------------------------------------------------------------------------------- calibration


def _relative_focal_std(fx_px: float | None, fx_std_px: float | None) -> float:
    if fx_px is None or fx_std_px is None or not (math.isfinite(fx_std_px) and fx_px > 0):
        return math.inf
    return fx_std_px / fx_px


def _normal_std_deg(value: float | None) -> float:
    return value if value is not None and math.isfinite(value) else math.inf


def at_least_as_supported(new: CalibrationValues, current: CalibrationVersion) -> bool:
    """Whether a new solve may replace the current version without being forced.

    Support is what the solve rests on: the people it kept as inliers, and how tightly they pin the camera
    (relative focal-length and ground-normal uncertainty). A new solve qualifies when it keeps at least as many
    inliers, or when it is at least as precise on both focal length and normal. It is refused only when it is
    worse on both counts, i.e. fewer people agree with it *and* it is less certain: typically a sample that hit
    a bad batch of detections, which should not silently overwrite a good calibration. Inlier counts alone are
    not enough, because once evidence exceeds the sample cap every solve uses about the same number of people.
    """
    if new.status != "ok":
        return False
    if new.inliers >= current.inliers:
        return True
    new_fx = _relative_focal_std(new.fx_px, new.fx_std_px)
    current_fx = _relative_focal_std(current.fx_px, current.fx_std_px)
    return new_fx <= current_fx and _normal_std_deg(new.normal_std_deg) <= _normal_std_deg(current.normal_std_deg)


def calibrate_camera(camera_id: str, forced: bool = False) -> str:
    """Solve a camera on a capped, spatially balanced sample of its evidence; deduplicated per camera.

    The CalibrationGate in Redis guarantees one solve per camera at a time; requests that arrived while this one
    ran become exactly one re-run, queued when this one finishes (whatever the outcome, hence `finally`).
    """
    settings = get_settings()
    dispatcher = _dispatcher(settings)
    job = get_current_job()
    job_id = job.id if job is not None else new_calibration_job_id(camera_id)
    ticket = dispatcher.gate.start(camera_id, job_id)
    if not ticket.run:
        return SKIPPED  # another solve of this camera is running; the gate has scheduled a re-run after it
    try:
        outcome = _solve(settings, dispatcher, camera_id, forced=forced or ticket.forced)
    finally:
        next_job_id = new_calibration_job_id(camera_id)
        if dispatcher.gate.finish(camera_id, job_id, next_job_id):
            dispatcher.enqueue_calibration(camera_id, next_job_id)
    return outcome


def _solve(settings: Settings, dispatcher: RedisDispatcher, camera_id: str, *, forced: bool) -> str:
    from service.geometry import CalibrationError, calibrate

    with _transaction(settings) as session:
        camera = session.get(Camera, camera_id)
        if camera is None:
            return GONE
        if not forced and not calibration_due(
            camera, min_people=settings.calibration_min_people, growth_factor=settings.calibration_growth_factor
        ):
            # Frames that arrived during the previous solve saw "due" and asked again; if that solve already
            # covered the growth, another one now would change nothing. Forced solves always run.
            return SKIPPED
        sample = sample_evidence(session, camera_id, cap=settings.calibration_sample_cap)
        evidence_count = int(camera.usable_evidence_count)
        image_size = (camera.image_width_px, camera.image_height_px)
        height_m, equal_focal, known_focal_px = camera.person_height_m, camera.equal_focal, camera.known_focal_px

    started = time.perf_counter()
    try:
        solution = calibrate(
            sample.tops_px,
            sample.bottoms_px,
            image_size,
            height_m,
            equal_focal=equal_focal,
            focal_px=known_focal_px,
        )
        values = CalibrationValues.from_solution(
            solution, people_used=len(sample), evidence_count=evidence_count, duration_s=time.perf_counter() - started
        )
    except CalibrationError as exc:
        values = CalibrationValues.failure(
            _reason(str(exc)),
            person_height_m=height_m,
            people_used=len(sample),
            evidence_count=evidence_count,
            duration_s=time.perf_counter() - started,
        )

    try:
        with _transaction(settings) as session:
            current = current_calibration(session, camera_id)
            make_current = values.status == "ok" and (
                forced or current is None or at_least_as_supported(values, current)
            )
            record = add_calibration(session, camera_id, values, make_current=make_current, forced=forced)
            version = record.version
            waiting = []
            if make_current:
                waiting = [(frame.camera_id, frame.id) for frame in pending_frames(session, camera_id)]
    except CameraNotFoundError:
        return GONE
    log.info(
        "camera %s: version %d %s%s (%d people sampled, %d stored)",
        camera_id,
        version,
        values.status,
        ", current" if make_current else "",
        len(sample),
        evidence_count,
    )
    if waiting:
        dispatcher.frames_pending(waiting)
    if values.status != "ok":
        return FAILED
    return DONE if make_current else SKIPPED


def _reason(message: str) -> str:
    """Stored reasons are capped by the schema; keep the start, which says what went wrong."""
    return message if len(message) <= REASON_MAX_LENGTH else message[: REASON_MAX_LENGTH - 3] + "..."
