"""Credentials masked wherever text leaves the service: log lines and problem documents.

The service never puts a credential into either on purpose (no error detail repeats what was sent in an
Authorization header). But a client may put one where the service does repeat text: a key pasted into a URL comes
back in a 404's `instance` and goes into the access log's `path`. So API keys, recognised by their shape, and the
secrets the settings name (the admin key, database and Redis passwords) are replaced by `[redacted]` there.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable

# An API key's shape (service.keys.tokens; not imported: observability does not depend on keys).
API_KEY_PATTERN = r"pm_[0-9a-f]{12}_[0-9A-Za-z]{43}"
REDACTED = "[redacted]"


class Redactor:
    """Replaces API keys and the given secrets (also as JSON escapes them) in text; about a microsecond a line."""

    def __init__(self, secrets: Iterable[str] = ()) -> None:
        self._literals: set[str] = set()
        self._pattern = re.compile(API_KEY_PATTERN)
        self.add(secrets)

    def add(self, secrets: Iterable[str]) -> None:
        """Mask these too (empty strings are ignored)."""
        new = {form for secret in secrets if secret for form in (secret, json.dumps(secret)[1:-1])}
        if new - self._literals:
            self._literals |= new
            literals = sorted(self._literals, key=len, reverse=True)  # the longest first: no partial masks
            self._pattern = re.compile("|".join([API_KEY_PATTERN, *map(re.escape, literals)]))

    def __call__(self, text: str) -> str:
        return self._pattern.sub(REDACTED, text)


APP_SECRETS = Redactor()
"""API keys and the secrets of every app created in this process (create_app adds them): masked in problem
documents, and a request id holding one is not taken (service.observability.request_id)."""
