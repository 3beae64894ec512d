"""The in-process cache of verified API keys, which keeps authentication off the database on the hot path.

Every API process verifies a key against the database at most once per `ttl_s` (setting
`api_key_cache_ttl_s`); in between, a request costs one HMAC and a dictionary look-up. The price is that a key
revoked through another process (or with `posemetry keys revoke`) keeps working on this one until its entry
expires: at most `ttl_s`. A revocation through this process evicts the entry at once. Expiry dates are checked
on every request, cached or not. The cache is a bounded LRU, so a flood of distinct keys cannot grow memory.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from dataclasses import dataclass

from .principal import Principal

DEFAULT_MAX_ENTRIES = 10_000


@dataclass
class CachedKey:
    principal: Principal
    digest: str
    """The stored digest: a cached entry still has to match the presented token."""
    fresh_until_s: float
    """time.monotonic() after which the key must be read from the database again."""
    last_used_written_s: float
    """time.monotonic() when last_used_at was last known to be written (by any process); -inf: never."""


class KeyCache:
    """Thread-safe LRU of CachedKey by key id, each entry fresh for `ttl_s` after it was read."""

    def __init__(self, ttl_s: float, max_entries: int = DEFAULT_MAX_ENTRIES) -> None:
        if max_entries < 1:
            raise ValueError("max_entries must be at least 1")
        self.ttl_s = ttl_s
        self.max_entries = max_entries
        self._entries: OrderedDict[str, CachedKey] = OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return len(self._entries)

    def get(self, key_id: str) -> CachedKey | None:
        """The entry if it is still fresh; a stale one is dropped."""
        with self._lock:
            entry = self._entries.get(key_id)
            if entry is None:
                return None
            if time.monotonic() >= entry.fresh_until_s:
                del self._entries[key_id]
                return None
            self._entries.move_to_end(key_id)
            return entry

    def put(self, key_id: str, principal: Principal, digest: str, last_used_written_s: float) -> CachedKey:
        entry = CachedKey(principal, digest, time.monotonic() + self.ttl_s, last_used_written_s)
        if self.ttl_s <= 0:
            return entry  # caching disabled: every request reads the database
        with self._lock:
            self._entries[key_id] = entry
            self._entries.move_to_end(key_id)
            while len(self._entries) > self.max_entries:
                self._entries.popitem(last=False)
        return entry

    def evict(self, key_id: str) -> None:
        with self._lock:
            self._entries.pop(key_id, None)
