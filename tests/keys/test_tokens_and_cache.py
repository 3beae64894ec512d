"""Tokens (shape, entropy, hashing) and the bounded TTL cache of verified keys, without HTTP."""

from __future__ import annotations

import hashlib
import re
import time

import pytest
from pydantic import ValidationError

from service.keys.cache import KeyCache
from service.keys.principal import Principal
from service.keys.tokens import KEY_ID_PATTERN, digests_match, key_id_of, new_token, token_digest
from service.settings import Settings

PRINCIPAL = Principal(key_id="0123456789ab", name="k", admin=False)


def test_tokens_are_prefixed_unique_and_only_their_digest_is_kept() -> None:
    tokens = [new_token() for _ in range(200)]
    assert len({t.token for t in tokens}) == len({t.key_id for t in tokens}) == 200
    for token in tokens:
        assert re.fullmatch(r"pm_[0-9a-f]{12}_[0-9A-Za-z]{43}", token.token)
        assert re.fullmatch(KEY_ID_PATTERN, token.key_id)
        assert key_id_of(token.token) == token.key_id
        assert token.digest == token_digest(token.token) and token.token not in token.digest
    # Keyed: not the plain SHA-256 of the token, so a digest from elsewhere does not match.
    token = tokens[0].token
    assert token_digest(token) != hashlib.sha256(token.encode()).hexdigest()
    assert len(token_digest(token)) == 64
    # The secret parts use the whole base62 alphabet (a crude check that it is not, say, hex).
    secrets = "".join(t.token.rsplit("_", 1)[1] for t in tokens)
    assert len(set(secrets)) == 62


@pytest.mark.parametrize(
    "text",
    [
        "",
        "pm_",
        "pm_0123456789ab",
        "pm_0123456789AB_" + "a" * 43,
        "pm_0123456789ab_" + "a" * 42,
        "xx_0123456789ab_" + "a" * 43,
    ],
)
def test_malformed_tokens_have_no_key_id(text: str) -> None:
    assert key_id_of(text) is None


def test_digests_match_only_themselves() -> None:
    a = token_digest("a")
    assert digests_match(a, token_digest("a"))
    assert not digests_match(a, token_digest("b")) and not digests_match(a, a[:-1])


def test_cache_entries_expire_after_the_ttl() -> None:
    cache = KeyCache(ttl_s=0.2)
    cache.put("k", PRINCIPAL, "digest", last_used_written_s=0.0)
    assert cache.get("k") is not None
    time.sleep(0.25)
    assert cache.get("k") is None and len(cache) == 0


def test_cache_is_bounded_and_drops_the_least_recently_used() -> None:
    cache = KeyCache(ttl_s=60, max_entries=3)
    for name in "abc":
        cache.put(name, PRINCIPAL, name, last_used_written_s=0.0)
    assert cache.get("a") is not None  # a is now the most recently used
    cache.put("d", PRINCIPAL, "d", last_used_written_s=0.0)
    assert len(cache) == 3
    assert cache.get("b") is None
    assert all(cache.get(name) is not None for name in "acd")
    cache.evict("c")
    assert cache.get("c") is None


def test_a_zero_ttl_caches_nothing() -> None:
    cache = KeyCache(ttl_s=0)
    cache.put("k", PRINCIPAL, "digest", last_used_written_s=0.0)
    assert cache.get("k") is None and len(cache) == 0


def test_the_admin_key_setting_refuses_weak_keys_without_echoing_them() -> None:
    with pytest.raises(ValidationError) as refused:
        Settings(admin_key="hunter2-hunter2")
    assert "hunter2" not in str(refused.value) and "at least 32 characters" in str(refused.value)
    with pytest.raises(ValidationError):
        Settings(admin_key="x" * 31 + " " + "y")
    assert Settings(admin_key="").admin_key is None
    strong = Settings(admin_key="k" * 40)
    assert strong.admin_key is not None and "k" * 40 not in repr(strong)
