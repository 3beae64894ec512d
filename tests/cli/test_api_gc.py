"""`posemetry api` and `serve` build the API with a quieter garbage collector (service.cli.API_GC_THRESHOLDS)."""

from __future__ import annotations

import gc
import logging
from collections.abc import Iterator
from pathlib import Path

import pytest

from service.cli import processes as cli
from service.settings import get_settings


@pytest.fixture
def restored_gc() -> Iterator[None]:
    """The collector's settings and the root logger (create_api configures logging) as they were."""
    thresholds = gc.get_threshold()
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    gc.unfreeze()
    gc.set_threshold(*thresholds)
    root.handlers[:] = handlers
    root.setLevel(level)


def test_the_api_factory_freezes_start_up_objects_and_collects_less_often(
    restored_gc: None, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("POSEMETRY_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("POSEMETRY_REDIS_URL", "redis://127.0.0.1:1/0")  # never reached while building the app
    get_settings.cache_clear()
    try:
        gc.unfreeze()
        app = cli.create_api()
    finally:
        get_settings.cache_clear()
    assert app.title
    assert gc.get_threshold() == cli.API_GC_THRESHOLDS
    assert gc.get_freeze_count() > 10_000  # the modules and the app, out of the collector's sight
