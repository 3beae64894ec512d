"""Capturing the service's own log output in tests: the handler and formatter the commands install, into a
buffer, then parsed line by line as JSON (every line must parse)."""

from __future__ import annotations

import io
import json
import logging
from collections.abc import Iterator
from typing import Any

import pytest

from service.observability.logs import configure_logging


@pytest.fixture
def json_log() -> Iterator[io.StringIO]:
    """The process's logging as `posemetry api`/`worker` set it up (JSON lines), into a buffer; restored after."""
    root = logging.getLogger()
    level = root.level
    stream = io.StringIO()
    configure_logging("json", "info", stream=stream)
    handler = root.handlers[-1]
    yield stream
    root.removeHandler(handler)
    root.setLevel(level)


def json_lines(stream: io.StringIO) -> list[dict[str, Any]]:
    return [json.loads(line) for line in stream.getvalue().splitlines()]
