"""From an `Authorization` header to a Principal: parse, hash, look up (cached), check revocation and expiry.

The hot path (a cached key) is a few microseconds on the event loop: one HMAC-SHA256, a dictionary look-up and
a constant-time digest comparison. Only a cache miss (at most once per key, API process and `ttl_s`) reads the
database, in the thread pool; `last_used_at` is written at most once per TOUCH_INTERVAL_S per key and process,
by a conditional UPDATE that writes nothing when another process stamped the key recently.
"""

from __future__ import annotations

import logging
import math
import time
from datetime import UTC, datetime

from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker
from starlette.concurrency import run_in_threadpool

from service.http.problems import UNAVAILABLE_HEADERS, ProblemError
from service.keys import repository as stored_keys
from service.store.models import ApiKey

from .cache import DEFAULT_MAX_ENTRIES, CachedKey, KeyCache
from .principal import SETTINGS_ADMIN, Principal
from .tokens import TOKEN_FORMAT, digests_match, key_id_of, token_digest

log = logging.getLogger(__name__)

# last_used_at is accurate to about this much (plus the cache TTL when that is longer).
TOUCH_INTERVAL_S = 60.0
REALM = 'Bearer realm="posemetry"'


def unauthenticated(detail: str, *, token_given: bool) -> ProblemError:
    """401 with the RFC 6750 challenge: `invalid_token` when a token was presented, a bare challenge otherwise."""
    challenge = f'{REALM}, error="invalid_token"' if token_given else REALM
    return ProblemError(401, "unauthenticated", detail, headers={"WWW-Authenticate": challenge})


def forbidden(kind: str, detail: str) -> ProblemError:
    """403: the key is valid but may not do this (RFC 6750 `insufficient_scope`)."""
    return ProblemError(403, kind, detail, headers={"WWW-Authenticate": f'{REALM}, error="insufficient_scope"'})


# Authorization schemes a 401 may name (RFC 7235's registry and common API-key spellings). Anything else in the
# scheme's place is named by nobody: a key sent without `Bearer ` sits exactly there, and the 401 once echoed
# its first 20 characters (the key id and 4 secret characters).
KNOWN_SCHEMES = frozenset(
    {"basic", "digest", "negotiate", "ntlm", "hoba", "mutual", "vapid", "scram-sha-1", "scram-sha-256", "token"}
    | {"apikey", "api-key", "aws4-hmac-sha256", "dpop", "gnap", "privatetoken", "concealed"}
)


def bearer_token(authorization: str | None) -> str:
    """The token of an `Authorization: Bearer <token>` header (scheme case-insensitive), or a 401.

    No 401 repeats what was sent: only a registered scheme's name, which is no secret."""
    if not authorization or not authorization.strip():
        raise unauthenticated("This route needs an API key: send `Authorization: Bearer <key>`.", token_given=False)
    scheme, _, token = authorization.strip().partition(" ")
    if scheme.lower() != "bearer":
        named = f"the {scheme.capitalize()} scheme" if scheme.lower() in KNOWN_SCHEMES else "no Bearer scheme"
        raise unauthenticated(
            f"The Authorization header uses {named}; send `Authorization: Bearer <key>` (the word Bearer, a "
            "space, then the key).",
            token_given=False,
        )
    token = token.strip()
    if not token:
        raise unauthenticated("The Authorization header has no key after `Bearer`.", token_given=False)
    return token


def _utc_now() -> datetime:
    return datetime.now(UTC)


class Authenticator:
    """One per app: the configured admin key's digest, the cache of stored keys, and the sessions to read them."""

    def __init__(
        self,
        *,
        admin_key: str | None,
        read_sessions: sessionmaker[Session],
        write_sessions: sessionmaker[Session],
        cache_ttl_s: float,
        cache_max_entries: int = DEFAULT_MAX_ENTRIES,
    ) -> None:
        self._admin_digest = None if admin_key is None else token_digest(admin_key)
        self._read_sessions = read_sessions
        self._write_sessions = write_sessions
        self.cache = KeyCache(cache_ttl_s, cache_max_entries)

    async def authenticate(self, authorization: str | None) -> Principal:
        token = bearer_token(authorization)
        digest = token_digest(token)
        if self._admin_digest is not None and digests_match(digest, self._admin_digest):
            return SETTINGS_ADMIN
        key_id = key_id_of(token)
        if key_id is None:
            raise unauthenticated(f"Not a posemetry API key (they look like {TOKEN_FORMAT}).", token_given=True)
        entry = self.cache.get(key_id)
        if entry is None or not digests_match(entry.digest, digest):
            entry = await run_in_threadpool(self._load, key_id, digest)
        expires_at = entry.principal.expires_at
        if expires_at is not None and _utc_now() >= expires_at:
            self.cache.evict(key_id)
            raise unauthenticated(f"API key {key_id} expired at {expires_at.isoformat()}.", token_given=True)
        if time.monotonic() - entry.last_used_written_s >= TOUCH_INTERVAL_S:
            entry.last_used_written_s = time.monotonic()  # before the write, so concurrent requests do not pile up
            await run_in_threadpool(self._touch, key_id)
        return entry.principal

    def forget(self, key_id: str) -> None:
        """Drop a key from this process's cache (it was revoked here: no need to wait for the TTL)."""
        self.cache.evict(key_id)

    def _load(self, key_id: str, digest: str) -> CachedKey:
        try:
            with self._read_sessions() as session:
                key = stored_keys.get_key(session, key_id)
        except SQLAlchemyError as exc:
            log.warning("API key look-up failed: %s", exc)
            raise ProblemError(
                503,
                "database-unavailable",
                "The database is unreachable, so the API key cannot be checked.",
                headers=UNAVAILABLE_HEADERS,
            ) from exc
        if key is None or not digests_match(key.token_digest, digest):
            raise unauthenticated("Unknown API key.", token_given=True)
        if key.revoked_at is not None:
            raise unauthenticated(f"API key {key_id} was revoked at {key.revoked_at.isoformat()}.", token_given=True)
        return self.cache.put(key_id, principal_of(key), key.token_digest, self._last_written_s(key))

    @staticmethod
    def _last_written_s(key: ApiKey) -> float:
        """key.last_used_at on the monotonic clock, so a stamp by another process also counts."""
        if key.last_used_at is None:
            return -math.inf
        age_s = (_utc_now() - key.last_used_at).total_seconds()
        return time.monotonic() - max(age_s, 0.0)

    def _touch(self, key_id: str) -> None:
        """Best effort: a failed stamp is logged, never the request's failure."""
        try:
            with self._write_sessions() as session:
                stored_keys.touch_key(session, key_id, now=_utc_now(), min_interval_s=TOUCH_INTERVAL_S)
                session.commit()
        except SQLAlchemyError as exc:
            log.warning("could not record the use of API key %s: %s", key_id, exc)


def principal_of(key: ApiKey) -> Principal:
    return Principal(
        key_id=key.id,
        name=key.name,
        admin=key.admin,
        cameras=None if key.cameras is None else frozenset(key.cameras),
        expires_at=key.expires_at,
    )
