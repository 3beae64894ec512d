"""Sessions for work outside a request (jobs, commands, benchmarks): one engine per process and database URL.

The API builds its own engine per app (service.app); everything else asks here. Engines are keyed by pid: a
forking worker's child must not reuse connections opened by its parent (SQLite and PostgreSQL connections are
not fork-safe), so each process builds its own on first use.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

from sqlalchemy import Engine
from sqlalchemy.orm import Session, sessionmaker

from service.settings import Settings, get_settings

from .db import make_engine, make_session_factory

_engines: dict[tuple[int, str], tuple[Engine, sessionmaker[Session], sessionmaker[Session]]] = {}


def _factories(settings: Settings) -> tuple[sessionmaker[Session], sessionmaker[Session]]:
    """(writing, read-only) session factories on the configured database."""
    key = (os.getpid(), settings.database_url)
    if key not in _engines:
        engine = make_engine(settings.database_url, busy_timeout_s=settings.database_busy_timeout_s)
        _engines[key] = (engine, make_session_factory(engine), make_session_factory(engine, read_only=True))
    return _engines[key][1], _engines[key][2]


def session_factory(settings: Settings | None = None) -> sessionmaker[Session]:
    """Writing sessions on the configured database."""
    return _factories(settings or get_settings())[0]


def read_session_factory(settings: Settings | None = None) -> sessionmaker[Session]:
    """Read-only sessions: on SQLite they neither wait for nor hold the write lock."""
    return _factories(settings or get_settings())[1]


@contextmanager
def transaction(settings: Settings | None = None) -> Iterator[Session]:
    """A writing session in a transaction, committed when the block ends (rolled back if it raises)."""
    with session_factory(settings)() as session, session.begin():
        yield session


def dispose_engines() -> None:
    """Close this process's connections (before forking, and in tests that swap databases)."""
    for (pid, _url), (engine, _factory, _read) in list(_engines.items()):
        if pid == os.getpid():
            engine.dispose()
    _engines.clear()
