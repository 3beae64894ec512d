"""One delivery attempt: the signed POST (`send`), and what its answer means (`decide_attempt`).

What counts as what, in one place (`decide_attempt`, also the hook for delivery metrics):

- 2xx: delivered.
- 408 Request Timeout, 429 Too Many Requests, any 5xx, a timeout or a connection error: retried after a capped,
  exponentially growing, jittered delay (a receiver's Retry-After is honoured up to the cap), until the attempts
  run out; then the delivery has failed.
- 410 Gone: failed, and the subscription is disabled (the receiver says the endpoint is gone for good, as the
  Standard Webhooks scheme suggests).
- Any other 4xx or a 3xx: failed at once. The receiver understood the request and refused it (a wrong secret,
  a path that does not exist, a redirect, which is never followed); sending the same bytes again cannot change
  the answer, and retrying would only hammer it. Once the receiver is fixed, `POST .../redeliver` sends again.
- A URL whose host now resolves only to refused addresses (the SSRF policy): failed at once.
"""

from __future__ import annotations

import email.utils
import functools
import math
import random
import ssl
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Literal

import httpcore2

from service import __version__

from .addresses import AddressRefusedError, GuardedBackend, IPNetwork

# The first bytes of a receiver's answer kept in the delivery log.
RESPONSE_LOG_BYTES = 2048
USER_AGENT = f"posemetry-webhooks/{__version__}"
RETRIED_STATUSES = frozenset({408, 429})
GONE_STATUS = 410
# Jitter: a retry waits between this fraction and all of its nominal delay.
JITTER_FLOOR = 0.75

Outcome = Literal["delivered", "retry", "failed"]


@dataclass(frozen=True)
class AttemptResult:
    """What one POST came to: an HTTP status, or the error that prevented one."""

    duration_s: float
    status_code: int | None = None
    error: str | None = None
    response_body: str | None = None
    response_truncated: bool = False
    peer: str | None = None
    """The address connected to (ip:port)."""
    retry_after_s: float | None = None
    refused: bool = False
    """The SSRF policy refused every address the host resolved to."""


@dataclass(frozen=True)
class Decision:
    """What happens to a delivery after an attempt."""

    outcome: Outcome
    """delivered; retry (after delay_s); failed (permanently, or the attempts ran out)."""
    delay_s: float | None = None
    reason: str | None = None
    """Why it failed, in words for the log."""
    disable_subscription: str | None = None
    """Set when the subscription must be disabled (410 Gone): the reason recorded on it."""


def _retry_after_s(value: str | None, now_s: float) -> float | None:
    """Retry-After as seconds from now: either delta-seconds or an HTTP date."""
    if not value:
        return None
    value = value.strip()
    if value.isdigit():
        return float(value)
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    if when.tzinfo is None:
        when = when.replace(tzinfo=UTC)
    return max(0.0, when.timestamp() - now_s)


@functools.cache
def _default_ssl_context() -> ssl.SSLContext:
    """The system's trusted CAs, loaded once per process (loading them costs tens of milliseconds)."""
    return ssl.create_default_context()


def send(
    url: str,
    body: bytes,
    headers: dict[str, str],
    *,
    timeout_s: float,
    allowed: tuple[IPNetwork, ...] = (),
    ssl_context: ssl.SSLContext | None = None,
) -> AttemptResult:
    """POST `body` to `url` once: no redirects followed, no proxies, every connection through the SSRF policy.

    A fresh connection per attempt, so each attempt resolves and checks the host again. At most
    RESPONSE_LOG_BYTES of the answer are read; the connection is closed after that.
    """
    backend = GuardedBackend(allowed)
    request_headers = [
        ("content-type", "application/json"),
        ("user-agent", USER_AGENT),
        *headers.items(),
    ]
    timeouts = {"connect": timeout_s, "read": timeout_s, "write": timeout_s, "pool": timeout_s}
    started = time.perf_counter()
    status: int | None = None
    received = b""
    retry_after = None

    def result(**fields: object) -> AttemptResult:
        truncated = len(received) > RESPONSE_LOG_BYTES
        text = received[:RESPONSE_LOG_BYTES].decode("utf-8", errors="replace") if status is not None else None
        return AttemptResult(
            duration_s=time.perf_counter() - started,
            status_code=status,
            response_body=text,
            response_truncated=truncated,
            peer=backend.peer,
            retry_after_s=retry_after,
            **fields,  # type: ignore[arg-type]
        )

    pool = httpcore2.ConnectionPool(
        ssl_context=ssl_context or _default_ssl_context(),
        network_backend=backend,
        max_connections=1,
        max_keepalive_connections=0,
    )
    try:
        request = {"headers": request_headers, "content": body, "extensions": {"timeout": timeouts}}
        with pool, pool.stream("POST", url, **request) as r:  # type: ignore[arg-type]
            status = r.status
            names = {name.decode("latin-1").lower(): value.decode("latin-1") for name, value in r.headers}
            retry_after = _retry_after_s(names.get("retry-after"), time.time())
            try:
                for chunk in r.iter_stream():
                    received += chunk
                    if len(received) > RESPONSE_LOG_BYTES:
                        break
            except (httpcore2.TimeoutException, httpcore2.NetworkError, httpcore2.ProtocolError):
                pass  # the status decides; a body cut short is logged as far as it came
    except AddressRefusedError as exc:
        return result(error=f"refused by the SSRF policy: {exc}", refused=True)
    except httpcore2.TimeoutException as exc:
        if status is None:
            return result(error=f"timed out after {timeout_s:g} s ({type(exc).__name__})")
    except (httpcore2.NetworkError, httpcore2.ProtocolError, httpcore2.UnsupportedProtocol, ssl.SSLError) as exc:
        if status is None:
            return result(error=f"{type(exc).__name__}: {exc or 'connection failed'}")
    return result()


def retry_delay_s(
    attempt: int, *, base_s: float, cap_s: float, retry_after_s: float | None = None, rng: random.Random | None = None
) -> float:
    """Wait after failed attempt number `attempt` (1-based): base x 2^(attempt-1), jittered down by up to a
    quarter, at least the receiver's Retry-After, never more than cap_s."""
    nominal = base_s * math.pow(2.0, min(attempt - 1, 60))
    delay = min(cap_s, nominal) * (rng or random).uniform(JITTER_FLOOR, 1.0)
    if retry_after_s is not None:
        delay = max(delay, retry_after_s)
    return min(cap_s, delay)


def decide_attempt(
    result: AttemptResult,
    attempt: int,
    *,
    max_attempts: int,
    base_s: float,
    cap_s: float,
    rng: random.Random | None = None,
) -> Decision:
    """The one place an attempt's outcome is decided (see the module docstring for the rules)."""
    code = result.status_code
    if code is not None and 200 <= code < 300:
        return Decision("delivered")
    if result.refused:
        return Decision("failed", reason=result.error)
    if code == GONE_STATUS:
        reason = "the receiver answered 410 Gone"
        return Decision("failed", reason=reason, disable_subscription=reason)
    retryable = code is None or code in RETRIED_STATUSES or code >= 500
    what = f"HTTP {code}" if code is not None else (result.error or "no answer")
    if not retryable:
        return Decision("failed", reason=f"{what}: not retried (only 408, 429, 5xx and network errors are)")
    if attempt >= max_attempts:
        return Decision("failed", reason=f"{what}: gave up after {attempt} attempts")
    delay = retry_delay_s(attempt, base_s=base_s, cap_s=cap_s, retry_after_s=result.retry_after_s, rng=rng)
    return Decision("retry", delay_s=delay, reason=what)


def utc_timestamp_s() -> int:
    """The `webhook-timestamp` of an attempt: whole seconds, now (each retry is signed afresh)."""
    return math.floor(datetime.now(UTC).timestamp())
