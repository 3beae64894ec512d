"""Rows for the repository tests: cameras on a square image whose sampling cells are 100 px, standing people put in
given cells, frames, calibration values, and counts."""

from __future__ import annotations

from collections.abc import Sequence
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import Connection, func, inspect, select, text
from sqlalchemy.orm import Session

from service.calibration.evidence import key_new_evidence
from service.cameras.repository import upsert_camera
from service.domain import CalibrationValues, FrameOutcome, PersonIn, ViolationIn
from service.frames.ingest import add_keypoint_frame
from service.frames.repository import record_frame_outcomes
from service.geometry import DEFAULT_HEIGHT_M
from service.geometry.evidence import SAMPLE_GRID
from service.store import make_engine
from service.store.models import Camera, Frame, Observation

T0 = datetime(2024, 5, 1, 10, 0, 0, tzinfo=UTC)
GRID_COLS = SAMPLE_GRID[0]
SIZE_PX = 800  # square image: the 8 x 8 sampling grid has 100 px cells
CELL_PX = SIZE_PX // GRID_COLS


def add_camera(session: Session, camera_id: str = "cam-1", **overrides: Any) -> Camera:
    values: dict[str, Any] = {
        "image_width_px": SIZE_PX,
        "image_height_px": SIZE_PX,
        "person_height_m": DEFAULT_HEIGHT_M,
        **overrides,
    }
    camera, _ = upsert_camera(session, camera_id, **values)
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
    frame, created = add_keypoint_frame(
        session, camera_id, timestamp=at, people=people, client_frame_id=client_frame_id
    )
    assert created
    return frame


def count(session: Session, model: type[Any], **where: Any) -> int:
    stmt = select(func.count()).select_from(model).filter_by(**where)
    return int(session.execute(stmt).scalar_one())


def evidence_count(session: Session, camera_id: str) -> int:
    """The camera's usable-evidence counter (kept on insert), read afresh."""
    return int(session.execute(select(Camera.usable_evidence_count).where(Camera.id == camera_id)).scalar_one())


def record_violations(session: Session, frame: Frame, violations: Sequence[ViolationIn]) -> None:
    """Store the frame as measured with these violations, as the measuring job does (replacing earlier ones)."""
    outcome = FrameOutcome(frame.id, frame.camera_id, frame.timestamp, "done", 1, result={}, violations=violations)
    record_frame_outcomes(session, [outcome])


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
    while keyed := key_new_evidence(session, camera_id, limit=limit):
        session.commit()
        total += keyed
    return total


def insert_raw_camera_and_frame(connection: Connection, *, people: int, client_frame_id: str | None = None) -> None:
    """Camera 'c' and one pending keypoint frame in raw SQL valid from revision 0001 on, for migration tests that
    must write rows in an older schema than the models describe."""
    connection.execute(
        text(
            "INSERT INTO cameras (id, image_width_px, image_height_px, person_height_m, equal_focal, "
            "distance_threshold_m, created_at, updated_at) VALUES ('c', 640, 480, 1.3, true, 1.8, "
            "'2026-01-01 00:00:00', '2026-01-01 00:00:00')"
        )
    )
    frame_id = "00000000-0000-0000-0000-000000000001"
    connection.execute(
        text(
            "INSERT INTO frames (id, camera_id, client_frame_id, timestamp, received_at, source, status, people) "
            "VALUES (:id, 'c', :client, '2026-01-01 00:00:00', '2026-01-01 00:00:00', 'keypoints', 'pending', "
            ":people)"
        ),
        {
            "id": frame_id.replace("-", "") if connection.dialect.name == "sqlite" else frame_id,
            "client": client_frame_id,
            "people": people,
        },
    )


def observation_columns(url: str) -> set[str]:
    """The columns of the observations table at the database's current revision (the migration tests)."""
    engine = make_engine(url)
    try:
        with engine.connect() as connection:
            return {column["name"] for column in inspect(connection).get_columns("observations")}
    finally:
        engine.dispose()
