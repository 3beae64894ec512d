"""Logging for the API and the workers: one JSON object per line (or readable text on a terminal), every line
carrying the context it was written in.

JSON is the default for `posemetry api` and `posemetry worker`, which run under a supervisor or in containers
whose logs go to a collector; `posemetry serve` on a terminal prints text. Context comes from context
variables, not from each call site: the request id (service.observability.request_id) and whatever
`log_context(...)` holds (a job's id and queue, a camera). A field passed explicitly with `extra=` wins, which
is how the measuring job gives each frame's line that frame's own request id.

python-json-logger does the encoding (field order, exceptions as text, non-JSON values through `str`).
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any, Literal, TextIO

from pythonjsonlogger.json import JsonFormatter

from service.observability.redact import Redactor
from service.observability.request_id import current_request_id

LogFormat = Literal["json", "text"]
LOG_FORMATS: tuple[LogFormat, ...] = ("json", "text")
# Fields a line may carry from its context; text lines append them as key=value, JSON lines as keys.
CONTEXT_FIELDS = ("request_id", "job_id", "queue", "camera_id", "frame_id")
# The loggers of the jobs' work, wherever it lives (service.frames, service.calibration, service.webhooks): log
# collectors select the lines of measuring, pose, solving and deliveries by these names (README, Observability).
JOBS_LOGGER = "workers.jobs"
WEBHOOK_JOBS_LOGGER = "workers.webhooks"

_context: ContextVar[Mapping[str, Any] | None] = ContextVar("posemetry_log_context", default=None)


@contextmanager
def log_context(**fields: Any) -> Iterator[None]:
    """Add fields to every line logged within the block (nested blocks add to the outer ones)."""
    token = _context.set({**(_context.get() or {}), **fields})
    try:
        yield
    finally:
        _context.reset(token)


class ContextFilter(logging.Filter):
    """Puts the request id and the `log_context` fields on each record, unless the call passed them itself."""

    def filter(self, record: logging.LogRecord) -> bool:
        if getattr(record, "request_id", None) is None:
            request_id = current_request_id()
            if request_id is not None:
                record.request_id = request_id
        for name, value in (_context.get() or {}).items():
            if not hasattr(record, name):
                setattr(record, name, value)
        return True


def json_formatter() -> logging.Formatter:
    """time (ISO 8601, UTC), level, logger, pid (`serve` interleaves several processes), message, then the
    record's extra fields."""
    return JsonFormatter(
        "{levelname}{name}{process}{message}",
        style="{",
        rename_fields={"levelname": "level", "name": "logger", "process": "pid"},
        timestamp="time",
    )


class TextFormatter(logging.Formatter):
    """`time level logger: message key=value ...` with the context fields a record carries."""

    def __init__(self) -> None:
        super().__init__("%(asctime)s %(levelname)s %(name)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        extras = [f"{name}={getattr(record, name)}" for name in CONTEXT_FIELDS if getattr(record, name, None)]
        if not extras:
            return text
        first, newline, rest = text.partition("\n")  # keep a traceback below the line, not before the fields
        return f"{first} {' '.join(extras)}{newline}{rest}"


class RedactingFormatter(logging.Formatter):
    """Masks API keys and the given secrets in every line (service.observability.redact), however they got there."""

    def __init__(self, inner: logging.Formatter, secrets: Iterable[str] = ()) -> None:
        super().__init__()
        self.inner = inner
        self.redact = Redactor(secrets)

    def format(self, record: logging.LogRecord) -> str:
        return self.redact(self.inner.format(record))


def configure_logging(
    log_format: LogFormat, level: str | int = "INFO", stream: TextIO | None = None, secrets: Iterable[str] = ()
) -> None:
    """Replace the root logger's handlers with one stream handler in `log_format`; idempotent.

    Loggers that install their own handlers (uvicorn, RQ) are made to propagate to the root instead, so every
    line of the process comes out in one format. API keys and `secrets` are masked in every line.
    """
    if log_format not in LOG_FORMATS:
        raise ValueError(f"log format must be one of {', '.join(LOG_FORMATS)}, got {log_format!r}")
    handler = logging.StreamHandler(stream or sys.stderr)
    formatter = json_formatter() if log_format == "json" else TextFormatter()
    handler.setFormatter(RedactingFormatter(formatter, secrets))
    handler.addFilter(ContextFilter())
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
        old.close()
    root.addHandler(handler)
    root.setLevel(level if isinstance(level, int) else level.upper())
    for name in ("uvicorn", "uvicorn.error", "uvicorn.access", "rq.worker", "rq.job"):
        logger = logging.getLogger(name)
        logger.handlers.clear()
        logger.propagate = True
    # Alembic announces each of its autogenerate plugins at INFO on every start: seven lines of nothing for an
    # operator. Its migration lines ("Running upgrade ...") stay.
    logging.getLogger("alembic.runtime.plugins").setLevel(logging.WARNING)
    if log_format == "json":
        # RQ colours queue names with ANSI escapes when stdout is a terminal; they do not belong in JSON.
        from rq.logutils import colorizer

        colorizer.notty = True
