"""API key tokens: how they are made, recognised and hashed (pure stdlib; no I/O).

A token reads `pm_<id>_<secret>`: `pm_` makes a leaked key recognisable to people and to secret scanners, `<id>`
(12 hex digits) names the stored key so it can be looked up by primary key and shown in listings and logs, and
`<secret>` is 43 characters of base62 from `secrets` (256 bits). Only a hash of the whole token is stored.

Why HMAC-SHA256 and not bcrypt/scrypt/argon2: those are deliberately slow to make guessing *low-entropy
passwords* from a stolen hash expensive. A 256-bit random secret cannot be guessed however fast the hash is, so
slowness buys nothing, and it would cost ~100 ms of CPU per verification on the ingest hot path (or force caching
raw tokens). A keyed hash (the key is a fixed, versioned domain-separation constant, so the digest cannot be
confused with a plain SHA-256 of the token computed elsewhere) is the standard choice for high-entropy API tokens.
Stored digests are compared with `hmac.compare_digest`, in constant time.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
import string
from dataclasses import dataclass

TOKEN_PREFIX = "pm_"
KEY_ID_HEX_DIGITS = 12
SECRET_CHARS = 43  # 43 x log2(62) = 256 bits
_BASE62 = string.ascii_letters + string.digits
_TOKEN_PATTERN = re.compile(rf"pm_([0-9a-f]{{{KEY_ID_HEX_DIGITS}}})_([0-9A-Za-z]{{{SECRET_CHARS}}})")
KEY_ID_PATTERN = rf"^[0-9a-f]{{{KEY_ID_HEX_DIGITS}}}$"
TOKEN_FORMAT = f"{TOKEN_PREFIX}<{KEY_ID_HEX_DIGITS} hex id>_<{SECRET_CHARS} base62 characters>"
# Versioned: a future change of hashing gets a new constant, and old digests stay recognisable.
_HASH_KEY = b"posemetry api key v1"


@dataclass(frozen=True)
class NewToken:
    """A freshly generated key: the token is shown once; only `digest` is stored."""

    key_id: str
    token: str
    digest: str


def token_digest(token: str) -> str:
    """The stored form of a token (64 hex digits)."""
    return hmac.new(_HASH_KEY, token.encode("utf-8", "surrogatepass"), hashlib.sha256).hexdigest()


def digests_match(a: str, b: str) -> bool:
    return hmac.compare_digest(a.encode(), b.encode())


def new_token() -> NewToken:
    key_id = secrets.token_hex(KEY_ID_HEX_DIGITS // 2)
    secret = "".join(secrets.choice(_BASE62) for _ in range(SECRET_CHARS))
    token = f"{TOKEN_PREFIX}{key_id}_{secret}"
    return NewToken(key_id=key_id, token=token, digest=token_digest(token))


def key_id_of(token: str) -> str | None:
    """The key id inside a well-formed token, or None when the token does not have the `pm_` shape."""
    match = _TOKEN_PATTERN.fullmatch(token)
    return None if match is None else match.group(1)
