"""Standard Webhooks signatures (https://www.standardwebhooks.com/): secrets, and the three signed headers.

`webhook-signature` is `v1,` + base64(HMAC-SHA256(key, f"{id}.{timestamp}.{body}")), where the key is the
base64-decoded part of the `whsec_...` secret. A receiver verifies it with any Standard Webhooks library (the
tests use the reference `standardwebhooks` package). Signing is these few lines of the standard library rather
than that package: its `sign` treats every datetime as UTC whatever its zone, and its secret parser silently
skips characters that are not base64, so a mistyped secret would sign with a different key instead of failing.

During a secret rotation a message carries one signature per valid secret, space-separated, as the scheme allows;
receivers accept a message when any of them verifies.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import hmac
import re
import secrets
from collections.abc import Sequence

SECRET_PREFIX = "whsec_"
# The scheme asks for 24 to 64 random bytes; generated secrets use 32.
SECRET_MIN_BYTES = 24
SECRET_MAX_BYTES = 64
GENERATED_SECRET_BYTES = 32
_B64 = "[A-Za-z0-9+/]"
# Canonical base64 (whole quanta, padding only where the last quantum needs it): Python's decoder also takes
# surplus padding ("...A===") and so did the old pattern, which made "valid" depend on the decoder's leniency.
SECRET_PATTERN = rf"^whsec_(?:{_B64}{{4}})*(?:{_B64}{{2}}==|{_B64}{{3}}=)?$"
# The same with the 24-64 byte length written out (8-21 quanta, and at most one byte in a last padded one), for the
# OpenAPI document: what it calls valid is exactly what secret_key accepts. Validation checks the length itself,
# to say "decodes to 9 bytes" rather than "does not match the pattern".
SECRET_DOCUMENTED_PATTERN = (
    rf"^whsec_(?:{_B64}{{4}}){{8,20}}(?:{_B64}{{4}}(?:{_B64}{{2}}==)?|{_B64}{{2}}==|{_B64}{{3}}=)?$"
)


def generate_secret() -> str:
    """A new random secret in the `whsec_<base64>` form; shown to the subscriber once."""
    return SECRET_PREFIX + base64.b64encode(secrets.token_bytes(GENERATED_SECRET_BYTES)).decode("ascii")


def secret_key(secret: str) -> bytes:
    """The HMAC key of a `whsec_` secret; ValueError when it is not one (bad prefix, not base64, wrong length)."""
    if not secret.startswith(SECRET_PREFIX):
        raise ValueError(f"a secret starts with {SECRET_PREFIX!r}")
    if re.fullmatch(SECRET_PATTERN, secret) is None:
        raise ValueError(
            f"the part after {SECRET_PREFIX!r} is not valid base64 (whole 4-character groups, '=' only to pad the last)"
        )
    try:
        key = base64.b64decode(secret[len(SECRET_PREFIX) :], validate=True)
    except binascii.Error as exc:
        raise ValueError(f"the part after {SECRET_PREFIX!r} is not valid base64 ({exc})") from None
    if not SECRET_MIN_BYTES <= len(key) <= SECRET_MAX_BYTES:
        raise ValueError(
            f"the secret decodes to {len(key)} bytes; Standard Webhooks secrets are "
            f"{SECRET_MIN_BYTES} to {SECRET_MAX_BYTES} random bytes"
        )
    return key


def signature(secret: str, message_id: str, timestamp_s: int, body: bytes) -> str:
    """One `v1,<base64>` signature of the body under `secret`."""
    signed = f"{message_id}.{timestamp_s}.".encode() + body
    digest = hmac.new(secret_key(secret), signed, hashlib.sha256).digest()
    return "v1," + base64.b64encode(digest).decode("ascii")


def signed_headers(secrets_: Sequence[str], message_id: str, timestamp_s: int, body: bytes) -> dict[str, str]:
    """The three Standard Webhooks headers, signed with every secret given (the current one first)."""
    if not secrets_:
        raise ValueError("at least one secret is needed to sign")
    return {
        "webhook-id": message_id,
        "webhook-timestamp": str(timestamp_s),
        "webhook-signature": " ".join(signature(secret, message_id, timestamp_s, body) for secret in secrets_),
    }
