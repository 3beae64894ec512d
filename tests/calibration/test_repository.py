"""Calibration versions in the store, on SQLite and PostgreSQL; when a solve is due."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sqlalchemy import update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.calibration.evidence import key_new_evidence, sample_evidence
from service.calibration.repository import (
    add_calibration,
    calibration_history,
    current_calibration,
    get_calibration,
    reset_calibration,
)
from service.calibration.service import (
    evidence_for_next_solve,
    has_converged,
    next_solve_at,
    people_needed,
    solve_due,
)
from service.cameras.repository import CameraNotFoundError, get_camera
from service.domain import CalibrationValues
from service.settings import Settings
from service.store.models import CalibrationVersion, Camera, Observation
from tests.support.store import add_camera, count, evidence_count, ok_values, populate_cells

pytestmark = pytest.mark.both_backends


def test_calibration_is_due_first_at_the_minimum_then_on_growth() -> None:
    def due(evidence: int, last: int) -> bool:
        camera = Camera(usable_evidence_count=evidence, evidence_at_last_solve=last)
        return evidence >= evidence_for_next_solve(camera, min_people=30, growth_factor=1.5)

    assert not due(29, 0)
    assert due(30, 0)
    assert not due(44, 30)
    assert due(45, 30)


def test_more_people_stop_being_due_once_they_no_longer_sharpen_the_solve() -> None:
    """growth_factor while a solve's sample grows, refresh_factor once it is full or the camera has converged."""

    def target(last: int, *, converged: bool = False) -> int:
        camera = Camera(usable_evidence_count=0, evidence_at_last_solve=last)
        schedule = {"min_people": 30, "growth_factor": 1.5, "refresh_factor": 4.0, "sample_cap": 2000}
        return evidence_for_next_solve(camera, **schedule, converged=converged)

    assert target(0) == 30 and target(1000) == 1500 and target(1999) == 2999
    assert target(2000) == 8000 and target(5000) == 20_000  # a full sample: only a refresh is due
    assert target(100, converged=True) == 400


def _solved(session: Session, fx_px: float, *, grade: str = "good", normal: tuple = (0.0, -0.8, 0.6)) -> None:
    values = ok_values(
        evidence_count=200,
        fx_px=fx_px,
        fx_std_px=20.0,
        normal=normal,
        normal_std_deg=0.5,
        rho_std_m=0.1,
        quality={"grade": grade},
    )
    add_calibration(session, "cam-1", values, make_current=True)


def test_a_camera_converges_when_a_solve_moves_the_answer_by_less_than_its_sigma(session: Session) -> None:
    camera = add_camera(session, "cam-1")
    _solved(session, 1000.0)
    assert not has_converged(session, camera)  # one solve: nothing to compare with
    _solved(session, 1015.0)  # 0.75 sigma from the one before
    assert has_converged(session, camera)
    _solved(session, 1050.0)  # the focal length moved by 1.75 sigma: back on the fast schedule
    assert not has_converged(session, camera)
    _solved(session, 1050.0, normal=(0.0, -0.79, 0.613))  # the normal moved by 0.95 degrees (1.9 sigma)
    assert not has_converged(session, camera)
    _solved(session, 1050.0, normal=(0.0, -0.79, 0.613), grade="rough")  # agrees, but not graded good
    assert not has_converged(session, camera)


def test_a_converged_camera_is_not_due_on_every_growth_of_its_evidence(session: Session) -> None:
    """With its last two solves in agreement the camera waits for the refresh factor; a camera whose last solve
    moved the answer is due at the growth factor, as before."""
    settings = Settings(calibration_min_people=30, calibration_growth_factor=1.5, calibration_refresh_factor=4.0)
    camera = add_camera(session, "cam-1")
    _solved(session, 1000.0)
    _solved(session, 1010.0)
    camera.usable_evidence_count = 300  # the last solve's was 200
    assert next_solve_at(session, camera, settings) == 800 and not solve_due(session, camera, settings)
    assert people_needed(session, camera, settings) == 500
    _solved(session, 1100.0)
    assert next_solve_at(session, camera, settings) == 300 and solve_due(session, camera, settings)


def test_versions_increase_and_only_allowed_ones_become_current(session: Session) -> None:
    add_camera(session, "cam-1")
    add_camera(session, "cam-2")
    v1 = add_calibration(session, "cam-1", ok_values(evidence_count=30), make_current=True)
    v2 = add_calibration(session, "cam-1", ok_values(evidence_count=45), make_current=False)
    failure = CalibrationValues.failure(
        "all people on one line", person_height_m=1.32, people_used=68, evidence_count=68
    )
    v3 = add_calibration(session, "cam-1", failure, make_current=False)
    with pytest.raises(ValueError, match="only a successful"):
        add_calibration(session, "cam-1", failure, make_current=True)
    session.commit()
    assert [v.version for v in (v1, v2, v3)] == [1, 2, 3]
    current = current_calibration(session, "cam-1")
    assert current is not None and current.version == 1
    camera = get_camera(session, "cam-1")
    assert camera is not None and camera.evidence_at_last_solve == 68  # failed solves count too

    v4 = add_calibration(session, "cam-1", ok_values(evidence_count=70), make_current=True, forced=True)
    session.commit()
    session.expire_all()
    current = current_calibration(session, "cam-1")
    assert current is not None and (current.version, current.forced) == (4, True)
    assert v4.is_current
    assert [v.version for v in calibration_history(session, "cam-1")] == [4, 3, 2, 1]
    assert [v.is_current for v in calibration_history(session, "cam-1")] == [True, False, False, False]
    assert [v.version for v in calibration_history(session, "cam-1", limit=2, before_version=3)] == [2, 1]
    stored_failure = get_calibration(session, "cam-1", 3)
    assert stored_failure is not None
    assert (stored_failure.status, stored_failure.reason, stored_failure.fx_px) == ("failed", failure.reason, None)

    other = add_calibration(session, "cam-2", ok_values(), make_current=True)
    assert other.version == 1  # numbering is per camera
    with pytest.raises(CameraNotFoundError):
        add_calibration(session, "nope", ok_values(), make_current=True)


def test_the_database_allows_one_current_version_per_camera(session: Session) -> None:
    add_camera(session)
    add_calibration(session, "cam-1", ok_values(), make_current=True)
    add_calibration(session, "cam-1", ok_values(), make_current=False)
    session.commit()
    with pytest.raises(IntegrityError):
        session.execute(update(CalibrationVersion).values(is_current=True))
        session.flush()


def test_a_geometry_solution_round_trips_with_non_finite_values_as_null(session: Session) -> None:
    from dataclasses import replace

    from bench.simulate import SceneConfig, draw_scene
    from service.geometry import CalibrationProblem, calibrate

    scene = draw_scene(replace(SceneConfig(), n_people=60, image_size=(800, 800)), np.random.default_rng(3))
    solution = calibrate(scene.tops_px, scene.bottoms_px, CalibrationProblem((800, 800), 1.7))
    assert solution.uncertainty is not None
    covariance = np.array(solution.uncertainty.covariance, dtype=float)
    covariance[0, 0] = np.nan
    solution = replace(solution, uncertainty=replace(solution.uncertainty, covariance=covariance, rho_m=math.inf))
    add_camera(session)
    values = CalibrationValues.from_solution(solution, people_used=60, evidence_count=60, duration_s=0.02)
    add_calibration(session, "cam-1", values, make_current=True)
    session.commit()
    session.expire_all()

    stored = current_calibration(session, "cam-1")
    assert stored is not None
    assert stored.fx_px == pytest.approx(solution.fx) and stored.rho_m == pytest.approx(solution.rho)
    normal = np.array([stored.normal_x, stored.normal_y, stored.normal_z], dtype=float)
    np.testing.assert_allclose(normal, solution.normal)
    assert stored.inliers == solution.num_inliers and stored.person_height_m == 1.7
    assert stored.rho_std_m is None  # inf: stored as NULL on both backends
    assert stored.covariance is not None and stored.covariance[0][0] is None
    assert stored.covariance[1][1] == pytest.approx(covariance[1, 1])


def test_reset_opens_a_new_epoch_that_keeps_old_people_stored_but_out_of_solves(session: Session) -> None:
    add_camera(session)
    populate_cells(session, {0: 30})
    add_calibration(session, "cam-1", ok_values(evidence_count=30), make_current=True)
    session.commit()

    reset_calibration(session, "cam-1")
    session.commit()
    assert current_calibration(session, "cam-1") is None
    assert [v.epoch for v in calibration_history(session, "cam-1")] == [1]
    camera = get_camera(session, "cam-1")
    assert camera is not None and camera.evidence_at_last_solve == 0
    assert (camera.epoch, camera.epoch_reason, camera.moved_at, camera.moves) == (2, "reset", None, 0)
    assert camera.usable_evidence_count == 0
    assert count(session, Observation, camera_id="cam-1", usable=True) == 30  # kept for audit
    key_new_evidence(session, "cam-1", limit=100)
    assert len(sample_evidence(session, "cam-1", cap=100)) == 0
    assert len(sample_evidence(session, "cam-1", cap=100, epoch=1)) == 30

    reset_calibration(session, "cam-1", drop_evidence=True)
    session.commit()
    assert evidence_count(session, "cam-1") == 0
    assert count(session, Observation, camera_id="cam-1") == 0
    assert get_camera(session, "cam-1").epoch == 3  # type: ignore[union-attr]
