"""The request id: one short string that ties together every log line, problem body and job of one request.

A client (or a proxy in front of the API) may send its own id in `X-Request-ID`, so its logs and ours can be
joined; it is accepted only when well-formed, because it is echoed in a response header and written to logs and
to the database: at most REQUEST_ID_MAX_LENGTH characters of letters, digits and `.`, `_`, `:`, `-`, starting
with a letter or digit, and holding no API key or configured secret. Anything else (too long, spaces, control
characters, quotes, a key) is replaced by a fresh id rather than cleaned up, so an id in our logs is always
either the client's exact id or ours.

The id of the request being served lives in a context variable: set by the HTTP middleware for the duration of
the request (sync handlers run in a thread pool that copies the context), read by the log filter, the problem
bodies and the dispatcher (which attaches it to the jobs it queues). Workers set it from a job's meta.
"""

from __future__ import annotations

import random
import re
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar

from service.observability.redact import APP_SECRETS

HEADER = "X-Request-ID"
HEADER_KEY = b"x-request-id"
REQUEST_ID_MAX_LENGTH = 128
REQUEST_ID_PATTERN = re.compile(rf"[A-Za-z0-9][A-Za-z0-9._:-]{{0,{REQUEST_ID_MAX_LENGTH - 1}}}")
# The key of a job's meta that carries the id of the request that queued it.
JOB_META_KEY = "request_id"

_current: ContextVar[str | None] = ContextVar("posemetry_request_id", default=None)


def new_request_id() -> str:
    """32 random hex digits: unique without coordination, and safe everywhere an id goes.

    Not uuid4: it reads os.urandom, a system call that releases the GIL, and the event loop that gives up the GIL
    under load waits for it behind the API's other threads. An id needs uniqueness, not secrecy; `random` is
    seeded from the OS, and again in each forked process."""
    return f"{random.getrandbits(128):032x}"


def accepted_request_id(value: str | bytes | None) -> str | None:
    """The client's id when it is well-formed, else None (the caller then generates one)."""
    if value is None:
        return None
    if isinstance(value, bytes):
        try:
            value = value.decode("ascii")
        except UnicodeDecodeError:
            return None
    # A credential is well-formed too, but an id is echoed and logged: one that holds a key or a secret is not taken.
    return value if REQUEST_ID_PATTERN.fullmatch(value) and APP_SECRETS(value) == value else None


def current_request_id() -> str | None:
    """The id of the request (or of the job's originating request) this code runs for, if any."""
    return _current.get()


@contextmanager
def request_id_context(request_id: str | None) -> Iterator[None]:
    """Make `request_id` current within the block (None clears it, e.g. for a job no request queued)."""
    token = _current.set(request_id)
    try:
        yield
    finally:
        _current.reset(token)
