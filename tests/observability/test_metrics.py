"""The observability pieces that need no server: the metrics directory's lifecycle, the webhook counter's
contract, and the text log format."""

from __future__ import annotations

import io
import logging
import os
import subprocess
import sys
from pathlib import Path

import pytest
from prometheus_client import REGISTRY

from service.observability.logs import RedactingFormatter, TextFormatter, configure_logging, log_context
from service.observability.metrics import WEBHOOK_OUTCOMES, record_webhook_delivery
from service.observability.multiprocess import ENV, sweep_dead_processes, use_directory
from service.observability.request_id import accepted_request_id, request_id_context


def _dead_pid() -> int:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


def test_a_serve_start_clears_the_metrics_left_by_the_last_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(ENV, str(tmp_path))  # as if set before prometheus_client was imported here
    (tmp_path / "counter_123.db").write_bytes(b"old")
    (tmp_path / "notes.txt").write_text("not ours")
    assert use_directory(tmp_path, clear=True) == tmp_path
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]


def test_the_directory_cannot_change_once_prometheus_client_is_loaded(tmp_path: Path) -> None:
    assert "prometheus_client" in sys.modules  # imported by this test module
    with pytest.raises(RuntimeError, match=ENV):
        use_directory(tmp_path / "elsewhere", clear=True)


def test_a_sweep_forgets_dead_processes_live_gauges_but_keeps_their_counters(tmp_path: Path) -> None:
    dead, alive = _dead_pid(), os.getpid()
    files = [
        f"gauge_livesum_{dead}.db",
        f"gauge_livesum_{dead}-horse.db",
        f"gauge_liveall_{dead}.db",
        f"counter_{dead}.db",
        f"histogram_{dead}.db",
        f"gauge_livesum_{alive}.db",
    ]
    for name in files:
        (tmp_path / name).write_bytes(b"")
    assert sweep_dead_processes(tmp_path) == [dead]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [f"counter_{dead}.db", f"histogram_{dead}.db", f"gauge_livesum_{alive}.db"]
    )


def test_webhook_deliveries_are_counted_by_a_bounded_outcome() -> None:
    def delivered() -> float:
        return REGISTRY.get_sample_value("posemetry_webhook_deliveries_total", {"outcome": "delivered"}) or 0.0

    before = delivered()
    record_webhook_delivery("delivered")
    assert delivered() == before + 1
    assert all(
        REGISTRY.get_sample_value("posemetry_webhook_deliveries_total", {"outcome": o}) is not None
        for o in WEBHOOK_OUTCOMES
    )  # exported as 0 before the first delivery
    with pytest.raises(ValueError, match="delivered"):
        record_webhook_delivery("HTTP 502 from https://example.invalid")  # type: ignore[arg-type]


def test_text_lines_append_their_context() -> None:
    stream = io.StringIO()
    root = logging.getLogger()
    level = root.level
    configure_logging("text", "info", stream=stream)
    handler = root.handlers[-1]
    try:
        with request_id_context("req-9"), log_context(job_id="job-1"), log_context(camera_id="lobby"):
            try:
                raise ValueError("boom")
            except ValueError:
                logging.getLogger("workers.jobs").exception("solve failed")
        logging.getLogger("workers.jobs").info("outside")
        logging.getLogger("alembic.runtime.plugins").info("setup plugin alembic.autogenerate.schemas")  # start noise
    finally:
        root.removeHandler(handler)
        root.setLevel(level)
    first, *traceback, last = stream.getvalue().splitlines()
    assert first.endswith("ERROR workers.jobs: solve failed request_id=req-9 job_id=job-1 camera_id=lobby")
    assert traceback[-1] == "ValueError: boom"
    assert last.endswith("INFO workers.jobs: outside")
    assert isinstance(handler.formatter, RedactingFormatter) and isinstance(handler.formatter.inner, TextFormatter)


@pytest.mark.parametrize(
    ("value", "accepted"),
    [(b"abc-1", "abc-1"), ("trace:7.x_y", "trace:7.x_y"), (b"\xff\xfe", None), ("", None), (None, None)],
)
def test_request_id_acceptance(value: str | bytes | None, accepted: str | None) -> None:
    assert accepted_request_id(value) == accepted
