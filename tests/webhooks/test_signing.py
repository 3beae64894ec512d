"""Standard Webhooks signatures, checked by the scheme's reference library (`standardwebhooks`)."""

from __future__ import annotations

import base64
import time
from datetime import UTC, datetime

import pytest
from standardwebhooks.webhooks import Webhook, WebhookVerificationError

from service.webhooks.signing import SECRET_MAX_BYTES, generate_secret, secret_key, signature, signed_headers

BODY = b'{"type":"violation.detected","timestamp":"2026-01-01T12:00:00Z","data":{"camera_id":"lobby"}}'


def test_generated_secrets_are_whsec_base64_of_32_random_bytes() -> None:
    secrets = {generate_secret() for _ in range(20)}
    assert len(secrets) == 20
    for secret in secrets:
        assert secret.startswith("whsec_")
        assert len(base64.b64decode(secret[6:], validate=True)) == 32


def test_the_reference_library_verifies_our_signature() -> None:
    secret = generate_secret()
    now = int(time.time())
    headers = signed_headers([secret], "msg_1", now, BODY)
    assert set(headers) == {"webhook-id", "webhook-timestamp", "webhook-signature"}
    assert headers["webhook-signature"].startswith("v1,")
    assert Webhook(secret).verify(BODY, headers)["data"]["camera_id"] == "lobby"
    # ... and the signature is exactly the reference library's for the same inputs.
    reference = Webhook(secret).sign("msg_1", datetime.fromtimestamp(now, UTC), BODY.decode())
    assert signature(secret, "msg_1", now, BODY) == reference


@pytest.mark.parametrize("tamper", ["body", "id", "timestamp", "secret"])
def test_anything_changed_fails_verification(tamper: str) -> None:
    secret = generate_secret()
    now = int(time.time())
    headers = signed_headers([secret], "msg_1", now, BODY)
    body = BODY
    if tamper == "body":
        body = BODY.replace(b"lobby", b"lobbx")
    elif tamper == "id":
        headers["webhook-id"] = "msg_2"
    elif tamper == "timestamp":
        headers["webhook-timestamp"] = str(now - 1)
    else:
        secret = generate_secret()
    with pytest.raises(WebhookVerificationError):
        Webhook(secret).verify(body, headers)


def test_during_a_rotation_both_secrets_verify() -> None:
    old, new = generate_secret(), generate_secret()
    headers = signed_headers([new, old], "msg_1", int(time.time()), BODY)
    assert len(headers["webhook-signature"].split(" ")) == 2
    for secret in (old, new):
        Webhook(secret).verify(BODY, headers)
    with pytest.raises(WebhookVerificationError):
        Webhook(generate_secret()).verify(BODY, headers)


@pytest.mark.parametrize(
    ("secret", "fragment"),
    [
        ("c2VjcmV0LXNlY3JldC1zZWNyZXQtc2VjcmV0", "starts with"),
        ("whsec_not*base64!", "not valid base64"),
        ("whsec_" + base64.b64encode(b"short").decode(), "5 bytes"),
        ("whsec_" + base64.b64encode(bytes(SECRET_MAX_BYTES + 1)).decode(), "65 bytes"),
    ],
)
def test_malformed_secrets_are_refused(secret: str, fragment: str) -> None:
    with pytest.raises(ValueError, match=fragment):
        secret_key(secret)
