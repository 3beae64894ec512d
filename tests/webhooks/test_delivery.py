"""One attempt against a real HTTP receiver on loopback, and the rules that judge it."""

from __future__ import annotations

import random
import time
from email.utils import formatdate

import pytest

from service.webhooks.delivery import RESPONSE_LOG_BYTES, AttemptResult, decide_attempt, retry_delay_s, send
from service.webhooks.signing import generate_secret, signed_headers
from tests.support.receiver import Answer, Receiver, parse_networks

LOOPBACK = parse_networks(["127.0.0.0/8"])
BODY = b'{"type":"calibration.updated","timestamp":"2026-01-01T00:00:00Z","data":{}}'


@pytest.fixture
def receiver() -> Receiver:
    server = Receiver().start()
    yield server
    server.stop()


def test_a_signed_post_arrives_and_verifies(receiver: Receiver) -> None:
    secret = generate_secret()
    result = send(
        receiver.url, BODY, signed_headers([secret], "evt-1", int(time.time()), BODY), timeout_s=5, allowed=LOOPBACK
    )
    assert (result.status_code, result.response_body, result.error) == (200, "ok", None)
    assert result.peer == f"127.0.0.1:{receiver.port}"
    [request] = receiver.received()
    assert request.headers["content-type"] == "application/json"
    assert request.headers["user-agent"].startswith("posemetry-webhooks/")
    assert request.verify(secret)["type"] == "calibration.updated"
    assert request.webhook_id == "evt-1"


def test_loopback_is_refused_without_the_setting(receiver: Receiver) -> None:
    result = send(receiver.url, BODY, {}, timeout_s=5)
    assert result.refused and "loopback" in (result.error or "")
    assert receiver.received() == []
    assert decide_attempt(result, 1, max_attempts=5, base_s=1, cap_s=10).outcome == "failed"


def test_a_long_answer_is_cut_for_the_log(receiver: Receiver) -> None:
    receiver.answers.append(Answer(500, "é".encode() * 10_000))
    result = send(receiver.url, BODY, {}, timeout_s=5, allowed=LOOPBACK)
    assert result.status_code == 500
    assert result.response_truncated
    assert len(result.response_body.encode()) <= RESPONSE_LOG_BYTES + 3  # a split character becomes U+FFFD
    short = send(receiver.url, BODY, {}, timeout_s=5, allowed=LOOPBACK)
    assert (short.response_body, short.response_truncated) == ("ok", False)


def test_redirects_are_not_followed(receiver: Receiver) -> None:
    receiver.answers.append(Answer(302, b"", {"location": "http://169.254.169.254/latest/meta-data/"}))
    result = send(receiver.url, BODY, {}, timeout_s=5, allowed=LOOPBACK)
    assert result.status_code == 302
    assert len(receiver.received()) == 1
    decision = decide_attempt(result, 1, max_attempts=5, base_s=1, cap_s=10)
    assert decision.outcome == "failed" and "302" in (decision.reason or "")


def test_a_slow_receiver_times_out(receiver: Receiver) -> None:
    receiver.answers.append(Answer(200, delay_s=2.0))
    result = send(receiver.url, BODY, {}, timeout_s=0.5, allowed=LOOPBACK)
    assert result.status_code is None and "timed out" in (result.error or "")
    assert 0.4 < result.duration_s < 1.9
    assert decide_attempt(result, 1, max_attempts=5, base_s=1, cap_s=10).outcome == "retry"


def test_connection_refused_is_retried(receiver: Receiver) -> None:
    receiver.stop()
    result = send(receiver.url, BODY, {}, timeout_s=2, allowed=LOOPBACK)
    assert result.status_code is None and "refused" in (result.error or "").lower()
    assert decide_attempt(result, 1, max_attempts=5, base_s=1, cap_s=10).outcome == "retry"


def test_retry_after_is_read_in_seconds_and_as_a_date(receiver: Receiver) -> None:
    receiver.answers.append(Answer(429, headers={"retry-after": "7"}))
    receiver.answers.append(Answer(503, headers={"retry-after": formatdate(time.time() + 30, usegmt=True)}))
    assert send(receiver.url, BODY, {}, timeout_s=5, allowed=LOOPBACK).retry_after_s == 7
    assert 25 < (send(receiver.url, BODY, {}, timeout_s=5, allowed=LOOPBACK).retry_after_s or 0) <= 30


@pytest.mark.parametrize(
    ("status", "outcome"),
    [(200, "delivered"), (204, "delivered"), (299, "delivered"), (500, "retry"), (502, "retry"), (503, "retry"),
     (408, "retry"), (429, "retry"), (400, "failed"), (401, "failed"), (403, "failed"), (404, "failed"),
     (301, "failed"), (410, "failed")],
)  # fmt: skip
def test_status_codes(status: int, outcome: str) -> None:
    decision = decide_attempt(AttemptResult(0.1, status_code=status), 1, max_attempts=5, base_s=1, cap_s=10)
    assert decision.outcome == outcome
    assert (decision.disable_subscription is not None) == (status == 410)


def test_retries_stop_after_max_attempts() -> None:
    result = AttemptResult(0.1, status_code=500)
    assert decide_attempt(result, 4, max_attempts=5, base_s=1, cap_s=10).outcome == "retry"
    last = decide_attempt(result, 5, max_attempts=5, base_s=1, cap_s=10)
    assert last.outcome == "failed" and "gave up after 5 attempts" in (last.reason or "")


def test_backoff_doubles_with_jitter_up_to_the_cap() -> None:
    rng = random.Random(1)
    for attempt in range(1, 12):
        nominal = min(60.0, 2.0 * 2 ** (attempt - 1))
        delays = [retry_delay_s(attempt, base_s=2, cap_s=60, rng=rng) for _ in range(200)]
        assert 0.75 * nominal <= min(delays) and max(delays) <= nominal
        assert max(delays) - min(delays) > 0.1 * nominal  # jittered, not fixed
    assert retry_delay_s(1, base_s=2, cap_s=60, retry_after_s=30) >= 30
    assert retry_delay_s(1, base_s=2, cap_s=60, retry_after_s=3600) == 60  # a Retry-After is capped too
