"""The RQ jobs: find the people in an image frame (`detect_people`), measure a camera's pending frames
(`measure_frames`) and solve a camera (`calibrate_camera`).

Measuring and solving are gated per camera (service.queue.CameraGate); all three are safe to run more than once
(RQ retries a job whose process died, see service.queue): a pose job stores people only while its frame is still
`detecting`, a measuring job commits each chunk's results with their violation events and webhook deliveries in
one transaction and takes only frames still pending, and a solve appends a version whose promotion to current
follows a rule (`at_least_as_supported`), not arrival order. A job that meets an unavailable database fails (RQ
retries it at once, in case it was a blip) and asks for the workers' recovery pass, which queues the work again
once the database answers (workers.recovery). Database transactions are kept short and never span a solve
or a batch's arithmetic: reads use deferred transactions, and on SQLite every writing transaction holds the one
write lock, which the API needs to keep storing frames.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from typing import ParamSpec, TypeVar

from rq import get_current_job
from sqlalchemy import Engine
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from service.dispatch import DispatchUnavailableError
from service.observability.logs import log_context
from service.observability.request_id import request_id_context
from service.queue import CALIBRATION_QUEUE, FRAMES_JOB_BUDGET_S, FRAMES_QUEUE, RedisDispatcher, new_job_id
from service.settings import Settings, get_settings
from service.store import CalibrationVersion, Camera, Frame, make_engine, make_session_factory
from service.store.db import is_database_unavailable
from service.store.models import clip_reason
from service.store.repository import (
    CalibrationValues,
    CameraNotFoundError,
    FrameOutcome,
    add_calibration,
    calibration_due,
    current_calibration,
    frame_image,
    frames_points,
    key_new_evidence,
    pending_frames,
    record_detection_failure,
    record_detections,
    record_frame_outcomes,
    sample_evidence,
)
from service.webhooks.events import calibration_deliveries, first_attempts, violation_deliveries
from workers.liveness import PACEMAKER
from workers.recovery import request_recovery

log = logging.getLogger(__name__)

# Outcomes the jobs return: RQ keeps them in logs, tests assert on them.
DONE = "done"
PENDING = "pending"
FAILED = "failed"
GONE = "gone"
SKIPPED = "skipped"

# Frames measured per read/compute/write round: large enough to amortise the transactions, small enough that
# the write lock is held for milliseconds.
FRAMES_CHUNK = 50
# People keyed for sampling per transaction: the first chunk, then as many as fit KEY_TRANSACTION_S. Keying shares
# index pages between people when a camera's index is small (100 000 people: 11 us per person), but with a million
# stored each person dirties pages of its own (41 us per person), and a fixed 2 000 would hold SQLite's one write
# lock for 80 ms while the API waits to store frames.
KEY_CHUNK = 2000
KEY_CHUNK_BOUNDS = (100, 20_000)
KEY_TRANSACTION_S = 0.02

_engines: dict[tuple[int, str], tuple[Engine, sessionmaker[Session], sessionmaker[Session]]] = {}
_P = ParamSpec("_P")
_R = TypeVar("_R")


def _factories(settings: Settings) -> tuple[sessionmaker[Session], sessionmaker[Session]]:
    """(writing, read-only) session factories on the configured database, one engine per process and URL.

    Keyed by pid: a forking worker's child must not reuse connections opened by its parent (SQLite and
    PostgreSQL connections are not fork-safe), so each process builds its own engine on first use.
    """
    key = (os.getpid(), settings.database_url)
    if key not in _engines:
        engine = make_engine(settings.database_url, busy_timeout_s=settings.database_busy_timeout_s)
        _engines[key] = (engine, make_session_factory(engine), make_session_factory(engine, read_only=True))
    return _engines[key][1], _engines[key][2]


def session_factory(settings: Settings | None = None) -> sessionmaker[Session]:
    """Writing sessions on the configured database (see `_factories`)."""
    return _factories(settings or get_settings())[0]


def read_session_factory(settings: Settings | None = None) -> sessionmaker[Session]:
    """Read-only sessions: on SQLite they neither wait for nor hold the write lock."""
    return _factories(settings or get_settings())[1]


def dispose_engines() -> None:
    """Close this process's connections (before forking, and in tests that swap databases)."""
    for (pid, _url), (engine, _factory, _read) in list(_engines.items()):
        if pid == os.getpid():
            engine.dispose()
    _engines.clear()


def preload() -> None:
    """Import the geometry now, so forked job processes inherit it instead of each importing scipy again."""
    import service.geometry
    import service.results  # noqa: F401


def preload_pose(settings: Settings) -> None:
    """Load the pose models now (a pose worker's first job should not pay ~0.5 s), and say loudly if they are
    missing; the worker still serves its other queues, and image frames fail with the same message."""
    from service.pose.model_files import ModelFilesError
    from service.pose.pipeline import load_pose_estimator

    try:
        estimator = load_pose_estimator(settings)
    except ModelFilesError as exc:
        log.error("pose models unavailable, image frames will fail until they are installed: %s", exc)
        return
    log.info("pose estimator %s loaded", estimator.name)


@contextmanager
def _transaction(settings: Settings) -> Iterator[Session]:
    with session_factory(settings)() as session, session.begin():
        yield session


def _announce(dispatcher: RedisDispatcher, deliveries: list[uuid.UUID]) -> None:
    """Queue committed webhook deliveries; if Redis fails now they stay pending in SQL for the sweep."""
    if not deliveries:
        return
    try:
        dispatcher.deliveries_due(first_attempts(deliveries))
    except DispatchUnavailableError as exc:
        log.warning("could not queue %d webhook deliveries (the sweep will): %s", len(deliveries), exc)


def _dispatcher(settings: Settings) -> RedisDispatcher:
    """The dispatcher on the Redis this job came from (else the configured one, for direct calls)."""
    job = get_current_job()
    if job is not None:
        return RedisDispatcher(job.connection)
    return RedisDispatcher.from_settings(settings)


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
                request_recovery(_dispatcher(get_settings()).connection)
            raise

    return run


def _gated(kind: str, camera_id: str, work: Callable[[RedisDispatcher, bool], str]) -> str:
    """Run `work(dispatcher, forced)` in the camera's slot for `kind`, then queue the re-run it owes.

    The gate guarantees one job of a kind per camera at a time; requests that arrived while this one ran become
    exactly one re-run, queued when this one finishes (whatever the outcome, hence `finally`). While the work
    runs, the process's heartbeat renews the slot (workers.liveness): if the process dies, the slot lapses within
    seconds and RQ's retry of this job takes it again.
    """
    dispatcher = _dispatcher(get_settings())
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


# --------------------------------------------------------------------------------------------------- pose


@_recovers_from_outages
def detect_people(frame_id: str) -> str:
    """Run pose inference on an image frame, store its people (the image goes unless the camera keeps images),
    then have the camera's pending frames measured.

    The estimator is loaded once per worker process (`load_pose_estimator` caches it). A picture that cannot be
    analysed, or missing model files, fail this frame with the reason, not the worker. Its log lines carry the
    request id of the request that posted the image.
    """
    settings = get_settings()
    frame_uuid = uuid.UUID(frame_id)
    with read_session_factory(settings)() as session:
        frame = session.get(Frame, frame_uuid)
        if frame is None:
            return GONE  # its camera was deleted after the frame was queued
        if frame.status != "detecting":
            # A duplicate run, or the retry of a run whose process died after storing the people and before it
            # asked for them to be measured: ask again (deduplicated per camera, so a duplicate costs nothing).
            if frame.status == "pending":
                _dispatcher(settings).measure_requested([frame.camera_id])
            return SKIPPED
        camera = session.get(Camera, frame.camera_id)
        image = frame_image(session, frame_uuid)
        data = None if image is None else image.data
        request_id = frame.request_id
    if camera is None:
        return GONE
    # The frame's own request id: also right for a job queued again by a starting worker, which has no meta.
    with request_id_context(request_id), log_context(camera_id=camera.id, frame_id=frame_id):
        return _detect(settings, frame_uuid, camera, data)


def _detect(settings: Settings, frame_uuid: uuid.UUID, camera: Camera, data: bytes | None) -> str:
    from service.images import ImageError, decode
    from service.keypoints import people_from_detections
    from service.observability.metrics import POSE_INFERENCE
    from service.pose.model_files import ModelFilesError
    from service.pose.pipeline import load_pose_estimator

    try:
        if data is None:
            raise ImageError("the frame's image is no longer stored")
        _header, bgr = decode(data, max_pixels=settings.max_image_pixels)
        estimator = load_pose_estimator(settings)
        started = time.perf_counter()
        found = estimator(bgr)
        inference_s = time.perf_counter() - started
    except (ImageError, ModelFilesError) as exc:
        log.warning("pose of frame %s of camera %s failed: %s", frame_uuid, camera.id, exc)
        with _transaction(settings) as session:
            record_detection_failure(session, frame_uuid, str(exc))
        return FAILED
    POSE_INFERENCE.labels(model=estimator.name).observe(inference_s)
    size = (camera.image_width_px, camera.image_height_px)
    people = people_from_detections(found[: settings.max_people_per_frame], size)
    with _transaction(settings) as session:
        stored = record_detections(session, frame_uuid, people, pose_model=estimator.name)
    if stored is None:
        return SKIPPED
    log.info(
        "frame %s of camera %s: %d people found in %.0f ms",
        frame_uuid,
        camera.id,
        len(people),
        inference_s * 1000,
        extra={"people": len(people), "inference_ms": round(inference_s * 1000, 1), "pose_model": estimator.name},
    )
    _dispatcher(settings).measure_requested([camera.id])
    return DONE


# --------------------------------------------------------------------------------------------------- frames


@_recovers_from_outages
def measure_frames(camera_id: str) -> str:
    """Answer the camera's pending frames with its current calibration, a chunk at a time; then nudge a solve.

    An uncalibrated camera leaves its frames pending: the first calibration asks for them to be measured, so they
    are answered then (recomputed, not dropped). After FRAMES_JOB_BUDGET_S the job stops and queues its own re-run,
    so a camera with a backlog shares the workers with the others.
    """
    settings = get_settings()
    return _gated(FRAMES_QUEUE, camera_id, lambda dispatcher, _: _measure_pending(settings, dispatcher, camera_id))


def _measure_pending(settings: Settings, dispatcher: RedisDispatcher, camera_id: str) -> str:
    from service.results import frame_outcome

    deadline = time.monotonic() + FRAMES_JOB_BUDGET_S
    outcome = DONE
    while True:
        with read_session_factory(settings)() as session:
            camera = session.get(Camera, camera_id)
            if camera is None:
                return GONE
            calibration = current_calibration(session, camera_id)
            if calibration is None:
                outcome = PENDING
                break
            frames = pending_frames(session, camera_id, limit=FRAMES_CHUNK)
            people = frames_points(session, [frame.id for frame in frames])
        outcomes = [frame_outcome(frame, people.get(frame.id, []), camera, calibration) for frame in frames]
        if outcomes:
            client_ids = {frame.id: frame.client_frame_id for frame in frames}
            outcomes, deliveries = store_outcomes(settings, camera, outcomes, client_ids)
            _announce(dispatcher, deliveries)
        for frame, measured in zip(frames, outcomes, strict=True):
            _log_measured(frame, measured)
        if len(frames) < FRAMES_CHUNK:
            break
        if time.monotonic() > deadline:
            dispatcher.request(FRAMES_QUEUE, camera_id)  # we are running: this schedules our re-run
            break
    if calibration_due(
        camera, min_people=settings.calibration_min_people, growth_factor=settings.calibration_growth_factor
    ):
        dispatcher.calibration_requested(camera_id, False)
    return outcome


def store_outcomes(
    settings: Settings, camera: Camera, outcomes: list[FrameOutcome], client_ids: dict[uuid.UUID, str | None]
) -> tuple[list[FrameOutcome], list[uuid.UUID]]:
    """Store a chunk's results with their violation events and webhook deliveries; (outcomes as stored, deliveries).

    One transaction for the chunk. If it fails for any reason but an unavailable database, each frame is stored in
    a transaction of its own, and a frame that fails alone is stored `failed` with the reason: one frame the store
    cannot take must not hold back its neighbours (a chunk that always failed would fail every retry of the job,
    and the camera's frames behind it would wait for ever).
    """
    try:
        with _transaction(settings) as session:
            record_frame_outcomes(session, outcomes)
            return outcomes, violation_deliveries(session, camera, outcomes, settings, client_frame_ids=client_ids)
    except Exception as exc:
        if isinstance(exc, SQLAlchemyError) and is_database_unavailable(exc):
            raise
        log.warning("a chunk of %d results failed (%r); storing them one at a time", len(outcomes), exc)
    stored, deliveries = [], []
    for outcome in outcomes:
        try:
            with _transaction(settings) as session:
                record_frame_outcomes(session, [outcome])
                deliveries += violation_deliveries(session, camera, [outcome], settings, client_frame_ids=client_ids)
        except Exception as exc:
            if isinstance(exc, SQLAlchemyError) and is_database_unavailable(exc):
                raise
            log.error("the result of frame %s could not be stored: %r", outcome.frame_id, exc, exc_info=exc)
            reason = clip_reason(f"its result could not be stored ({type(exc).__name__}: {exc})")
            outcome = replace(outcome, status=FAILED, result=None, violations=(), error=reason)
            with _transaction(settings) as session:
                record_frame_outcomes(session, [outcome])
        stored.append(outcome)
    return stored, deliveries


def _log_measured(frame: Frame, outcome: FrameOutcome) -> None:
    """One line per frame, under the request id that posted it: frames of many requests share a job."""
    fields = {"request_id": frame.request_id, "frame_id": str(frame.id), "frame_status": outcome.status}
    if outcome.status == "failed":
        log.warning("frame %s of camera %s failed: %s", frame.id, frame.camera_id, outcome.error, extra=fields)
        return
    fields.update(violations=len(outcome.violations), calibration_version=outcome.calibration_version)
    log.info(
        "frame %s of camera %s measured: %d people, %d violations",
        frame.id,
        frame.camera_id,
        frame.people,
        len(outcome.violations),
        extra=fields,
    )


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


@_recovers_from_outages
def calibrate_camera(camera_id: str, forced: bool = False) -> str:
    """Solve a camera on a capped, spatially balanced sample of its evidence; deduplicated per camera."""
    settings = get_settings()
    return _gated(
        CALIBRATION_QUEUE,
        camera_id,
        lambda dispatcher, ticket_forced: _solve(settings, dispatcher, camera_id, forced=forced or ticket_forced),
    )


def key_camera_evidence(settings: Settings, camera_id: str) -> int:
    """Key every person the camera stored since its last solve, in short transactions; returns how many."""
    total, chunk = 0, KEY_CHUNK
    while True:
        started = time.perf_counter()
        with _transaction(settings) as session:
            keyed = key_new_evidence(session, camera_id, limit=chunk)
        total += keyed
        if keyed < chunk:
            return total
        per_person_s = max(time.perf_counter() - started, 1e-6) / keyed
        low, high = KEY_CHUNK_BOUNDS
        chunk = min(max(int(KEY_TRANSACTION_S / per_person_s), low), high)


def _solve(settings: Settings, dispatcher: RedisDispatcher, camera_id: str, *, forced: bool) -> str:
    from service.geometry.evidence import solve_evidence

    with read_session_factory(settings)() as session:
        camera = session.get(Camera, camera_id)
        if camera is None:
            return GONE
        if not forced and not calibration_due(
            camera, min_people=settings.calibration_min_people, growth_factor=settings.calibration_growth_factor
        ):
            # Frames that arrived during the previous solve saw "due" and asked again; if that solve already
            # covered the growth, another one now would change nothing. Forced solves always run.
            return SKIPPED
    key_camera_evidence(settings, camera_id)
    with read_session_factory(settings)() as session:
        camera = session.get(Camera, camera_id)
        if camera is None:
            return GONE
        sample = sample_evidence(session, camera_id, cap=settings.calibration_sample_cap)
        evidence_count = int(camera.usable_evidence_count)
        image_size = (camera.image_width_px, camera.image_height_px)
        height_m, equal_focal, known_focal_px = camera.person_height_m, camera.equal_focal, camera.known_focal_px

    started = time.perf_counter()
    # The sample is already capped and balanced by the store; repeats (still people, a mannequin) count once.
    solve = solve_evidence(
        sample.tops_px, sample.bottoms_px, image_size, height_m, equal_focal=equal_focal, focal_px=known_focal_px
    )
    people_used = solve.people_used
    duration_s = time.perf_counter() - started
    if solve.calibration is not None:
        values = CalibrationValues.from_solution(
            solve.calibration, people_used=people_used, evidence_count=evidence_count, duration_s=duration_s
        )
    else:
        values = CalibrationValues.failure(
            clip_reason(solve.error or "no camera"),
            person_height_m=height_m,
            people_used=people_used,
            evidence_count=evidence_count,
            duration_s=duration_s,
        )

    try:
        with _transaction(settings) as session:
            current = current_calibration(session, camera_id)
            make_current = values.status == "ok" and (
                forced or current is None or at_least_as_supported(values, current)
            )
            record = add_calibration(session, camera_id, values, make_current=make_current, forced=forced)
            version = record.version
            waiting = make_current and bool(pending_frames(session, camera_id, limit=1))
            deliveries = calibration_deliveries(session, camera_id, record, current) if make_current else []
    except CameraNotFoundError:
        return GONE
    log.info(
        "camera %s: version %d %s%s (%d people sampled, %d after collapsing repeats, %d stored)",
        camera_id,
        version,
        values.status,
        ", current" if make_current else "",
        len(sample),
        people_used,
        evidence_count,
    )
    _announce(dispatcher, deliveries)
    if waiting:
        dispatcher.measure_requested([camera_id])
    if values.status != "ok":
        return FAILED
    return DONE if make_current else SKIPPED
