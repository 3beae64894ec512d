"""Database fixtures (a pytest plugin, see tests/conftest.py): real SQLite files and a real, throwaway PostgreSQL.

`database_url` is an empty database (for migration tests); `migrated_url`, `engine` and `session` give a fresh
database already at the head revision, on the test's `backend`: SQLite, unless the test parametrises `backend`
itself or its module is marked `pytestmark = pytest.mark.both_backends` (every repository test is: portability
is the point), which runs each of its tests that touches a database on both. Migrating once per backend and
copying the result (a file copy for SQLite, CREATE DATABASE ... TEMPLATE for PostgreSQL) keeps each test's setup
to milliseconds.

Without PostgreSQL binaries the PostgreSQL variants are skipped (with the reason shown), unless
POSEMETRY_TESTS_REQUIRE_POSTGRES=1, which turns that into a failure; `.ci/run` installs PostgreSQL.
"""

from __future__ import annotations

import itertools
import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import Engine
from sqlalchemy.orm import Session

from service.store import make_engine, make_session_factory
from service.store.migrate import upgrade
from tests.support.postgres import PostgresCluster, cluster_or_skip

BACKENDS = ("sqlite", "postgresql")
PG_TEMPLATE = "posemetry_template"
_database_numbers = itertools.count()


@pytest.fixture(scope="session")
def postgres_cluster() -> Iterator[PostgresCluster]:
    cluster = cluster_or_skip()
    try:
        yield cluster.start()
    finally:
        cluster.stop()


@pytest.fixture(scope="session")
def sqlite_template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("sqlite-template") / "template.sqlite3"
    upgrade(f"sqlite:///{path}")
    return path


@pytest.fixture(scope="session")
def postgres_template(postgres_cluster: PostgresCluster) -> str:
    upgrade(postgres_cluster.create_database(PG_TEMPLATE))
    return PG_TEMPLATE


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "both_backends: run the tests that use a database on SQLite and PostgreSQL")


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    """Tests marked `both_backends` that use a database (through any fixture) run once per backend."""
    if "backend" not in metafunc.fixturenames or metafunc.definition.get_closest_marker("both_backends") is None:
        return
    direct = (m.args[0] for m in metafunc.definition.iter_markers("parametrize"))
    if not any("backend" in (names.split(",") if isinstance(names, str) else names) for names in direct):
        metafunc.parametrize("backend", BACKENDS, indirect=True)


@pytest.fixture
def backend(request: pytest.FixtureRequest) -> str:
    """SQLite, unless the test parametrises `backend` (directly, or through the `both_backends` mark)."""
    return str(getattr(request, "param", "sqlite"))


def _postgres_database(request: pytest.FixtureRequest, template: str | None) -> Iterator[str]:
    cluster: PostgresCluster = request.getfixturevalue("postgres_cluster")
    name = f"test_{next(_database_numbers)}"
    yield cluster.create_database(name, template=template)
    cluster.drop_database(name)


@pytest.fixture
def database_url(backend: str, request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """An empty database on the test's backend."""
    if backend == "sqlite":
        yield f"sqlite:///{tmp_path / 'empty.sqlite3'}"
    else:
        yield from _postgres_database(request, template=None)


@pytest.fixture
def migrated_url(backend: str, request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[str]:
    """A fresh database at the head revision on the test's backend."""
    if backend == "sqlite":
        path = tmp_path / "store.sqlite3"
        shutil.copyfile(request.getfixturevalue("sqlite_template"), path)
        yield f"sqlite:///{path}"
    else:
        yield from _postgres_database(request, template=request.getfixturevalue("postgres_template"))


@pytest.fixture
def engine(migrated_url: str) -> Iterator[Engine]:
    engine = make_engine(migrated_url, busy_timeout_s=10.0)
    yield engine
    engine.dispose()


@pytest.fixture
def session(engine: Engine) -> Iterator[Session]:
    with make_session_factory(engine)() as session:
        yield session
