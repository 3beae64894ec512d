"""Revision 0014 adds what measuring reads of a verdict (observations.posture, placed_from_box, static), filled from
the reasons stored before, and drops them again keeping every person, on both backends."""

from __future__ import annotations

import pytest
from alembic import command
from sqlalchemy import text

from service.frames.keypoints import BOX_REASON, PARTIAL_REASON, SEATED_REASON, STATIC_REASON
from service.store import make_engine
from service.store.migrate import alembic_config, upgrade
from tests.support.store import insert_raw_camera_and_frame, observation_columns

pytestmark = pytest.mark.both_backends

FRAME_ID = "00000000-0000-0000-0000-000000000001"
NEW_COLUMNS = {"posture", "placed_from_box", "static"}
# (reason, usable, detector box) as the earlier code stored people, and the verdict the upgrade reads from them.
PEOPLE = [
    (None, True, True, ("standing", False, False)),  # a standing person found in an image
    (None, True, False, (None, False, False)),  # a posted person: no posture
    ("ankle centre not visible", False, False, ("partial", False, False)),  # posted shoulders, no ankles
    (SEATED_REASON, False, True, ("seated", False, False)),
    (PARTIAL_REASON, False, True, ("partial", False, False)),
    (BOX_REASON, False, True, (None, True, False)),
    (STATIC_REASON, False, True, (None, False, True)),
    # The combined reason of a static person placed from their box: 202 characters, which only SQLite stored.
    (f"{STATIC_REASON}; {BOX_REASON}", False, True, (None, True, True)),
    ("same pose as person 0 (a repeated detection, or a neighbour's pose)", False, True, (None, False, False)),
]


def test_0014_reads_the_verdicts_from_the_reasons_and_downgrades_without_losing_people(database_url: str) -> None:
    upgrade(database_url, "0013")
    engine = make_engine(database_url)
    try:
        with engine.begin() as connection:
            insert_raw_camera_and_frame(connection, people=len(PEOPLE))
            frame_id = FRAME_ID.replace("-", "") if connection.dialect.name == "sqlite" else FRAME_ID
            postgres = connection.dialect.name == "postgresql"
            for index, (reason, usable, boxed, _) in enumerate(PEOPLE):
                if postgres and reason is not None and len(reason) > 200:
                    continue
                connection.execute(
                    text(
                        "INSERT INTO observations (camera_id, frame_id, person_index, shoulder_x_px, shoulder_y_px, "
                        "ankle_x_px, ankle_y_px, usable, unusable_reason, cell, box_left_px) "
                        "VALUES ('c', :frame, :index, 1, 1, :ankle, :ankle, :usable, :reason, 0, :box)"
                    ),
                    {
                        "frame": frame_id,
                        "index": index,
                        "usable": usable,
                        "reason": reason,
                        "box": 1.0 if boxed else None,
                        "ankle": None if reason == "ankle centre not visible" else 2.0,
                    },
                )
        assert not NEW_COLUMNS & observation_columns(database_url)
        upgrade(database_url, "0014")
        assert NEW_COLUMNS <= observation_columns(database_url)
        with engine.connect() as connection:
            stored = connection.execute(
                text("SELECT person_index, posture, placed_from_box, static FROM observations ORDER BY person_index")
            ).all()
        expected = [
            (index, *verdict)
            for index, (reason, _, _, verdict) in enumerate(PEOPLE)
            if not (postgres and reason is not None and len(reason) > 200)
        ]
        assert [(row[0], row[1], bool(row[2]), bool(row[3])) for row in stored] == expected
        command.downgrade(alembic_config(database_url), "0013")
        assert not NEW_COLUMNS & observation_columns(database_url)
        with engine.connect() as connection:
            kept = connection.execute(text("SELECT person_index FROM observations ORDER BY person_index"))
            assert kept.scalars().all() == [row[0] for row in expected]
    finally:
        engine.dispose()
    upgrade(database_url)
