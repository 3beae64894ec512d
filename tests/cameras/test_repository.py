"""Cameras in the store, on SQLite and PostgreSQL."""

from __future__ import annotations

from datetime import UTC, timedelta

import pytest
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.calibration.repository import add_calibration
from service.cameras.repository import delete_camera, get_camera, list_cameras, upsert_camera
from service.domain import ViolationIn
from service.store.models import CalibrationVersion, Frame, Observation, ViolationEvent
from tests.support.store import T0, add_camera, add_frame, count, ok_values, person_in_cell, record_violations

pytestmark = pytest.mark.both_backends


def test_upsert_creates_then_updates_only_what_changed(session: Session) -> None:
    camera, created = upsert_camera(
        session, "cam-1", image_width_px=1920, image_height_px=1080, person_height_m=1.32, now=T0
    )
    assert created
    assert (camera.person_height_m, camera.equal_focal, camera.known_focal_px) == (1.32, True, None)
    assert camera.distance_threshold_m == pytest.approx(1.8288)
    session.commit()

    same, created = upsert_camera(
        session, "cam-1", image_width_px=1920, image_height_px=1080, person_height_m=1.32, now=T0 + timedelta(hours=1)
    )
    assert not created and same.updated_at == T0

    later = T0 + timedelta(hours=2)
    updated, created = upsert_camera(
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
    stored = get_camera(session, "cam-1")
    assert stored is not None
    assert (stored.distance_threshold_m, stored.known_focal_px) == (2.0, 1400.0)
    assert (stored.created_at, stored.updated_at) == (T0, later)
    assert stored.created_at.tzinfo is UTC


def test_upsert_refuses_values_the_schema_forbids(session: Session) -> None:
    with pytest.raises(IntegrityError):
        upsert_camera(session, "cam-1", image_width_px=0, image_height_px=1080, person_height_m=1.32)


def test_list_cameras_pages_in_id_order(session: Session) -> None:
    for camera_id in ("c", "a", "d", "b"):
        add_camera(session, camera_id)
    session.commit()
    assert [c.id for c in list_cameras(session, limit=3)] == ["a", "b", "c"]
    assert [c.id for c in list_cameras(session, limit=3, after="c")] == ["d"]
    assert get_camera(session, "zzz") is None


def test_delete_camera_cascades_to_everything_it_owns(session: Session) -> None:
    add_camera(session, "gone")
    add_camera(session, "kept")
    for camera_id in ("gone", "kept"):
        frame = add_frame(session, camera_id, [person_in_cell(0), person_in_cell(1)])
        record_violations(session, frame, [ViolationIn(0, 1, 1.2)])
        add_calibration(session, camera_id, ok_values(), make_current=True)
    session.commit()

    assert delete_camera(session, "gone")
    session.commit()
    assert not delete_camera(session, "gone")
    for model in (Frame, Observation, CalibrationVersion, ViolationEvent):
        assert count(session, model, camera_id="gone") == 0, model
        assert count(session, model, camera_id="kept") > 0, model
    assert get_camera(session, "gone") is None
