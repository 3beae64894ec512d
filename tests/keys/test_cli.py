"""`posemetry keys` on a real database (SQLite and PostgreSQL), checked against the real app."""

from __future__ import annotations

import re
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner, Result

from service.app import create_app
from service.cli import app as cli
from service.keys import repository as stored_keys
from service.settings import Settings, get_settings
from service.store import make_engine, make_session_factory
from tests.support.dispatch import RecordingDispatcher

pytestmark = pytest.mark.both_backends

TOKEN = re.compile(r"pm_[0-9a-f]{12}_[0-9A-Za-z]{43}")


@pytest.fixture
def database(migrated_url: str, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    monkeypatch.setenv("POSEMETRY_DATABASE_URL", migrated_url)
    monkeypatch.delenv("POSEMETRY_ADMIN_KEY", raising=False)
    get_settings.cache_clear()
    yield migrated_url
    get_settings.cache_clear()


def keys(*args: str) -> Result:
    return CliRunner().invoke(cli, ["keys", *args])


def api(database: str, token: str, tmp_path: Path) -> TestClient:
    settings = Settings(database_url=database, data_dir=tmp_path, api_key_cache_ttl_s=0)
    return TestClient(
        create_app(settings, dispatcher=RecordingDispatcher()), headers={"Authorization": f"Bearer {token}"}
    )


def test_create_prints_the_token_alone_on_stdout(database: str, tmp_path: Path) -> None:
    result = keys("create", "--name", "gateway", "--camera", "lobby", "--camera", "hall", "--expires-in", "30d")
    assert result.exit_code == 0, result.output
    token = result.stdout.strip()
    assert TOKEN.fullmatch(token), result.stdout
    assert "created API key" in result.stderr and "shown only now" in result.stderr and token not in result.stderr
    with api(database, token, tmp_path) as client:
        me = client.get("/v1/keys/current").json()
        assert me["name"] == "gateway" and me["cameras"] == ["hall", "lobby"] and not me["admin"]
        expires = datetime.fromisoformat(me["expires_at"])
        assert abs(expires - (datetime.now(UTC) + timedelta(days=30))) < timedelta(minutes=1)
        assert client.get("/v1/cameras/elsewhere").status_code == 403
        assert client.get("/v1/keys").status_code == 403


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_admin_key_for_recovery_then_list_and_revoke(database: str, tmp_path: Path) -> None:
    created = keys("create", "--name", "ops on call", "--admin")
    assert created.exit_code == 0, created.output
    admin_token = created.stdout.strip()
    plain = keys("create", "--name", "dashboard").stdout.strip()
    plain_id = plain.split("_")[1]
    with api(database, admin_token, tmp_path) as admin:
        assert admin.get("/v1/keys").status_code == 200
        listing = keys("list")
        assert listing.exit_code == 0, listing.output
        assert "ops on call" in listing.stdout and "dashboard" in listing.stdout and plain_id in listing.stdout
        assert admin_token not in listing.stdout and plain not in listing.stdout

        revoked = keys("revoke", plain_id)
        assert revoked.exit_code == 0, revoked.output
        assert "revoked API key" in revoked.stderr
        with api(database, plain, tmp_path) as client:
            assert client.get("/v1/cameras").status_code == 401
        assert admin.get(f"/v1/keys/{plain_id}").json()["created_by"] == "posemetry keys"
    assert plain_id not in keys("list").stdout
    assert plain_id in keys("list", "--all").stdout
    assert keys("revoke", "0123456789ab").exit_code == 1


@pytest.mark.parametrize(
    "args",
    [
        ["--name", "x", "--admin", "--camera", "lobby"],
        ["--name", "x", "--camera", "../etc"],
        ["--name", "x", "--expires-in", "soon"],
        ["--name", "x", "--expires-in", "0d"],
        ["--name", ""],
    ],
)
def test_invalid_create_options_store_nothing(database: str, args: list[str]) -> None:
    result = keys("create", *args)
    assert result.exit_code == 2, result.output
    engine = make_engine(database)
    try:
        with make_session_factory(engine)() as session:
            assert stored_keys.list_keys(session, include_revoked=True) == []
    finally:
        engine.dispose()


def test_an_unmigrated_database_is_reported(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("POSEMETRY_DATABASE_URL", f"sqlite:///{tmp_path / 'empty.sqlite3'}")
    get_settings.cache_clear()
    try:
        result = keys("create", "--name", "x")
    finally:
        get_settings.cache_clear()
    assert result.exit_code == 1
    assert "posemetry db upgrade" in result.stderr
