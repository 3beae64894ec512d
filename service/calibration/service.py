"""A camera's calibration as a process: when a solve is due, solving on a sample of the stored evidence, and
whether the new version becomes current.

`solve_camera` is what the calibration job runs (workers.jobs.calibrate_camera is its RQ adapter). Database
transactions are kept short and never span the solve itself: reads use read-only sessions, and on SQLite every
writing transaction holds the one write lock, which the API needs to keep storing frames. A solve appends a
version whose promotion to current follows a rule (`at_least_as_supported`), not arrival order, so a solve that
runs twice (RQ retries a job whose process died) never makes things worse.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Collection, Mapping
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from service.calibration import evidence
from service.calibration.camera_model import model_record, problem_for, quality_record
from service.calibration.repository import add_calibration, current_calibration
from service.cameras.repository import CameraNotFoundError, camera_counters
from service.domain import DONE, FAILED, GONE, SKIPPED, CalibrationValues, CameraCounters
from service.frames.repository import pending_frames
from service.geometry import Calibration, CalibrationError, CalibrationProblem
from service.geometry.evidence import EvidenceSolve, solve_evidence
from service.geometry.quality import MIN_INDIVIDUALS
from service.observability.logs import JOBS_LOGGER
from service.settings import Settings
from service.store.models import CalibrationVersion, Camera, clip_reason
from service.store.sessions import read_session_factory, transaction
from service.webhooks.events import announce, calibration_deliveries

if TYPE_CHECKING:
    from service.dispatch import Dispatcher
    from service.queue import RedisDispatcher

log = logging.getLogger(JOBS_LOGGER)

# People keyed for sampling per transaction: the first chunk, then as many as fit KEY_TRANSACTION_S. Keying shares
# index pages between people when a camera's index is small (100 000 people: 11 us per person), but with a million
# stored each person dirties pages of its own (41 us per person), and a fixed 2 000 would hold SQLite's one write
# lock for 80 ms while the API waits to store frames. Under `posemetry bench load`, two pairs of runs alternating:
# 10 ms transactions gave a keypoint POST p99 of 119-123 ms and due solves 8.0-9.0 s (p99), 20 ms gave 130-191 ms
# and 10.5-11.0 s.
KEY_CHUNK = 2000
KEY_CHUNK_BOUNDS = (100, 20_000)
KEY_TRANSACTION_S = 0.01


def evidence_for_next_solve(
    camera: Camera,
    *,
    min_people: int,
    growth_factor: float,
    refresh_factor: float | None = None,
    sample_cap: int | None = None,
    converged: bool = False,
) -> int:
    """Usable evidence at which the next solve is due: min_people first, then growth_factor x the last solve's
    while more people still sharpen the answer, and refresh_factor x once they no longer do.

    A solve's sigma shrinks as 1/sqrt of the people it rests on, so each growth by growth_factor buys a
    sqrt(growth_factor) sharper answer, until either (a) the last solve already used a full sample (`sample_cap`:
    more stored evidence no longer enlarges the sample, so a re-solve draws an equally precise answer), or (b) the
    camera has converged (`converged`, see `has_converged`: the last solve did not move the answer beyond its
    sigma). From then on a re-solve only refreshes the sample: at refresh_factor x (4: three quarters of a new
    sample are people the last solve never saw), while the movement test watches every frame for a change of
    the camera (service.calibration.moves)."""
    last = camera.evidence_at_last_solve
    if last <= 0:
        return min_people
    settled = converged or (sample_cap is not None and last >= sample_cap)
    factor = refresh_factor if settled and refresh_factor is not None else growth_factor
    return max(min_people, math.ceil(factor * last))


# A solve has converged when it moved none of focal length, ground normal and camera height by more than this many
# of its own sigmas from the solve before it, and is graded good.
CONVERGED_SIGMAS = 1.0


def has_converged(session: Session, camera: Camera) -> bool:
    """Whether the camera's last two successful solves of its epoch agree within the newer one's sigma, the newer
    graded good: the evidence added between them did not move the answer beyond its sigma, so the same growth
    again (which moves it less: by sigma x sqrt(1 - 1/growth_factor) on honest sigmas) will not either. A solve
    that moves re-arms the fast schedule."""
    stmt = (
        select(CalibrationVersion)
        .where(
            CalibrationVersion.camera_id == camera.id,
            CalibrationVersion.epoch == camera.epoch,
            CalibrationVersion.status == "ok",
        )
        .order_by(CalibrationVersion.version.desc())
        .limit(2)
    )
    versions = list(session.scalars(stmt))
    if len(versions) < 2 or versions[0].quality_grade != "good":
        return False
    return solves_agree(versions[0], versions[1])


def solves_agree(newer: CalibrationVersion, older: CalibrationVersion, sigmas: float = CONVERGED_SIGMAS) -> bool:
    """Whether `older` lies within `sigmas` of `newer`'s own sigma in focal length, normal direction and height."""
    values = (newer.fx_px, newer.fx_std_px, older.fx_px, newer.normal_std_deg, newer.rho_m, newer.rho_std_m)
    if any(v is None or not math.isfinite(v) for v in (*values, older.rho_m)):
        return False
    normals = np.array(
        [[newer.normal_x, newer.normal_y, newer.normal_z], [older.normal_x, older.normal_y, older.normal_z]], float
    )
    if not np.all(np.isfinite(normals)):
        return False
    cosine = float(normals[0] @ normals[1] / (np.linalg.norm(normals[0]) * np.linalg.norm(normals[1])))
    angle_deg = math.degrees(math.acos(min(1.0, max(-1.0, cosine))))
    return (
        abs(newer.fx_px - older.fx_px) <= sigmas * newer.fx_std_px  # type: ignore[operator]
        and angle_deg <= sigmas * newer.normal_std_deg  # type: ignore[operator]
        and abs(newer.rho_m - older.rho_m) <= sigmas * newer.rho_std_m  # type: ignore[operator]
    )


def _schedule(settings: Settings) -> dict[str, Any]:
    return {
        "min_people": settings.calibration_min_people,
        "growth_factor": settings.calibration_growth_factor,
        "refresh_factor": settings.calibration_refresh_factor,
        "sample_cap": settings.calibration_sample_cap,
    }


def next_solve_at(session: Session, camera: Camera, settings: Settings) -> int:
    """The usable evidence at which the camera's next solve is due, on the settings' schedule (reads the last two
    solves when convergence decides it)."""
    last = camera.evidence_at_last_solve
    if last <= 0 or last >= settings.calibration_sample_cap:
        return evidence_for_next_solve(camera, **_schedule(settings))
    return evidence_for_next_solve(camera, **_schedule(settings), converged=has_converged(session, camera))


def may_be_due(camera: Camera, settings: Settings) -> bool:
    """False when no schedule could make the camera due yet (no read needed): what a measuring job asks first."""
    return _may_be_due(camera.usable_evidence_count, camera.evidence_at_last_solve, settings)


def _may_be_due(evidence: int, evidence_at_last_solve: int, settings: Settings) -> bool:
    factor = min(settings.calibration_growth_factor, settings.calibration_refresh_factor)
    return evidence_at_last_solve <= 0 or evidence >= max(
        settings.calibration_min_people, factor * evidence_at_last_solve
    )


def solve_due(session: Session, camera: Camera, settings: Settings) -> bool:
    """Whether the camera is due a solve now (next_solve_at reached)."""
    return camera.usable_evidence_count >= next_solve_at(session, camera, settings)


class DueSolves:
    """Asks for a camera's solve as soon as the evidence that makes it due is stored (the API's after-commit step).

    Otherwise the ask came from the camera's next measuring job, and under load the measuring queue runs seconds to
    tens of seconds behind the posts (`posemetry bench load`: a camera's measuring job ran every ~20 s), all of it
    added to the wait of a solve that was due. Each write batch's cameras cost one light read of their counters;
    the evidence at which each camera's next solve is due (`next_solve_at`, which may read the last two versions)
    is kept until a solve, a reset or a move changes the camera's `evidence_at_last_solve` or epoch, and a camera
    is asked for once per such state. A lost ask, or a forced solve that changed the schedule without moving the
    counter, costs only time: the measuring job and the workers' recovery pass ask too. Called from one thread
    (the frame writer's after-commit thread). The batch's own transaction hands over the counters it left
    (ingest.add_keypoint_frames), so for a batch whose cameras are all in it no statement runs (a session connects
    only when one does) unless a camera's next target must be computed.
    """

    def __init__(self, settings: Settings, read_sessions: sessionmaker[Session], dispatcher: Dispatcher) -> None:
        self.settings, self.read_sessions, self.dispatcher = settings, read_sessions, dispatcher
        # camera -> ((epoch, evidence_at_last_solve), the evidence its next solve is due at, asked for already)
        self._schedule: dict[str, tuple[tuple[int, int], int, bool]] = {}

    def __call__(self, camera_ids: Collection[str], counters: Mapping[str, CameraCounters] | None = None) -> list[str]:
        """Ask for the solves these cameras are due; returns the cameras asked for. `counters`: those the write
        transaction left (the cameras not in it are read)."""
        if not camera_ids:
            return []
        given = counters or {}
        due = []
        with self.read_sessions() as session:
            state_of = {camera_id: given[camera_id] for camera_id in camera_ids if camera_id in given}
            missing = set(camera_ids) - set(state_of)
            if missing:
                state_of.update(camera_counters(session.connection(), missing))
            for camera_id, now in sorted(state_of.items()):
                if not _may_be_due(now.usable_evidence_count, now.evidence_at_last_solve, self.settings):
                    continue
                state = (now.epoch, now.evidence_at_last_solve)
                known = self._schedule.get(camera_id)
                if known is None or known[0] != state:
                    camera = session.get(Camera, camera_id)
                    if camera is None:
                        continue
                    known = (state, next_solve_at(session, camera, self.settings), False)
                    self._schedule[camera_id] = known
                if not known[2] and now.usable_evidence_count >= known[1]:
                    due.append(camera_id)
        for camera_id in due:
            self.dispatcher.calibration_requested(camera_id, False)
            state, target, _ = self._schedule[camera_id]
            self._schedule[camera_id] = (state, target, True)
        return due


def people_needed(session: Session, camera: Camera, settings: Settings) -> int:
    """Usable people still missing before the next solve is due."""
    return max(0, next_solve_at(session, camera, settings) - camera.usable_evidence_count)


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


def too_thin(cal: Calibration) -> str | None:
    """Why a solve rests on too few distinct people to be reported as a calibration (None: it does not).

    The geometry refuses a camera only when the people leave the focal length undetermined; between that and
    MIN_INDIVIDUALS it grades the solve `unreliable`. The service goes further for thin evidence: a posterior
    from a dozen people is far from Gaussian, so its sigma cannot be trusted either, and such a camera is not
    reported as calibrated at all (the solve is kept in the history as failed, and frames wait). Other reasons
    for `unreliable` (people at one distance, in a corner of the view, a wide predicted error) leave a
    calibration that measures, with its wide sigma, but raises no alerts.
    """
    individuals = cal.individuals or cal.num_inliers
    if individuals >= MIN_INDIVIDUALS:
        return None
    return (
        f"too thin to calibrate: only {individuals} distinct people agree (at least {MIN_INDIVIDUALS} are needed); "
        "more people, spread over the view and over distances, or the camera's known intrinsics"
    )


def key_camera_evidence(settings: Settings, camera_id: str) -> int:
    """Key every person the camera stored since its last solve, in short transactions; returns how many."""
    total, chunk = 0, KEY_CHUNK
    while True:
        started = time.perf_counter()
        with transaction(settings) as session:
            keyed = evidence.key_new_evidence(session, camera_id, limit=chunk)
        total += keyed
        if keyed < chunk:
            return total
        per_person_s = max(time.perf_counter() - started, 1e-6) / keyed
        low, high = KEY_CHUNK_BOUNDS
        chunk = min(max(int(KEY_TRANSACTION_S / per_person_s), low), high)


def solve_camera(settings: Settings, dispatcher: RedisDispatcher, camera_id: str, *, forced: bool) -> str:
    """Solve the camera on a capped, spatially balanced sample of its evidence, unless no solve is due (a forced
    one always is); store the version, make it current by the rule, raise its webhooks and have waiting frames
    measured. Returns the job's outcome: done, failed (no camera found), skipped (kept, not current) or gone."""
    with read_session_factory(settings)() as session:
        camera = session.get(Camera, camera_id)
        if camera is None:
            return GONE
        if not forced and not solve_due(session, camera, settings):
            # Frames that arrived during the previous solve saw "due" and asked again; if that solve already
            # covered the growth, another one now would change nothing. Forced solves always run.
            return SKIPPED
    key_camera_evidence(settings, camera_id)
    with read_session_factory(settings)() as session:
        camera = session.get(Camera, camera_id)
        if camera is None:
            return GONE
        epoch = camera.epoch
        sample = evidence.sample_evidence(session, camera_id, cap=settings.calibration_sample_cap, epoch=epoch)
        evidence_count = int(camera.usable_evidence_count)
        height_m = camera.person_height_m
        problem: CalibrationProblem | None = None
        problem_error = ""
        try:
            problem = problem_for(camera)
        except (CalibrationError, ValueError) as exc:
            problem, problem_error = None, str(exc)

    started = time.perf_counter()
    if problem is None:
        solve = EvidenceSolve(np.arange(len(sample)), None, f"the camera's settings: {problem_error}")
    else:
        # The sample is already capped and balanced by the store; repeats (still people, a mannequin) count once,
        # and the frame times (with the appearance or the client's track ids, across gaps of seconds) link one
        # walker's observations into one individual with one height.
        solve = solve_evidence(
            sample.tops_px,
            sample.bottoms_px,
            problem,
            times_s=sample.times_s,
            appearance=sample.appearance,
            client_tracks=sample.track_ids,
        )
    people_used = solve.people_used
    duration_s = time.perf_counter() - started
    thin = None if solve.calibration is None else too_thin(solve.calibration)
    if thin is not None:
        solve = EvidenceSolve(solve.used, None, thin)
    if solve.calibration is not None and problem is not None:
        values = replace(
            CalibrationValues.from_solution(
                solve.calibration, people_used=people_used, evidence_count=evidence_count, duration_s=duration_s
            ),
            camera_model=model_record(solve.calibration, problem),
            quality=quality_record(solve.calibration.quality),
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
        with transaction(settings) as session:
            current = current_calibration(session, camera_id)
            make_current = values.status == "ok" and (
                forced or current is None or at_least_as_supported(values, current)
            )
            record = add_calibration(session, camera_id, values, make_current=make_current, forced=forced, epoch=epoch)
            make_current = record.is_current  # False for an epoch that closed while the solve ran
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
    announce(dispatcher, deliveries)
    if waiting:
        dispatcher.measure_requested([camera_id])
    if values.status != "ok":
        return FAILED
    return DONE if make_current else SKIPPED
