"""Issuing keys, shared by the HTTP API, `posemetry keys` and `posemetry serve`'s first admin key."""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy.orm import Session

from service.keys import repository as stored_keys
from service.store.models import ApiKey

from .tokens import new_token

FIRST_ADMIN_NAME = "first admin key (posemetry serve)"
CREATED_BY_SERVE = "posemetry serve"
CREATED_BY_CLI = "posemetry keys"


@dataclass(frozen=True)
class IssuedKey:
    """A stored key and its token: the only moment the token exists outside the client's hands."""

    key: ApiKey
    token: str


def issue_key(
    session: Session,
    *,
    name: str,
    admin: bool = False,
    cameras: Collection[str] | None = None,
    expires_at: datetime | None = None,
    created_by: str,
) -> IssuedKey:
    """Generate a token and store its digest (flushed, not committed: the caller commits)."""
    token = new_token()
    key = stored_keys.add_key(
        session,
        key_id=token.key_id,
        name=name,
        digest=token.digest,
        admin=admin,
        cameras=cameras,
        expires_at=expires_at,
        created_by=created_by,
    )
    return IssuedKey(key, token.token)


def first_admin_key(session: Session) -> IssuedKey | None:
    """The first admin key of a database that never had one (committed), else None.

    Only ever the first: once any admin key was stored, revoked or expired ones included, this returns None, so
    revoking every admin key does not make the next start hand out a new one (`posemetry keys create --admin`
    does, for whoever holds the database).
    """
    if stored_keys.admin_key_ever_stored(session):
        return None
    issued = issue_key(session, name=FIRST_ADMIN_NAME, admin=True, created_by=CREATED_BY_SERVE)
    session.commit()
    return issued
