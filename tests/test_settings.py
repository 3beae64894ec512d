"""Settings: environment overrides, the derived SQLite default, validation, and documented fields."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from service.settings import Settings, get_settings, settings_table


def test_defaults_put_a_sqlite_file_in_the_data_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    for name in ("DATA_DIR", "DATABASE_URL", "REDIS_URL"):
        monkeypatch.delenv(f"POSEMETRY_{name}", raising=False)
    settings = Settings()
    assert settings.data_dir == tmp_path / "var"
    assert settings.database_url == f"sqlite:///{tmp_path / 'var' / 'posemetry.sqlite3'}"
    assert settings.redis_url is None


def test_environment_overrides(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("POSEMETRY_DATABASE_URL", "postgresql://db/posemetry")
    monkeypatch.setenv("POSEMETRY_CALIBRATION_SAMPLE_CAP", "500")
    monkeypatch.setenv("POSEMETRY_REDIS_URL", "redis://localhost:6379/0")
    settings = Settings()
    assert settings.database_url == "postgresql://db/posemetry"
    assert settings.calibration_sample_cap == 500
    assert settings.redis_url == "redis://localhost:6379/0"


def test_invalid_values_are_refused() -> None:
    with pytest.raises(ValidationError):
        Settings(calibration_growth_factor=1.0)
    with pytest.raises(ValidationError):
        Settings(max_people_per_frame=0)


def test_every_field_is_documented() -> None:
    """The descriptions become the README configuration table."""
    for name, info in Settings.model_fields.items():
        assert info.description and len(info.description) > 30, name


def test_get_settings_is_read_once(monkeypatch: pytest.MonkeyPatch) -> None:
    get_settings.cache_clear()
    try:
        monkeypatch.setenv("POSEMETRY_MAX_BODY_BYTES", "4096")
        first = get_settings()
        monkeypatch.setenv("POSEMETRY_MAX_BODY_BYTES", "8192")
        assert get_settings() is first and first.max_body_bytes == 4096
    finally:
        get_settings.cache_clear()


def test_readme_configuration_table_is_current() -> None:
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    assert settings_table() in readme, (
        "README's configuration table is stale: replace it with the output of "
        '`.venv/bin/python -c "from service.settings import settings_table; print(settings_table())"`'
    )
