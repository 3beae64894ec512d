"""Engines and sessions for SQLite (one machine) and PostgreSQL (production), configured so both behave alike.

SQLite needs the most help: foreign keys are off unless asked for on every connection (and the schema relies on
ON DELETE CASCADE); WAL lets readers proceed while one process writes; the busy timeout makes a second writer
wait instead of failing at once; and transactions that may write start with BEGIN IMMEDIATE. That last one
matters because the API and the workers are separate processes: a deferred transaction that reads and then
writes fails with "database is locked" immediately (no waiting) when another process committed in between,
whereas an immediate one takes the write lock up front and simply queues on the busy timeout. Sessions that only
read (`make_session_factory(engine, read_only=True)`) begin DEFERRED instead: in WAL mode they never wait for the
writer, which is what keeps GETs and the workers' reads off the one write lock.

Within one process, writers also queue on a Python lock before asking SQLite for its lock. SQLite's busy handler
polls with sleeps of up to 100 ms, so sixteen request threads fighting over the lock sleep far longer than any of
them holds it (seen as p99 latencies of seconds at 40 frames/s); a Python lock wakes the next writer the moment
the previous one commits, and leaves only the few processes (the API, each worker) to SQLite's polling.

Python 3.11's sqlite3 driver also has to be told to stop managing transactions itself, or SAVEPOINTs (used for
idempotent inserts) do not nest.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, create_engine, event
from sqlalchemy import exc as sa_exc
from sqlalchemy.engine import URL, make_url
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.pool import StaticPool

POSTGRES_DRIVER = "postgresql+psycopg"
# Execution option naming how a SQLite transaction begins (IMMEDIATE unless a read-only session says DEFERRED).
SQLITE_BEGIN = "posemetry_sqlite_begin"
# Kept-open SQLite connections per engine: about two per request thread of the API's thread pool.
SQLITE_POOL_SIZE = 48
# How often a writer retries SQLite's write lock while another process holds it (see _begin_immediate).
WRITE_POLL_S = 0.0005
# Connection-record flag: this connection's transaction holds the engine's in-process write lock.
_HOLDS_WRITE_LOCK = "posemetry_holds_write_lock"
# How long opening a PostgreSQL connection may take: a database host that drops packets would otherwise hold a
# request (or a job) for the operating system's TCP timeout, minutes, before it can be answered 503.
POSTGRES_CONNECT_TIMEOUT_S = 10


class EncodedJSON(str):
    """A JSON column value already encoded (e.g. by pydantic's `model_dump_json`), stored as it is.

    Encoding a batch of frame results is the slowest part of writing them; done before the transaction, it no
    longer holds SQLite's one write lock while the API waits.
    """


def _json_dumps(value: Any) -> str:
    """Strict JSON: PostgreSQL rejects NaN and Infinity, so they must fail on SQLite too rather than in production."""
    if isinstance(value, EncodedJSON):
        return str(value)
    return json.dumps(value, allow_nan=False, separators=(",", ":"))


def is_database_unavailable(exc: BaseException) -> bool:
    """Whether an error means the database cannot be used right now (down, restarting, unreachable, locked past the
    busy timeout, read-only, out of pooled connections), rather than that a statement was wrong: the API answers
    the first kind with 503 and the workers retry it; the second kind is a bug."""
    if isinstance(exc, sa_exc.OperationalError | sa_exc.InterfaceError | sa_exc.TimeoutError):
        return True
    return isinstance(exc, sa_exc.DBAPIError) and exc.connection_invalidated


def normalise_url(url: str | URL) -> URL:
    """Point plain `postgresql://` and `postgres://` URLs at psycopg 3, the only PostgreSQL driver installed."""
    parsed = make_url(url) if isinstance(url, str) else url
    if parsed.drivername in ("postgresql", "postgres"):
        parsed = parsed.set(drivername=POSTGRES_DRIVER)
    return parsed


def is_sqlite_memory(url: URL) -> bool:
    return url.get_backend_name() == "sqlite" and url.database in (None, "", ":memory:")


def make_engine(url: str | URL, *, busy_timeout_s: float = 30.0, echo: bool = False) -> Engine:
    """An engine for `url` with the per-backend settings described in the module docstring.

    For a SQLite file, its directory is created, so a fresh `data_dir` works without a setup step.
    """
    parsed = normalise_url(url)
    backend = parsed.get_backend_name()
    if backend == "sqlite":
        return _sqlite_engine(parsed, busy_timeout_s=busy_timeout_s, echo=echo)
    if backend == "postgresql":
        # pre-ping: a restarted or briefly unreachable database costs one failed request, not a restart.
        connect_args = {} if "connect_timeout" in parsed.query else {"connect_timeout": POSTGRES_CONNECT_TIMEOUT_S}
        return create_engine(
            parsed, echo=echo, pool_pre_ping=True, json_serializer=_json_dumps, connect_args=connect_args
        )
    raise ValueError(f"unsupported database {parsed.render_as_string(hide_password=True)}: use sqlite or postgresql")


def _sqlite_engine(url: URL, *, busy_timeout_s: float, echo: bool) -> Engine:
    memory = is_sqlite_memory(url)
    if not memory and url.database is not None:
        Path(url.database).expanduser().parent.mkdir(parents=True, exist_ok=True)
    # isolation_level=None: the driver stops issuing its own BEGINs; the "begin" hook below issues ours.
    connect_args: dict[str, Any] = {"isolation_level": None}
    kwargs: dict[str, Any] = {}
    if memory:
        # An in-memory database exists once per connection: share one connection, across threads too.
        connect_args["check_same_thread"] = False
        kwargs["poolclass"] = StaticPool
    else:
        # Every request thread holds up to two connections (a read and a write session). With SQLAlchemy's
        # default pool of 5 the overflow connections are opened and closed per request, each paying the pragmas
        # below: a third of the API's CPU under load. SQLite connections are cheap to keep open.
        kwargs["pool_size"] = SQLITE_POOL_SIZE
        kwargs["max_overflow"] = SQLITE_POOL_SIZE
    engine = create_engine(url, echo=echo, connect_args=connect_args, json_serializer=_json_dumps, **kwargs)
    busy_timeout_ms = int(busy_timeout_s * 1000)

    @event.listens_for(engine, "connect")
    def _configure(dbapi_connection: Any, _record: Any) -> None:
        cursor = dbapi_connection.cursor()
        try:
            if not memory:
                cursor.execute("PRAGMA journal_mode=WAL")
                # In WAL mode NORMAL never corrupts and loses nothing on a process crash; only an OS crash or
                # power cut can lose the last commits. FULL would fsync on every frame.
                cursor.execute("PRAGMA synchronous=NORMAL")
            cursor.execute("PRAGMA foreign_keys=ON")
            cursor.execute(f"PRAGMA busy_timeout={busy_timeout_ms}")
        finally:
            cursor.close()

    write_lock = threading.Lock()

    def _release(connection: Any) -> None:
        if connection.info.pop(_HOLDS_WRITE_LOCK, False):
            write_lock.release()

    @event.listens_for(engine, "begin")
    def _begin(connection: Any) -> None:
        mode = connection.get_execution_options().get(SQLITE_BEGIN, "IMMEDIATE")
        if mode != "IMMEDIATE":
            connection.exec_driver_sql(f"BEGIN {mode}")
            return
        write_lock.acquire()
        connection.info[_HOLDS_WRITE_LOCK] = True
        try:
            _begin_immediate(connection.connection.driver_connection, busy_timeout_s)
        except sqlite3.Error as exc:
            _release(connection)
            # Raised from an event hook, the driver's error would reach callers unwrapped; as SQLAlchemy's own
            # type it is handled like any other ("database is locked" past the busy timeout: unavailable).
            raise sa_exc.OperationalError("BEGIN IMMEDIATE", None, exc) from exc
        except BaseException:
            _release(connection)
            raise

    # Both fire just before the COMMIT/ROLLBACK itself; the next writer then waits that long on SQLite's lock.
    event.listen(engine, "commit", _release)
    event.listen(engine, "rollback", _release)

    return engine


def _begin_immediate(raw: Any, busy_timeout_s: float) -> None:
    """BEGIN IMMEDIATE, waiting for another process's write lock by polling every WRITE_POLL_S.

    SQLite's own busy handler backs off to sleeps of 100 ms, so a writer that finds the lock taken for a
    millisecond (a worker committing a batch) typically sleeps tens of milliseconds, with every request of its
    process queued behind it. Polling at a fixed fine interval waits about as long as the lock is actually held.
    The connection's busy timeout is switched off for this one statement and restored after.
    """
    deadline = time.monotonic() + busy_timeout_s
    raw.execute("PRAGMA busy_timeout=0")
    try:
        while True:
            try:
                raw.execute("BEGIN IMMEDIATE")
                return
            except sqlite3.OperationalError as exc:
                if "locked" not in str(exc) or time.monotonic() >= deadline:
                    raise
                time.sleep(WRITE_POLL_S)
    finally:
        raw.execute(f"PRAGMA busy_timeout={int(busy_timeout_s * 1000)}")


def make_session_factory(engine: Engine, *, read_only: bool = False) -> sessionmaker[Session]:
    """Sessions whose objects stay readable after commit, so a route can commit and then serialise the result.

    `read_only` sessions begin DEFERRED on SQLite (see the module docstring) and must not write: a deferred
    transaction that tries to is refused whenever another process committed since it began.
    """
    bind = engine.execution_options(**{SQLITE_BEGIN: "DEFERRED"}) if read_only else engine
    return sessionmaker(bind=bind, expire_on_commit=False)
