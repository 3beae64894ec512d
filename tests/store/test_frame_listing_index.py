"""Migration 0009: the index behind a camera's frame list, added and removed on both backends, and used by the list's
query (each page one index range scan, not a sort of the camera's frames)."""

from __future__ import annotations

import uuid
from datetime import UTC, datetime

import pytest
from alembic import command
from sqlalchemy import event, inspect
from sqlalchemy.orm import Session

from service.frames import listing
from service.store import make_engine
from service.store.migrate import alembic_config, upgrade

pytestmark = pytest.mark.both_backends

INDEX = "ix_frames_camera_id_timestamp_id"


def frame_indexes(url: str) -> set[str]:
    engine = make_engine(url)
    try:
        with engine.connect() as connection:
            return {index["name"] for index in inspect(connection).get_indexes("frames")}  # type: ignore[misc]
    finally:
        engine.dispose()


def test_0009_adds_the_index_and_its_downgrade_removes_it(database_url: str) -> None:
    upgrade(database_url, "0009")
    assert INDEX in frame_indexes(database_url)
    command.downgrade(alembic_config(database_url), "0006")
    assert INDEX not in frame_indexes(database_url)
    upgrade(database_url)
    assert INDEX in frame_indexes(database_url)


def test_a_page_is_an_index_range_scan(session: Session) -> None:
    """The statement a page runs (with a cursor and a status filter: the deepest page's shape), as the driver got it,
    is planned on the index with no sort, on both backends."""
    engine = session.get_bind()
    captured: list[tuple[str, object]] = []

    def capture(conn, cursor, statement, parameters, context, executemany):  # type: ignore[no-untyped-def]
        if statement.lstrip().startswith("SELECT") and "FROM frames" in statement and not captured:
            captured.append((statement, parameters))

    position = listing.FramePosition(datetime(2026, 1, 1, tzinfo=UTC), uuid.uuid4())
    event.listen(engine, "before_cursor_execute", capture)
    try:
        listing.list_frames(session, "cam", limit=50, before=position, status="done")
    finally:
        event.remove(engine, "before_cursor_execute", capture)
    statement, parameters = captured[0]
    connection = session.connection()
    if engine.dialect.name == "sqlite":
        rows = connection.exec_driver_sql(f"EXPLAIN QUERY PLAN {statement}", parameters)  # type: ignore[arg-type]
        plan = " | ".join(str(row[-1]) for row in rows)
        assert INDEX in plan and "TEMP B-TREE" not in plan, plan
    else:
        connection.exec_driver_sql("SET LOCAL enable_seqscan = off")
        rows = connection.exec_driver_sql(f"EXPLAIN {statement}", parameters)  # type: ignore[arg-type]
        plan = " | ".join(str(row[0]) for row in rows)
        assert INDEX in plan and "Sort" not in plan, plan
