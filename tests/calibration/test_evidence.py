"""The calibration's evidence in the store, on SQLite and PostgreSQL: keyed in bulk, sampled balanced over the grid."""

from __future__ import annotations

from collections import Counter
from dataclasses import replace

import numpy as np
import pytest
from sqlalchemy import event, select, text, update
from sqlalchemy.orm import Session

from service.calibration.evidence import (
    GRID_CELLS,
    _CellCursor,
    _page_parameters,
    _round_statement,
    key_new_evidence,
    observation_links,
    sample_evidence,
    sample_key,
)
from service.geometry.appearance import DESCRIPTOR_BYTES
from service.geometry.evidence import SAMPLE_GRID, balanced_sample, grid_cells
from service.store.models import Observation
from tests.support.store import (
    GRID_COLS,
    SIZE_PX,
    add_camera,
    add_frame,
    count,
    key_everyone,
    person_in_cell,
    populate_cells,
)

pytestmark = pytest.mark.both_backends


def test_grid_cell_buckets_and_clamps() -> None:
    def grid_cell(x_px: float, y_px: float, width_px: int, height_px: int) -> int:
        return int(grid_cells(np.array([[x_px, y_px]]), (width_px, height_px))[0])

    assert grid_cell(0.0, 0.0, 1920, 1080) == 0
    assert grid_cell(1919.9, 1079.9, 1920, 1080) == GRID_CELLS - 1
    assert grid_cell(-50.0, 2000.0, 1920, 1080) == GRID_CELLS - GRID_COLS
    assert grid_cell(240.0, 135.0, 1920, 1080) == GRID_COLS + 1


def test_people_are_stored_unkeyed_and_keyed_in_bulk_oldest_first(session: Session) -> None:
    add_camera(session, "cam-1")
    add_camera(session, "cam-2")
    frames = [add_frame(session, "cam-1", [person_in_cell(3), person_in_cell(40)]) for _ in range(3)]
    add_frame(session, "cam-2", [person_in_cell(3)])
    session.commit()
    assert count(session, Observation, sample_key=None) == 7
    assert len(sample_evidence(session, "cam-1", cap=50)) == 0  # unkeyed people are not sampled yet

    assert key_new_evidence(session, "cam-1", limit=4) == 4
    session.commit()
    keyed = session.execute(
        select(Observation.id, Observation.frame_id, Observation.sample_key)
        .where(Observation.sample_key.is_not(None))
        .order_by(Observation.id)
    ).all()
    assert [row.frame_id for row in keyed] == [frames[0].id, frames[0].id, frames[1].id, frames[1].id]
    assert [row.sample_key for row in keyed] == [sample_key(row.id) for row in keyed]
    assert len(sample_evidence(session, "cam-1", cap=50)) == 4

    assert key_everyone(session, "cam-1") == 2
    assert key_new_evidence(session, "cam-1", limit=10) == 0
    assert len(sample_evidence(session, "cam-1", cap=50)) == 6
    assert count(session, Observation, camera_id="cam-2", sample_key=None) == 1  # other cameras wait their turn
    with pytest.raises(ValueError):
        key_new_evidence(session, "cam-1", limit=0)


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


@pytest.mark.parametrize("wrapped", [False, True])
def test_a_sample_page_scans_one_cell_of_the_sampling_index(session: Session, wrapped: bool) -> None:
    """The statement the sampler runs, with its bounds: on the cell's range of the sampling index, not on the
    camera's whole key range (SQLite took that other index once the key's upper bound was a plain bound too)."""
    cursor = _CellCursor(start=5_000, wrapped=wrapped, last=(7_000, 3) if not wrapped else (2_000, 3))
    stmt = _round_statement(2).params(
        camera_id="c", epoch=1, **_page_parameters(0, 3, cursor, 10), **_page_parameters(1, 4, _CellCursor(9), 10)
    )
    sql = str(stmt.compile(session.get_bind(), compile_kwargs={"literal_binds": True}))
    if session.get_bind().dialect.name == "sqlite":
        plan = " ".join(row[-1] for row in session.execute(text(f"EXPLAIN QUERY PLAN {sql}")))
        assert plan.count("ix_observations_camera_id_epoch_usable_cell_sample_key (") == 2, plan
    else:
        session.execute(text("SET LOCAL enable_seqscan = off"))
        plan = " ".join(row[0] for row in session.execute(text(f"EXPLAIN {sql}")))
    assert "SCAN observations" not in plan and "Seq Scan" not in plan, plan


def test_samples_reuse_one_statement_per_number_of_cells(session: Session) -> None:
    """Every value of a round is bound, so SQLAlchemy compiles a statement per number of cells read, not one per
    mix of cursor states (which made compiling most of a solve's CPU under load)."""
    add_camera(session)
    populate_cells(session, {cell: 3 + (cell * 7) % 11 for cell in range(0, GRID_CELLS, 2)})
    statements: list[str] = []

    def record(conn: object, cursor: object, statement: str, *args: object) -> None:
        if "UNION ALL" in statement or "ORDER BY" in statement:
            statements.append(statement)

    engine = session.get_bind()
    event.listen(engine, "before_cursor_execute", record)
    try:
        for seed in range(6):
            sample_evidence(session, "cam-1", cap=150, seed=seed)
    finally:
        event.remove(engine, "before_cursor_execute", record)
    pages = {statement: statement.count("ORDER BY") for statement in statements}
    assert len(statements) > len(pages) and len(set(pages.values())) == len(pages) > 1


def test_sample_is_spatially_balanced_capped_and_reads_little(session: Session) -> None:
    add_camera(session)
    sparse = {cell: 10 for cell in range(10, 30)}
    populate_cells(session, {0: 1000, **sparse})
    sample = sample_evidence(session, "cam-1", cap=300, seed=7)

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

    small = sample_evidence(session, "cam-1", cap=40, seed=7)
    assert len(small) == 40 and max(Counter(small.cells).values()) == 2  # 21 cells, round-robin


def test_sample_is_deterministic_per_seed_and_random_across_seeds(session: Session) -> None:
    add_camera(session)
    populate_cells(session, {0: 400, 9: 400})
    first = sample_evidence(session, "cam-1", cap=100, seed=1)
    again = sample_evidence(session, "cam-1", cap=100, seed=1)
    other = sample_evidence(session, "cam-1", cap=100, seed=2)
    assert first.observation_ids == again.observation_ids
    assert set(first.observation_ids) != set(other.observation_ids)
    assert Counter(first.cells) == Counter(other.cells) == {0: 50, 9: 50}


@pytest.mark.parametrize("seed", [0, 3, 11])
def test_a_cap_above_the_evidence_returns_every_usable_observation_once(session: Session, seed: int) -> None:
    """Reading each cell from a seeded start and wrapping around must neither skip nor repeat anyone."""
    add_camera(session)
    usable_ids = populate_cells(session, {0: 37, 5: 3, 63: 61, 20: 1})
    for cap in (len(usable_ids), len(usable_ids) + 50):
        sample = sample_evidence(session, "cam-1", cap=cap, seed=seed)
        assert sorted(sample.observation_ids) == sorted(usable_ids)


def test_sample_keys_that_tie_are_not_skipped(session: Session) -> None:
    add_camera(session)
    usable_ids = populate_cells(session, {12: 40})
    session.execute(update(Observation).values(sample_key=123_456))
    session.commit()
    sample = sample_evidence(session, "cam-1", cap=1000, seed=0)
    assert sorted(sample.observation_ids) == sorted(usable_ids)


def test_sample_of_a_camera_without_evidence_is_empty(session: Session) -> None:
    add_camera(session)
    sample = sample_evidence(session, "cam-1", cap=50)
    assert len(sample) == 0 and sample.tops_px.shape == (0, 2)
    with pytest.raises(ValueError):
        sample_evidence(session, "cam-1", cap=0)


# --------------------------------------------------------------------------------------------------- one grid


@pytest.mark.parametrize(("cap", "most_apart"), [(30, 0), (31, 1), (45, 1)])
def test_the_store_and_the_in_memory_sampler_agree(session: Session, cap: int, most_apart: int) -> None:
    """The store's sampler (the workers' solves) and the in-memory one (`posemetry analyze`) use one grid: on the
    same people they find the same cells and fill them alike, each cell the same count up to the last level's
    random remainder."""
    add_camera(session)
    per_cell = {0: 40, 9: 3, 27: 12, 63: 25}
    ids = populate_cells(session, per_cell)
    rows = session.execute(
        select(Observation.cell, Observation.ankle_x_px, Observation.ankle_y_px).where(Observation.id.in_(ids))
    ).all()
    ankles = np.array([(row.ankle_x_px, row.ankle_y_px) for row in rows])
    size_px = (SIZE_PX, SIZE_PX)
    assert [row.cell for row in rows] == grid_cells(ankles, size_px).tolist()

    stored = Counter(sample_evidence(session, "cam-1", cap=cap).cells)
    in_memory = Counter(grid_cells(ankles[balanced_sample(ankles, size_px, cap)], size_px).tolist())
    assert stored.total() == in_memory.total() == cap
    assert set(stored) == set(in_memory) == set(per_cell)
    assert all(abs(stored[cell] - in_memory[cell]) <= most_apart for cell in per_cell)


def test_the_stored_cells_are_the_grids() -> None:
    """The schema's check on `cell` (written out in the models, not imported) admits exactly the grid's cells."""
    (check,) = [c for c in Observation.__table__.constraints if str(c.name).endswith("cell_on_grid")]
    assert f"cell < {GRID_CELLS}" in str(check.sqltext)  # type: ignore[attr-defined]
    assert GRID_CELLS == SAMPLE_GRID[0] * SAMPLE_GRID[1]


def test_the_sample_carries_each_persons_appearance_and_none_for_posted_keypoints(session: Session) -> None:
    add_camera(session, "cam-1")
    looks = [bytes([k]) * DESCRIPTOR_BYTES for k in range(1, 4)]
    add_frame(
        session,
        "cam-1",
        [replace(person_in_cell(cell), appearance=look) for cell, look in zip((3, 9, 40), looks, strict=True)],
    )
    add_frame(session, "cam-1", [person_in_cell(20)])  # posted as keypoints: no appearance
    session.commit()
    key_everyone(session, "cam-1")
    sample = sample_evidence(session, "cam-1", cap=50)
    by_id = dict(zip(sample.observation_ids, sample.appearance, strict=True))
    stored = dict(session.execute(select(Observation.id, Observation.appearance)).all())
    assert len(by_id) == 4 and by_id == {oid: (None if blob is None else bytes(blob)) for oid, blob in stored.items()}
    assert sorted(look for look in by_id.values() if look is not None) == looks
    empty = observation_links(session, [])
    assert (len(empty.times_s), empty.appearance, empty.track_ids) == (0, [], [])


def test_the_sample_carries_each_persons_client_track_id(session: Session) -> None:
    """Track ids are read with the descriptors, in one primary-key lookup, and land on their own observations."""
    add_camera(session, "cam-1")
    add_frame(session, "cam-1", [replace(person_in_cell(3), track_id="a"), person_in_cell(9)])
    add_frame(session, "cam-1", [replace(person_in_cell(40), track_id="b"), replace(person_in_cell(5), track_id="a")])
    session.commit()
    key_everyone(session, "cam-1")
    sample = sample_evidence(session, "cam-1", cap=50)
    by_id = dict(zip(sample.observation_ids, sample.track_ids, strict=True))
    stored = dict(session.execute(select(Observation.id, Observation.client_track_id)).all())
    assert len(by_id) == 4 and by_id == stored
    assert sorted(track for track in by_id.values() if track is not None) == ["a", "a", "b"]
    assert sample.appearance == [None] * 4
