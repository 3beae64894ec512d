"""Frames as a process: the checks a posted frame's people pass, measuring stored frames, and their outcomes.

`measure_pending` is what the measuring job runs (workers.jobs.measure_frames is its RQ adapter); the routes use
`people_for_camera`, and the synchronous distances route `compute_frame_result`.
A chunk's frames are measured together (`frame_outcomes`): one geometric pass for all their people.
"""

from __future__ import annotations

import logging
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import replace
from functools import partial
from typing import TYPE_CHECKING, Any

from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session

from service.calibration import moves
from service.calibration.camera_model import calibration_from_version
from service.calibration.repository import current_calibration, movement_state
from service.calibration.service import may_be_due, solve_due
from service.domain import DONE, FAILED, GONE, PENDING, FrameOutcome, PersonIn, StoredCentres
from service.frames.keypoints import drop_posted_repeats, person_from_centres, person_from_keypoints
from service.frames.measure import FrameComputation, measure_frames
from service.frames.repository import frames_points, pending_frames, record_frame_outcomes
from service.frames.schemas import PersonObservation
from service.frames.static import StaticMarks, mark_keypoint_frames, record_static_marks, spots_seen
from service.geometry import Calibration
from service.http.problems import ProblemError, field_errors
from service.observability.logs import JOBS_LOGGER
from service.settings import Settings
from service.store.db import EncodedJSON, is_database_unavailable
from service.store.models import CalibrationVersion, Camera, Frame, clip_reason
from service.store.sessions import read_session_factory, transaction
from service.webhooks.events import announce, violation_deliveries

if TYPE_CHECKING:
    from service.queue import RedisDispatcher

log = logging.getLogger(JOBS_LOGGER)

# Keypoints may lie somewhat outside the image (pose models extrapolate cut-off limbs), but not absurdly far:
# anything beyond half an image width/height past an edge is a unit or coordinate-system mistake.
COORDINATE_MARGIN_FRACTION = 0.5
# Frames measured per read/compute/write round: large enough to amortise the transactions, small enough that
# the write lock is held for milliseconds (the API's frame writers queue behind it). Under `posemetry bench load`,
# runs alternating: 50 gave a keypoint POST p99 of 153-173 ms, 25 gave 112-127 ms with measuring as far behind
# (keypoint frames answered 11-15 s after their post, p50, against 7-12), 12 gave 93 and 173 ms with measuring
# further behind (18-20 s).
FRAMES_CHUNK = 25
# A measuring job stops taking new chunks after FRAMES_JOB_BUDGET_S (and queues its own re-run), so one busy
# camera cannot hold a worker while other cameras wait.
FRAMES_JOB_BUDGET_S = 5


def people_for_camera(people: Sequence[PersonObservation], camera: Camera, settings: Settings) -> list[PersonIn]:
    """Posted people as store rows, after the checks that need the camera and the settings.

    Too many people is 413 (settings.max_people_per_frame). Coordinates more than half an image beyond an edge
    are 422 with each bad field's location, whatever their score: pose models put the joints they did not find
    at placeholders inside or next to the image (0, 0 or -1, -1), never half an image away, and a number that
    passes here must be one the store can keep (a score-0 keypoint at 1e39 once failed a whole write batch).
    """
    if len(people) > settings.max_people_per_frame:
        raise ProblemError(
            413,
            "too-many-people",
            f"{len(people)} people in one frame; at most {settings.max_people_per_frame} are accepted "
            "(setting max_people_per_frame).",
        )
    width, height = size = (camera.image_width_px, camera.image_height_px)
    # The accepted band per axis. The loops below compare inline: 340 points per frame, where a function call per
    # point was a quarter of the event loop's time per frame.
    low_x, high_x = -COORDINATE_MARGIN_FRACTION * width, (1 + COORDINATE_MARGIN_FRACTION) * width
    low_y, high_y = -COORDINATE_MARGIN_FRACTION * height, (1 + COORDINATE_MARGIN_FRACTION) * height
    errors: list[dict[str, Any]] = []

    def far_outside(loc: list[Any], x: float, y: float) -> None:
        errors.append(
            {
                "loc": ["body", "people", *loc],
                "msg": f"point ({x:g}, {y:g}) px is far outside the camera's {width}x{height} image",
                "type": "coordinate_out_of_image",
            }
        )

    rows = []
    for index, person in enumerate(people):
        if person.keypoints is not None:
            for k, (x, y, _score) in enumerate(person.keypoints):
                if not (low_x <= x <= high_x and low_y <= y <= high_y):
                    far_outside([index, "keypoints", k], x, y)
            rows.append(person_from_keypoints(person.keypoints, size, track_id=person.track_id))
        else:
            for name in ("shoulder", "ankle"):
                point = getattr(person, name)
                if point is not None and not (low_x <= point[0] <= high_x and low_y <= point[1] <= high_y):
                    far_outside([index, name], *point)
            rows.append(person_from_centres(person.shoulder, person.ankle, size, track_id=person.track_id))
    if errors:
        fields = field_errors(errors)
        more = f" (and {len(fields) - 1} more)" if len(fields) > 1 else ""
        detail = f"Invalid request: {fields[0]['field']}: {fields[0]['msg']}{more}"
        raise ProblemError(422, "validation-error", detail, errors=fields)
    return drop_posted_repeats(rows)


def compute_frame_result(
    people: Sequence[StoredCentres | PersonIn],
    calibration: CalibrationVersion,
    *,
    image_size_px: tuple[int, int],
    distance_threshold_m: float,
    camera: Calibration | None = None,
) -> FrameComputation:
    """A frame's result with a stored calibration version (see `measure_people`); `camera` is the version as the
    geometry's Calibration when the caller already has it (a measuring job builds it once per chunk, not per frame)."""
    return compute_frame_results(
        [people], calibration, image_size_px=image_size_px, distance_threshold_m=distance_threshold_m, camera=camera
    )[0]


def compute_frame_results(
    frames: Sequence[Sequence[StoredCentres | PersonIn]],
    calibration: CalibrationVersion,
    *,
    image_size_px: tuple[int, int],
    distance_threshold_m: float,
    camera: Calibration | None = None,
) -> list[FrameComputation]:
    """Several frames' results (each frame's people), measured in one pass (service.frames.measure.measure_frames)."""
    return measure_frames(
        frames,
        camera if camera is not None else calibration_from_version(calibration, image_size_px),
        distance_threshold_m=distance_threshold_m,
        calibration_version=calibration.version,
        noise_px=calibration.noise_px or 0.0,
        calibration_grade=calibration.quality_grade,
    )


def frame_outcomes(
    frames: Sequence[Frame],
    people: Sequence[Sequence[StoredCentres]],
    camera: Camera,
    calibration: CalibrationVersion,
    geometry: Calibration | None = None,
) -> list[FrameOutcome]:
    """Stored frames (`people`: each frame's) measured together with `calibration`, in one geometric pass: each
    done with its result, or failed with the reason (no I/O).

    Bad stored data for one frame (a person the geometry refuses) fails that frame, not the worker's batch: when
    the pass over the chunk raises, the frames are measured one by one, so the error lands on its own frame.
    """
    try:
        computations = compute_frame_results(
            people,
            calibration,
            image_size_px=(camera.image_width_px, camera.image_height_px),
            distance_threshold_m=camera.distance_threshold_m,
            camera=geometry,
        )
    except (ValueError, ArithmeticError) as exc:
        if len(frames) > 1:
            return [
                outcome
                for one, its_people in zip(frames, people, strict=True)
                for outcome in frame_outcomes([one], [its_people], camera, calibration, geometry)
            ]
        return [
            FrameOutcome(
                frame.id, frame.camera_id, frame.timestamp, "failed", calibration.version, error=clip_reason(str(exc))
            )
            for frame in frames
        ]
    return [
        FrameOutcome(
            frame.id,
            frame.camera_id,
            frame.timestamp,
            "done",
            calibration.version,
            result=EncodedJSON(computation.result_json()),
            violations=computation.violations,
        )
        for frame, computation in zip(frames, computations, strict=True)
    ]


def measure_pending(settings: Settings, dispatcher: RedisDispatcher, camera_id: str) -> str:
    """Answer the camera's pending frames with its current calibration, a chunk at a time; then nudge a solve.

    Each chunk is first shown to the movement test (service.calibration.moves): when it finds that the camera
    moved, the frames from the move on stay pending for the new epoch's calibration and the rest are measured.
    Keypoint frames meet the camera's static spots here (service.frames.static): people standing on one raise no
    violation and leave the evidence, in the chunk's transaction.
    An uncalibrated camera leaves its frames pending: the first calibration asks for them to be measured, so they
    are answered then (recomputed, not dropped). After FRAMES_JOB_BUDGET_S this stops and queues its own re-run,
    so a camera with a backlog shares the workers with the others. Each chunk's results are committed with their
    violation events and webhook deliveries in one transaction, and only frames still pending are taken, so
    measuring twice (a retried job) counts nothing twice.
    """
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
            stored_test = movement_state(session, camera_id) if frames else None
            keypoint_frames = any(frame.source == "keypoints" for frame in frames)
            spots = spots_seen(session, camera_id, settings.static_after_s) if keypoint_frames else None
        watched = moves.watch(calibration, stored_test, frames, people) if frames else None
        moved_at = None if watched is None else watched.moved_at
        measured = [frame for frame in frames if moved_at is None or frame.timestamp < moved_at]
        marks = StaticMarks() if spots is None else mark_keypoint_frames(spots, measured, people)
        geometry = _geometry(calibration, camera) if measured else None
        chunk_people = [marks.people(frame.id, people.get(frame.id, [])) for frame in measured]
        outcomes = frame_outcomes(measured, chunk_people, camera, calibration, geometry)
        if watched is not None:
            client_ids = {frame.id: frame.client_frame_id for frame in measured}
            keep_watch = partial(moves.keep_watch, camera=camera, calibration=calibration, watched=watched)
            also = partial(_chunk_state, camera=camera, marks=marks, settings=settings, keep_watch=keep_watch)
            outcomes, deliveries = store_outcomes(settings, camera, outcomes, client_ids, also)
            announce(dispatcher, deliveries)
        for frame, answered in zip(measured, outcomes, strict=True):
            _log_measured(frame, answered)
        if moved_at is not None:
            outcome = PENDING  # uncalibrated in the new epoch: its first solve has the frames measured
            break
        if len(frames) < FRAMES_CHUNK:
            break
        if time.monotonic() > deadline:
            dispatcher.measure_requested([camera_id])  # we are running: this schedules our re-run
            break
    if _solve_due(settings, camera):
        dispatcher.calibration_requested(camera_id, False)
    return outcome


def _chunk_state(
    session: Session,
    *,
    camera: Camera,
    marks: StaticMarks,
    settings: Settings,
    keep_watch: Callable[[Session], list[uuid.UUID]],
) -> list[uuid.UUID]:
    """What a chunk's transaction stores beside its results: the static spots' share, then the movement test's."""
    record_static_marks(session, camera, marks, settings.static_after_s)
    return keep_watch(session)


def _solve_due(settings: Settings, camera: Camera) -> bool:
    """Whether the camera is due a solve (service.calibration.service.next_solve_at); most jobs learn that it is
    not without a read."""
    if not may_be_due(camera, settings):
        return False
    with read_session_factory(settings)() as session:
        return solve_due(session, camera, settings)


def _geometry(calibration: CalibrationVersion, camera: Camera) -> Calibration | None:
    """The chunk's calibration as the geometry's Calibration, built once for all its frames (per frame it was
    2.5 % of a measuring job's time); None when the stored version cannot be one, so each frame fails with the
    reason as before."""
    try:
        return calibration_from_version(calibration, (camera.image_width_px, camera.image_height_px))
    except (ValueError, ArithmeticError):
        return None


def store_outcomes(
    settings: Settings,
    camera: Camera,
    outcomes: list[FrameOutcome],
    client_ids: dict[uuid.UUID, str | None],
    also: Callable[[Session], list[uuid.UUID]] | None = None,
) -> tuple[list[FrameOutcome], list[uuid.UUID]]:
    """Store a chunk's results with their violation events and webhook deliveries; (outcomes as stored, deliveries).

    One transaction for the chunk, which `also` joins (the movement test's state, or the move it found). If it fails
    for any reason but an unavailable database, each frame is stored in a transaction of its own (and `also` in one
    after them), and a frame that fails alone is stored `failed` with the reason: one frame the store cannot take
    must not hold back its neighbours (a chunk that always failed would fail every retry of the job, and the
    camera's frames behind it would wait for ever).
    """
    try:
        with transaction(settings) as session:
            record_frame_outcomes(session, outcomes)
            deliveries = []
            if outcomes:
                deliveries = violation_deliveries(session, camera, outcomes, settings, client_frame_ids=client_ids)
            return outcomes, deliveries + (also(session) if also is not None else [])
    except Exception as exc:
        if isinstance(exc, SQLAlchemyError) and is_database_unavailable(exc):
            raise
        log.warning("a chunk of %d results failed (%r); storing them one at a time", len(outcomes), exc)
    stored, deliveries = [], []
    for outcome in outcomes:
        try:
            with transaction(settings) as session:
                record_frame_outcomes(session, [outcome])
                deliveries += violation_deliveries(session, camera, [outcome], settings, client_frame_ids=client_ids)
        except Exception as exc:
            if isinstance(exc, SQLAlchemyError) and is_database_unavailable(exc):
                raise
            log.error("the result of frame %s could not be stored: %r", outcome.frame_id, exc, exc_info=exc)
            reason = clip_reason(f"its result could not be stored ({type(exc).__name__}: {exc})")
            outcome = replace(outcome, status=FAILED, result=None, violations=(), error=reason)
            with transaction(settings) as session:
                record_frame_outcomes(session, [outcome])
        stored.append(outcome)
    if also is not None:
        with transaction(settings) as session:
            deliveries += also(session)
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
