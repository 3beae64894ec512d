"""Every repository operation, on SQLite and PostgreSQL (see conftest.py)."""

from __future__ import annotations

import math
import threading
import uuid
from collections import Counter
from datetime import UTC, datetime, timedelta, timezone
from typing import Any

import numpy as np
import pytest
from sqlalchemy import Engine, func, select, text, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.geometry import DEFAULT_HEIGHT_M, CalibrationProblem
from service.store import make_session_factory, repository
from service.store.models import (
    GRID_CELLS,
    GRID_COLS,
    CalibrationVersion,
    Camera,
    Frame,
    Observation,
    ViolationEvent,
)
from service.store.repository import (
    CalibrationValues,
    CameraNotFoundError,
    FrameNotFoundError,
    PersonIn,
    ViolationBucket,
    ViolationIn,
)

T0 = datetime(2024, 5, 1, 10, 0, 0, tzinfo=UTC)
SIZE_PX = 800  # square image: the 8 x 8 sampling grid has 100 px cells
CELL_PX = SIZE_PX // GRID_COLS


def add_camera(session: Session, camera_id: str = "cam-1", **overrides: Any) -> Camera:
    values: dict[str, Any] = {
        "image_width_px": SIZE_PX,
        "image_height_px": SIZE_PX,
        "person_height_m": DEFAULT_HEIGHT_M,
        **overrides,
    }
    camera, _ = repository.upsert_camera(session, camera_id, **values)
    return camera


def person_at(x_px: float, y_px: float, **kwargs: Any) -> PersonIn:
    """A standing person whose ankle centre is at (x, y) and shoulder centre 60 px above."""
    return PersonIn(shoulder_px=(x_px, y_px - 60.0), ankle_px=(x_px, y_px), **kwargs)


def person_in_cell(cell: int, offset_px: float = 50.0) -> PersonIn:
    row, col = divmod(cell, GRID_COLS)
    return person_at(col * CELL_PX + offset_px, row * CELL_PX + offset_px)


def add_frame(
    session: Session, camera_id: str, people: list[PersonIn], *, at: datetime = T0, client_frame_id: str | None = None
) -> Frame:
    frame, created = repository.add_keypoint_frame(
        session, camera_id, timestamp=at, people=people, client_frame_id=client_frame_id
    )
    assert created
    return frame


def count(session: Session, model: type[Any], **where: Any) -> int:
    stmt = select(func.count()).select_from(model).filter_by(**where)
    return int(session.execute(stmt).scalar_one())


def ok_values(evidence_count: int = 100, inliers: int = 80, **overrides: Any) -> CalibrationValues:
    values: dict[str, Any] = {
        "status": "ok",
        "person_height_m": 1.32,
        "people_used": 90,
        "inliers": inliers,
        "evidence_count": evidence_count,
        "fx_px": 1000.0,
        "fy_px": 1000.0,
        "cx_px": 400.0,
        "cy_px": 400.0,
        "normal": (0.0, -0.8, 0.6),
        "rho_m": 4.0,
        **overrides,
    }
    return CalibrationValues(**values)


# --------------------------------------------------------------------------------------------------- cameras


def test_upsert_creates_then_updates_only_what_changed(session: Session) -> None:
    camera, created = repository.upsert_camera(
        session, "cam-1", image_width_px=1920, image_height_px=1080, person_height_m=1.32, now=T0
    )
    assert created
    assert (camera.person_height_m, camera.equal_focal, camera.known_focal_px) == (1.32, True, None)
    assert camera.distance_threshold_m == pytest.approx(1.8288)
    session.commit()

    same, created = repository.upsert_camera(
        session, "cam-1", image_width_px=1920, image_height_px=1080, person_height_m=1.32, now=T0 + timedelta(hours=1)
    )
    assert not created and same.updated_at == T0

    later = T0 + timedelta(hours=2)
    updated, created = repository.upsert_camera(
        session,
        "cam-1",
        image_width_px=1920,
        image_height_px=1080,
        person_height_m=1.32,
        distance_threshold_m=2.0,
        known_focal_px=1400.0,
        now=later,
    )
    session.commit()
    assert not created and updated.distance_threshold_m == 2.0
    session.expire_all()
    stored = repository.get_camera(session, "cam-1")
    assert stored is not None
    assert (stored.distance_threshold_m, stored.known_focal_px) == (2.0, 1400.0)
    assert (stored.created_at, stored.updated_at) == (T0, later)
    assert stored.created_at.tzinfo is UTC


def test_upsert_refuses_values_the_schema_forbids(session: Session) -> None:
    with pytest.raises(IntegrityError):
        repository.upsert_camera(session, "cam-1", image_width_px=0, image_height_px=1080, person_height_m=1.32)


def test_list_cameras_pages_in_id_order(session: Session) -> None:
    for camera_id in ("c", "a", "d", "b"):
        add_camera(session, camera_id)
    session.commit()
    assert [c.id for c in repository.list_cameras(session, limit=3)] == ["a", "b", "c"]
    assert [c.id for c in repository.list_cameras(session, limit=3, after="c")] == ["d"]
    assert repository.get_camera(session, "zzz") is None


def test_delete_camera_cascades_to_everything_it_owns(session: Session) -> None:
    add_camera(session, "gone")
    add_camera(session, "kept")
    for camera_id in ("gone", "kept"):
        frame = add_frame(session, camera_id, [person_in_cell(0), person_in_cell(1)])
        repository.record_violations(session, frame, [ViolationIn(0, 1, 1.2)])
        repository.add_calibration(session, camera_id, ok_values(), make_current=True)
    session.commit()

    assert repository.delete_camera(session, "gone")
    session.commit()
    assert not repository.delete_camera(session, "gone")
    for model in (Frame, Observation, CalibrationVersion, ViolationEvent):
        assert count(session, model, camera_id="gone") == 0, model
        assert count(session, model, camera_id="kept") > 0, model
    assert repository.get_camera(session, "gone") is None


# --------------------------------------------------------------------------------------------------- frames


def test_add_keypoint_frame_stores_people_and_counts_usable_evidence(session: Session) -> None:
    add_camera(session)
    keypoints = [[float(i), float(i) + 0.5, 0.9] for i in range(17)]
    people = [
        person_at(150.0, 750.0, keypoints=keypoints),
        PersonIn(shoulder_px=(10.0, 10.0), ankle_px=None),
        person_at(805.0, -3.0, unusable_reason="low keypoint scores"),
    ]
    received = T0 + timedelta(seconds=2)
    frame, created = repository.add_keypoint_frame(session, "cam-1", timestamp=T0, people=people, received_at=received)
    session.commit()
    assert created
    assert (frame.status, frame.source, frame.people, frame.result) == ("pending", "keypoints", 3, None)
    assert (frame.timestamp, frame.received_at) == (T0, received)

    observations = repository.frame_observations(session, frame.id)
    assert [o.person_index for o in observations] == [0, 1, 2]
    first, no_ankle, low_score = observations
    assert first.usable and first.unusable_reason is None
    assert (first.ankle_x_px, first.ankle_y_px, first.shoulder_y_px) == (150.0, 750.0, 690.0)
    assert first.cell == 7 * GRID_COLS + 1
    assert first.keypoints == keypoints
    assert not no_ankle.usable and no_ankle.unusable_reason == "ankle centre not visible"
    assert no_ankle.cell is None and no_ankle.ankle_x_px is None
    assert not low_score.usable and low_score.unusable_reason == "low keypoint scores"
    assert low_score.cell == GRID_COLS - 1  # outside the image: clamped to the edge cell
    assert repository.usable_evidence_count(session, "cam-1") == 1
    assert count(session, Observation, camera_id="cam-1", usable=True) == 1


def test_a_retry_with_the_same_client_frame_id_is_the_same_frame(session: Session) -> None:
    add_camera(session, "cam-1")
    add_camera(session, "cam-2")
    people = [person_in_cell(3), person_in_cell(4)]
    first, created = repository.add_keypoint_frame(session, "cam-1", timestamp=T0, people=people, client_frame_id="f-1")
    session.commit()
    retry, created_again = repository.add_keypoint_frame(
        session, "cam-1", timestamp=T0, people=people, client_frame_id="f-1"
    )
    session.commit()
    other, created_other = repository.add_keypoint_frame(
        session, "cam-2", timestamp=T0, people=people, client_frame_id="f-1"
    )
    session.commit()
    assert created and not created_again and created_other
    assert retry.id == first.id and other.id != first.id
    assert count(session, Frame, camera_id="cam-1") == 1
    assert count(session, Observation, camera_id="cam-1") == 2
    assert repository.usable_evidence_count(session, "cam-1") == 2


def test_frames_without_a_client_id_never_collide(session: Session) -> None:
    add_camera(session)
    ids = {add_frame(session, "cam-1", [person_in_cell(0)]).id for _ in range(3)}
    session.commit()
    assert len(ids) == 3
    assert repository.usable_evidence_count(session, "cam-1") == 3


def test_a_retry_that_loses_the_race_returns_the_winners_frame(
    session: Session, engine: Engine, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The pre-check missed the frame (another process committed it in between): the unique constraint decides."""
    add_camera(session)
    session.commit()
    with make_session_factory(engine)() as other:
        winner, _ = repository.add_keypoint_frame(
            other, "cam-1", timestamp=T0, people=[person_in_cell(0)], client_frame_id="f-1"
        )
        other.commit()

    real_lookup = repository._frame_by_client_id
    calls = []

    def stale_first_lookup(*args: Any) -> Frame | None:
        calls.append(args)
        return None if len(calls) == 1 else real_lookup(*args)

    monkeypatch.setattr(repository, "_frame_by_client_id", stale_first_lookup)
    frame, created = repository.add_keypoint_frame(
        session, "cam-1", timestamp=T0, people=[person_in_cell(0)], client_frame_id="f-1"
    )
    session.commit()
    assert not created and frame.id == winner.id and len(calls) == 2
    assert count(session, Observation, camera_id="cam-1") == 1
    assert repository.usable_evidence_count(session, "cam-1") == 1


def test_concurrent_retries_store_one_frame(session: Session, engine: Engine) -> None:
    add_camera(session)
    session.commit()
    factory = make_session_factory(engine)
    barrier = threading.Barrier(4)
    outcomes: list[tuple[uuid.UUID, bool]] = []
    errors: list[BaseException] = []

    def post() -> None:
        try:
            with factory() as own:
                barrier.wait()
                frame, created = repository.add_keypoint_frame(
                    own, "cam-1", timestamp=T0, people=[person_in_cell(5)] * 3, client_frame_id="same"
                )
                own.commit()
                outcomes.append((frame.id, created))
        except BaseException as exc:  # surfaced below: a thread's exception would otherwise vanish
            errors.append(exc)

    threads = [threading.Thread(target=post) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=30)
    assert not errors, errors
    assert len({frame_id for frame_id, _ in outcomes}) == 1
    assert sorted(created for _, created in outcomes) == [False, False, False, True]
    session.expire_all()
    assert count(session, Observation, camera_id="cam-1") == 3
    assert repository.usable_evidence_count(session, "cam-1") == 3


def test_frames_need_a_known_camera_aware_timestamps_and_finite_points(session: Session) -> None:
    with pytest.raises(CameraNotFoundError):
        repository.add_keypoint_frame(session, "nope", timestamp=T0, people=[])
    add_camera(session)
    with pytest.raises(ValueError, match="finite"):
        repository.add_keypoint_frame(
            session, "cam-1", timestamp=T0, people=[PersonIn(shoulder_px=(math.nan, 1.0), ankle_px=(1.0, 2.0))]
        )
    with pytest.raises(ValueError, match="timezone"):
        repository.add_keypoint_frame(session, "cam-1", timestamp=datetime(2024, 1, 1), people=[])


def test_pending_frames_results_and_scoping(session: Session) -> None:
    add_camera(session, "cam-1")
    add_camera(session, "cam-2")
    late = add_frame(session, "cam-1", [], at=T0)
    early = add_frame(session, "cam-1", [], at=T0)
    late.received_at, early.received_at = T0 + timedelta(seconds=5), T0 + timedelta(seconds=1)
    elsewhere = add_frame(session, "cam-2", [])
    elsewhere.received_at = T0 + timedelta(seconds=3)
    session.commit()
    assert [f.id for f in repository.pending_frames(session, "cam-1")] == [early.id, late.id]
    assert [f.id for f in repository.pending_frames(session)] == [early.id, elsewhere.id, late.id]
    assert [f.id for f in repository.pending_frames(session, limit=1)] == [early.id]

    result = {"people": [{"position_m": [1.0, 2.0]}], "pairs": [{"i": 0, "j": 1, "distance_m": 1.5}]}
    done = repository.set_frame_result(session, early.id, status="done", result=result, calibration_version=3)
    session.commit()
    assert done.processed_at is not None
    session.expire_all()
    fetched = repository.get_frame(session, "cam-1", early.id)
    assert fetched is not None
    assert (fetched.status, fetched.result, fetched.calibration_version) == ("done", result, 3)
    assert repository.get_frame(session, "cam-2", early.id) is None  # a frame id does not cross cameras
    assert [f.id for f in repository.pending_frames(session, "cam-1")] == [late.id]

    failed = repository.set_frame_result(session, late.id, status="failed", error="no calibration")
    assert (failed.status, failed.error) == ("failed", "no calibration")
    with pytest.raises(ValueError, match="status"):
        repository.set_frame_result(session, late.id, status="exploded")
    with pytest.raises(FrameNotFoundError):
        repository.set_frame_result(session, uuid.uuid4(), status="done")


# --------------------------------------------------------------------------------------------------- evidence


def test_grid_cell_buckets_and_clamps() -> None:
    assert repository.grid_cell(0.0, 0.0, 1920, 1080) == 0
    assert repository.grid_cell(1919.9, 1079.9, 1920, 1080) == GRID_CELLS - 1
    assert repository.grid_cell(-50.0, 2000.0, 1920, 1080) == GRID_CELLS - GRID_COLS
    assert repository.grid_cell(240.0, 135.0, 1920, 1080) == GRID_COLS + 1


def test_calibration_is_due_first_at_the_minimum_then_on_growth() -> None:
    def due(evidence: int, last: int) -> bool:
        camera = Camera(usable_evidence_count=evidence, evidence_at_last_solve=last)
        return repository.calibration_due(camera, min_people=30, growth_factor=1.5)

    assert not due(29, 0)
    assert due(30, 0)
    assert not due(44, 30)
    assert due(45, 30)


def populate_cells(session: Session, per_cell: dict[int, int], people_per_frame: int = 25) -> list[int]:
    """Store usable people per cell (plus one unusable person per frame); returns the usable observation ids."""
    people = [person_in_cell(cell, offset_px=10 + (i % 80)) for cell, n in per_cell.items() for i in range(n)]
    for start in range(0, len(people), people_per_frame):
        batch = people[start : start + people_per_frame]
        add_frame(session, "cam-1", [*batch, PersonIn(shoulder_px=(1.0, 1.0), ankle_px=None)])
    session.commit()
    key_everyone(session, "cam-1")
    stmt = select(Observation.id).where(Observation.camera_id == "cam-1", Observation.usable.is_(True))
    return list(session.scalars(stmt))


def key_everyone(session: Session, camera_id: str, limit: int = 333) -> int:
    """What the calibration job does before it samples: key in short transactions until none is left."""
    total = 0
    while keyed := repository.key_new_evidence(session, camera_id, limit=limit):
        session.commit()
        total += keyed
    return total


def test_people_are_stored_unkeyed_and_keyed_in_bulk_oldest_first(session: Session) -> None:
    add_camera(session, "cam-1")
    add_camera(session, "cam-2")
    frames = [add_frame(session, "cam-1", [person_in_cell(3), person_in_cell(40)]) for _ in range(3)]
    add_frame(session, "cam-2", [person_in_cell(3)])
    session.commit()
    assert count(session, Observation, sample_key=None) == 7
    assert len(repository.sample_evidence(session, "cam-1", cap=50)) == 0  # unkeyed people are not sampled yet

    assert repository.key_new_evidence(session, "cam-1", limit=4) == 4
    session.commit()
    keyed = session.execute(
        select(Observation.id, Observation.frame_id, Observation.sample_key)
        .where(Observation.sample_key.is_not(None))
        .order_by(Observation.id)
    ).all()
    assert [row.frame_id for row in keyed] == [frames[0].id, frames[0].id, frames[1].id, frames[1].id]
    assert [row.sample_key for row in keyed] == [repository.sample_key(row.id) for row in keyed]
    assert len(repository.sample_evidence(session, "cam-1", cap=50)) == 4

    assert key_everyone(session, "cam-1") == 2
    assert repository.key_new_evidence(session, "cam-1", limit=10) == 0
    assert len(repository.sample_evidence(session, "cam-1", cap=50)) == 6
    assert count(session, Observation, camera_id="cam-2", sample_key=None) == 1  # other cameras wait their turn
    with pytest.raises(ValueError):
        repository.key_new_evidence(session, "cam-1", limit=0)


@pytest.mark.parametrize(
    "statement",
    [
        "SELECT id FROM observations WHERE camera_id = 'c' AND sample_key IS NULL ORDER BY id LIMIT 10",
        "SELECT id FROM observations WHERE camera_id = 'c' AND usable = true AND cell = 3 "
        "AND sample_key IS NOT NULL AND sample_key >= 5 ORDER BY sample_key, id LIMIT 10",
        "DELETE FROM observations WHERE camera_id = 'c'",
    ],
)
def test_observations_are_found_through_an_index(session: Session, statement: str) -> None:
    """The partial indexes only help if the planner proves a query matches them: no full scans of the biggest
    table. PostgreSQL prefers a scan for a table this small, so it is told not to."""
    if session.get_bind().dialect.name == "sqlite":
        plan = " ".join(row[-1] for row in session.execute(text(f"EXPLAIN QUERY PLAN {statement}")))
    else:
        session.execute(text("SET LOCAL enable_seqscan = off"))
        plan = " ".join(row[0] for row in session.execute(text(f"EXPLAIN {statement}")))
    assert "ix_observations_" in plan and "SCAN observations" not in plan and "Seq Scan" not in plan, plan


def test_sample_is_spatially_balanced_capped_and_reads_little(session: Session) -> None:
    add_camera(session)
    sparse = {cell: 10 for cell in range(10, 30)}
    populate_cells(session, {0: 1000, **sparse})
    sample = repository.sample_evidence(session, "cam-1", cap=300, seed=7)

    assert len(sample) == 300
    per_cell = Counter(sample.cells)
    assert per_cell[0] == 100  # the crowd gets only what the sparse cells cannot use
    assert all(per_cell[cell] == 10 for cell in sparse)
    assert len(set(sample.observation_ids)) == 300
    assert sample.tops_px.shape == sample.bottoms_px.shape == (300, 2)
    np.testing.assert_allclose(sample.bottoms_px[:, 1] - sample.tops_px[:, 1], 60.0)
    # O(sample): a few statements, and hardly more rows read than returned (not the 1200 stored).
    assert sample.queries <= 6
    assert sample.rows_read <= 300 + GRID_CELLS

    small = repository.sample_evidence(session, "cam-1", cap=40, seed=7)
    assert len(small) == 40 and max(Counter(small.cells).values()) == 2  # 21 cells, round-robin


def test_sample_is_deterministic_per_seed_and_random_across_seeds(session: Session) -> None:
    add_camera(session)
    populate_cells(session, {0: 400, 9: 400})
    first = repository.sample_evidence(session, "cam-1", cap=100, seed=1)
    again = repository.sample_evidence(session, "cam-1", cap=100, seed=1)
    other = repository.sample_evidence(session, "cam-1", cap=100, seed=2)
    assert first.observation_ids == again.observation_ids
    assert set(first.observation_ids) != set(other.observation_ids)
    assert Counter(first.cells) == Counter(other.cells) == {0: 50, 9: 50}


@pytest.mark.parametrize("seed", [0, 3, 11])
def test_a_cap_above_the_evidence_returns_every_usable_observation_once(session: Session, seed: int) -> None:
    """Reading each cell from a seeded start and wrapping around must neither skip nor repeat anyone."""
    add_camera(session)
    usable_ids = populate_cells(session, {0: 37, 5: 3, 63: 61, 20: 1})
    for cap in (len(usable_ids), len(usable_ids) + 50):
        sample = repository.sample_evidence(session, "cam-1", cap=cap, seed=seed)
        assert sorted(sample.observation_ids) == sorted(usable_ids)


def test_sample_keys_that_tie_are_not_skipped(session: Session) -> None:
    add_camera(session)
    usable_ids = populate_cells(session, {12: 40})
    session.execute(update(Observation).values(sample_key=123_456))
    session.commit()
    sample = repository.sample_evidence(session, "cam-1", cap=1000, seed=0)
    assert sorted(sample.observation_ids) == sorted(usable_ids)


def test_sample_of_a_camera_without_evidence_is_empty(session: Session) -> None:
    add_camera(session)
    sample = repository.sample_evidence(session, "cam-1", cap=50)
    assert len(sample) == 0 and sample.tops_px.shape == (0, 2)
    with pytest.raises(ValueError):
        repository.sample_evidence(session, "cam-1", cap=0)


# --------------------------------------------------------------------------------------------------- calibrations


def test_versions_increase_and_only_allowed_ones_become_current(session: Session) -> None:
    add_camera(session, "cam-1")
    add_camera(session, "cam-2")
    v1 = repository.add_calibration(session, "cam-1", ok_values(evidence_count=30), make_current=True)
    v2 = repository.add_calibration(session, "cam-1", ok_values(evidence_count=45), make_current=False)
    failure = CalibrationValues.failure(
        "all people on one line", person_height_m=1.32, people_used=68, evidence_count=68
    )
    v3 = repository.add_calibration(session, "cam-1", failure, make_current=False)
    with pytest.raises(ValueError, match="only a successful"):
        repository.add_calibration(session, "cam-1", failure, make_current=True)
    session.commit()
    assert [v.version for v in (v1, v2, v3)] == [1, 2, 3]
    current = repository.current_calibration(session, "cam-1")
    assert current is not None and current.version == 1
    camera = repository.get_camera(session, "cam-1")
    assert camera is not None and camera.evidence_at_last_solve == 68  # failed solves count too

    v4 = repository.add_calibration(session, "cam-1", ok_values(evidence_count=70), make_current=True, forced=True)
    session.commit()
    session.expire_all()
    current = repository.current_calibration(session, "cam-1")
    assert current is not None and (current.version, current.forced) == (4, True)
    assert v4.is_current
    assert [v.version for v in repository.calibration_history(session, "cam-1")] == [4, 3, 2, 1]
    assert [v.is_current for v in repository.calibration_history(session, "cam-1")] == [True, False, False, False]
    assert [v.version for v in repository.calibration_history(session, "cam-1", limit=2, before_version=3)] == [2, 1]
    stored_failure = repository.get_calibration(session, "cam-1", 3)
    assert stored_failure is not None
    assert (stored_failure.status, stored_failure.reason, stored_failure.fx_px) == ("failed", failure.reason, None)

    other = repository.add_calibration(session, "cam-2", ok_values(), make_current=True)
    assert other.version == 1  # numbering is per camera
    with pytest.raises(CameraNotFoundError):
        repository.add_calibration(session, "nope", ok_values(), make_current=True)


def test_the_database_allows_one_current_version_per_camera(session: Session) -> None:
    add_camera(session)
    repository.add_calibration(session, "cam-1", ok_values(), make_current=True)
    repository.add_calibration(session, "cam-1", ok_values(), make_current=False)
    session.commit()
    with pytest.raises(IntegrityError):
        session.execute(update(CalibrationVersion).values(is_current=True))
        session.flush()


def test_a_geometry_solution_round_trips_with_non_finite_values_as_null(session: Session) -> None:
    from dataclasses import replace

    from bench.simulate import SceneConfig, draw_scene
    from service.geometry import calibrate

    scene = draw_scene(replace(SceneConfig(), n_people=60, image_size=(800, 800)), np.random.default_rng(3))
    solution = calibrate(scene.tops_px, scene.bottoms_px, CalibrationProblem((800, 800), 1.7))
    assert solution.uncertainty is not None
    covariance = np.array(solution.uncertainty.covariance, dtype=float)
    covariance[0, 0] = np.nan
    solution = replace(solution, uncertainty=replace(solution.uncertainty, covariance=covariance, rho_m=math.inf))
    add_camera(session)
    values = CalibrationValues.from_solution(solution, people_used=60, evidence_count=60, duration_s=0.02)
    repository.add_calibration(session, "cam-1", values, make_current=True)
    session.commit()
    session.expire_all()

    stored = repository.current_calibration(session, "cam-1")
    assert stored is not None
    assert stored.fx_px == pytest.approx(solution.fx) and stored.rho_m == pytest.approx(solution.rho)
    normal = np.array([stored.normal_x, stored.normal_y, stored.normal_z], dtype=float)
    np.testing.assert_allclose(normal, solution.normal)
    assert stored.inliers == solution.num_inliers and stored.person_height_m == 1.7
    assert stored.rho_std_m is None  # inf: stored as NULL on both backends
    assert stored.covariance is not None and stored.covariance[0][0] is None
    assert stored.covariance[1][1] == pytest.approx(covariance[1, 1])


def test_reset_makes_the_camera_uncalibrated_and_can_drop_evidence(session: Session) -> None:
    add_camera(session)
    populate_cells(session, {0: 30})
    repository.add_calibration(session, "cam-1", ok_values(evidence_count=30), make_current=True)
    session.commit()

    repository.reset_calibration(session, "cam-1")
    session.commit()
    assert repository.current_calibration(session, "cam-1") is None
    assert len(repository.calibration_history(session, "cam-1")) == 1
    camera = repository.get_camera(session, "cam-1")
    assert camera is not None and camera.evidence_at_last_solve == 0
    assert repository.usable_evidence_count(session, "cam-1") == 30

    repository.reset_calibration(session, "cam-1", drop_evidence=True)
    session.commit()
    assert repository.usable_evidence_count(session, "cam-1") == 0
    assert count(session, Observation, camera_id="cam-1") == 0
    with pytest.raises(CameraNotFoundError):
        repository.usable_evidence_count(session, "nope")


# --------------------------------------------------------------------------------------------------- violations


def test_recording_violations_replaces_the_frames_previous_events(session: Session) -> None:
    add_camera(session)
    frame = add_frame(session, "cam-1", [person_in_cell(0)] * 3)
    assert repository.record_violations(session, frame, [ViolationIn(0, 1, 1.1, 0.1), ViolationIn(2, 0, 0.9)]) == 2
    session.commit()
    pairs = session.execute(select(ViolationEvent.person_i, ViolationEvent.person_j).order_by(ViolationEvent.id))
    assert [tuple(p) for p in pairs] == [(0, 1), (0, 2)]

    assert repository.record_violations(session, frame, [ViolationIn(1, 2, 1.0)]) == 1
    session.commit()
    assert count(session, ViolationEvent, frame_id=frame.id) == 1
    with pytest.raises(ValueError, match="two different people"):
        repository.record_violations(session, frame, [ViolationIn(1, 1, 0.0)])


def test_violation_counts_per_minute_and_hour(session: Session) -> None:
    add_camera(session, "cam-1")
    add_camera(session, "cam-2")
    events = [  # (seconds after 10:00, violations in that frame)
        (5.5, 2),
        (59.9, 1),
        (60.0, 1),
        (3599.0, 1),
        (3600.0, 3),
    ]
    for offset_s, n in events:
        frame = add_frame(session, "cam-1", [person_in_cell(0)] * (n + 1), at=T0 + timedelta(seconds=offset_s))
        repository.record_violations(session, frame, [ViolationIn(0, k + 1, 1.0) for k in range(n)])
    noise = add_frame(session, "cam-2", [person_in_cell(0)] * 6, at=T0 + timedelta(seconds=10))
    repository.record_violations(session, noise, [ViolationIn(0, k + 1, 1.0) for k in range(5)])
    session.commit()

    def minute(m: int) -> datetime:
        return T0 + timedelta(minutes=m)

    assert repository.violation_counts(session, "cam-1", since=T0) == [
        ViolationBucket(minute(0), 3),
        ViolationBucket(minute(1), 1),
        ViolationBucket(minute(59), 1),
        ViolationBucket(minute(60), 3),
    ]
    assert repository.violation_counts(session, "cam-1", since=T0, bucket_s=repository.HOUR_S) == [
        ViolationBucket(T0, 5),
        ViolationBucket(T0 + timedelta(hours=1), 3),
    ]
    # since/until in another time zone mean the same instants; until is exclusive.
    plus_two = timezone(timedelta(hours=2))
    assert repository.violation_counts(
        session, "cam-1", since=minute(1).astimezone(plus_two), until=minute(60).astimezone(plus_two)
    ) == [ViolationBucket(minute(1), 1), ViolationBucket(minute(59), 1)]
    assert repository.violation_counts(session, "cam-1", since=T0 + timedelta(days=1)) == []
    assert repository.violation_counts(session, "cam-1", since=T0)[0].start.tzinfo is UTC
