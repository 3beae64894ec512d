"""The calibration's evidence in the store: every usable person keyed for sampling, and balanced samples of them.

People are stored with the sampling-grid cell of their ankle centre (service.geometry.evidence.grid_cells, the
grid the in-memory sampler of `posemetry analyze` uses too) and, once the next solve of their camera starts, a
pseudo-random sample key. A sample then reads a few index ranges per cell, whatever is stored.
"""

from __future__ import annotations

import functools
import random
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any, cast

import numpy as np
from sqlalchemy import (
    BigInteger,
    ColumnElement,
    Executable,
    Integer,
    Select,
    Table,
    bindparam,
    literal,
    select,
    true,
    union_all,
    update,
)
from sqlalchemy.orm import Session

from service.geometry.evidence import SAMPLE_GRID
from service.store.models import SAMPLE_KEY_SPACE, Camera, Frame, Observation

GRID_CELLS = SAMPLE_GRID[0] * SAMPLE_GRID[1]
_OBSERVATIONS = cast(Table, Observation.__table__)


@dataclass(frozen=True)
class EvidenceSample:
    """A calibration's input: shoulder/ankle centres of a balanced sample of usable observations, with the capture
    time of each one's frame (seconds from the earliest), so the solve can link one person's observations.

    `queries` and `rows_read` show the sampling's cost: rows_read stays near len(self) however much is stored
    (the frame times, appearance descriptors and client track ids are one primary-key lookup per LINKS_CHUNK
    observations on top: `observation_links`).
    """

    observation_ids: list[int]
    cells: list[int]
    tops_px: np.ndarray
    bottoms_px: np.ndarray
    times_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    appearance: list[bytes | None] = field(default_factory=list)
    """Each observation's appearance descriptor (service.geometry.appearance), None for posted keypoints."""
    track_ids: list[str | None] = field(default_factory=list)
    """Each observation's client track id (service.frames.schemas.PersonObservation), None where none was posted."""
    queries: int = 0
    rows_read: int = 0

    def __len__(self) -> int:
        return len(self.observation_ids)


# Fibonacci hashing of the observation id: the odd multiplier (2^32 / golden ratio) makes it a bijection on
# [0, SAMPLE_KEY_SPACE), so ids below 2^31 never tie, and consecutive ids (one frame's people, one camera's
# minutes) land far apart and evenly over the key space, so a range of keys samples evenly over time. Computed by
# the database (products stay below 2^63 on both backends); `sample_key` is the same function in Python.
_KEY_MULTIPLIER = 2654435761


def sample_key(observation_id: int) -> int:
    return (observation_id % SAMPLE_KEY_SPACE) * _KEY_MULTIPLIER % SAMPLE_KEY_SPACE


def _sample_key_sql(observation_id: ColumnElement[int]) -> ColumnElement[int]:
    space, multiplier = literal(SAMPLE_KEY_SPACE, BigInteger), literal(_KEY_MULTIPLIER, BigInteger)
    return (observation_id % space) * multiplier % space


def key_new_evidence(session: Session, camera_id: str, *, limit: int) -> int:
    """Give up to `limit` of the camera's unkeyed people their sample keys, oldest first; returns how many.

    Keying in bulk is what keeps ingest cheap: the sampling index is random in (cell, sample_key), so one person
    per insert dirtied one index page per person, while thousands at once share pages. Callers loop over short
    transactions until this returns less than `limit`, so ingest never waits long for the write lock.
    """
    if limit < 1:
        raise ValueError(f"limit must be positive, got {limit}")
    oldest = (
        select(_OBSERVATIONS.c.id)
        .where(_OBSERVATIONS.c.camera_id == camera_id, _OBSERVATIONS.c.sample_key.is_(None))
        .order_by(_OBSERVATIONS.c.id)
        .limit(limit)
    )
    result = session.execute(
        update(_OBSERVATIONS)
        .where(_OBSERVATIONS.c.id.in_(oldest.scalar_subquery()))
        .values(sample_key=_sample_key_sql(_OBSERVATIONS.c.id))
    )
    return int(result.rowcount)  # type: ignore[attr-defined]


@dataclass
class _CellCursor:
    """Where reading one cell in sample_key order resumes: keys >= start first, then wrapping to [0, start)."""

    start: int
    wrapped: bool = False
    last: tuple[int, int] | None = None  # (sample_key, id) of the last row read
    rows: list[Any] = field(default_factory=list)


_SAMPLE_COLUMNS = tuple(
    _OBSERVATIONS.c[name]
    for name in ("id", "cell", "sample_key", "shoulder_x_px", "shoulder_y_px", "ankle_x_px", "ankle_y_px")
)


def _cell_page(index: int) -> Select[*tuple[Any, ...]]:
    """The next rows of one cell: an index range scan on (camera_id, epoch, usable, cell, sample_key). The cell,
    the rows wanted and where to resume are bound parameters suffixed `index` (see `_page_parameters`)."""
    obs = _OBSERVATIONS.c

    def parameter(name: str) -> Any:
        return bindparam(f"{name}_{index}", type_=Integer if name in ("cell", "n") else BigInteger)

    return (
        select(*_SAMPLE_COLUMNS)
        .where(
            obs.camera_id == bindparam("camera_id"),
            obs.epoch == bindparam("epoch"),
            obs.usable == true(),
            obs.cell == parameter("cell"),
            obs.sample_key.is_not(None),  # the partial index holds keyed people only
            # The plain lower bound lets both backends scan the index from the resume point; the upper one is a
            # filter only (as a bound, SQLite would scan the camera's whole key range on another index instead of
            # the cell's); the OR breaks key ties by id.
            obs.sample_key >= parameter("low"),
            obs.sample_key + 0 < parameter("high"),
            (obs.sample_key > parameter("after_key")) | (obs.id > parameter("after_id")),
        )
        .order_by(obs.sample_key, obs.id)
        .limit(parameter("n"))
    )


@functools.cache
def _round_statement(cells: int) -> Executable:
    """One round's statement for this many cells: a UNION ALL of `_cell_page`s, built once per process.

    Built from the cursors' values instead, every round's mix of cells and cursor states was a new statement for
    SQLAlchemy to compile (its cache keys on structure), about a third of a solve's CPU under load; with every
    value bound, there are at most GRID_CELLS statements, each compiled once.
    """
    pages = [_cell_page(index) for index in range(cells)]
    return pages[0] if cells == 1 else union_all(*(page.subquery().select() for page in pages))


def _page_parameters(index: int, cell: int, cursor: _CellCursor, n: int) -> dict[str, int]:
    """The bound values of page `index`: n rows of `cell` from where its cursor stands (keys >= start first, then
    wrapping to [0, start)), after the last (key, id) read, if any."""
    low, high = (0, cursor.start) if cursor.wrapped else (cursor.start, SAMPLE_KEY_SPACE)
    after_key, after_id = (low - 1, -1) if cursor.last is None else cursor.last
    values = dict(cell=cell, n=n, low=max(low, after_key), high=high, after_key=after_key, after_id=after_id)
    return {f"{name}_{index}": value for name, value in values.items()}


# Observation ids per statement when reading what links them: well under SQLite's bound-parameter limit.
LINKS_CHUNK = 900


@dataclass(frozen=True)
class Links:
    """What tells a sample's observations apart as individuals (service.geometry.tracks), in the sample's order."""

    times_s: np.ndarray
    """Each observation's frame capture time, seconds from the earliest of them."""
    appearance: list[bytes | None]
    """Appearance descriptors (service.geometry.appearance): people found in images; None for posted keypoints."""
    track_ids: list[str | None]
    """Client track ids (service.frames.schemas.PersonObservation), None where none was posted."""


def observation_links(session: Session, observation_ids: list[int]) -> Links:
    """Frame times, appearance descriptors and client track ids of the observations, by primary-key lookups.

    Read apart from the sample's index scans: none of them is in the sampling index, and reading them there would
    take every row of a cell page from the table, for columns only the linking needs."""
    found: dict[int, tuple[datetime, bytes | None, str | None]] = {}
    for start in range(0, len(observation_ids), LINKS_CHUNK):
        chunk = observation_ids[start : start + LINKS_CHUNK]
        stmt = (
            select(Observation.id, Frame.timestamp, Observation.appearance, Observation.client_track_id)
            .join(Frame, Frame.id == Observation.frame_id)
            .where(Observation.id.in_(chunk))
        )
        found.update(
            (int(oid), (stamp, None if blob is None else bytes(blob), track))
            for oid, stamp, blob, track in session.execute(stmt)
        )
    rows = [found[oid] for oid in observation_ids]
    first = min((stamp for stamp, _, _ in rows), default=None)
    return Links(
        times_s=np.array([(stamp - first).total_seconds() for stamp, _, _ in rows], dtype=float),
        appearance=[blob for _, blob, _ in rows],
        track_ids=[track for _, _, track in rows],
    )


def sample_evidence(
    session: Session, camera_id: str, *, cap: int, seed: int = 0, epoch: int | None = None
) -> EvidenceSample:
    """At most `cap` usable observations of one calibration epoch (default: the camera's current one), spread as
    evenly over the image grid as the data allow.

    Round-robin over grid cells: every cell contributes equally, and cells with fewer people than their share
    give the remainder to the others (water-filling). Within a cell the order is the stored pseudo-random
    sample_key, read from a seed-dependent start, so a sample is random, reproducible for a given seed, and
    differs between seeds. The work is O(cap + cells) rows, whatever is stored: each round is one statement, a
    UNION ALL of one LIMITed index range scan per cell that is still short of the current level (per-cell LIMIT
    subqueries are the only "top n per group" that SQLite and PostgreSQL both run without reading every row;
    window functions and LATERAL do not qualify). Typically two to four rounds.
    """
    if cap < 1:
        raise ValueError(f"cap must be positive, got {cap}")
    if epoch is None:
        epoch = session.execute(select(Camera.epoch).where(Camera.id == camera_id)).scalar_one_or_none() or 1
    rng = random.Random(seed)
    start = rng.randrange(SAMPLE_KEY_SPACE)
    cell_order = list(range(GRID_CELLS))
    rng.shuffle(cell_order)
    cursors = {cell: _CellCursor(start) for cell in range(GRID_CELLS)}
    active = set(cursors)
    level = queries = rows_read = 0
    while active:
        wanted = {cell: level - len(cursors[cell].rows) for cell in active if len(cursors[cell].rows) < level}
        if not wanted:
            total = sum(len(c.rows) for c in cursors.values())
            if total >= cap:
                break
            level += -(-(cap - total) // len(active))
            wanted = {cell: level - len(cursors[cell].rows) for cell in active}
        parameters: dict[str, Any] = {"camera_id": camera_id, "epoch": epoch}
        for index, (cell, n) in enumerate(sorted(wanted.items())):
            parameters.update(_page_parameters(index, cell, cursors[cell], n))
        rows = session.execute(_round_statement(len(wanted)), parameters).all()
        queries += 1
        rows_read += len(rows)
        by_cell: dict[int, list[Any]] = {cell: [] for cell in wanted}
        for row in rows:
            by_cell[row.cell].append(row)
        for cell, n in wanted.items():
            cursor, got = cursors[cell], sorted(by_cell[cell], key=lambda r: (r.sample_key, r.id))
            cursor.rows.extend(got)
            if got:
                cursor.last = (got[-1].sample_key, got[-1].id)
            if len(got) < n:
                if cursor.wrapped:
                    active.discard(cell)
                else:
                    cursor.wrapped, cursor.last = True, None
    chosen: list[Any] = []
    for rank in range(level):
        for cell in cell_order:
            if len(chosen) == cap:
                break
            if rank < len(cursors[cell].rows):
                chosen.append(cursors[cell].rows[rank])
    ids = [int(r.id) for r in chosen]
    links = observation_links(session, ids)
    tops = np.array([(r.shoulder_x_px, r.shoulder_y_px) for r in chosen], dtype=float).reshape(-1, 2)
    bottoms = np.array([(r.ankle_x_px, r.ankle_y_px) for r in chosen], dtype=float).reshape(-1, 2)
    return EvidenceSample(
        observation_ids=ids,
        cells=[int(r.cell) for r in chosen],
        tops_px=tops,
        bottoms_px=bottoms,
        times_s=links.times_s,
        appearance=links.appearance,
        track_ids=links.track_ids,
        queries=queries,
        rows_read=rows_read,
    )
