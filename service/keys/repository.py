"""API keys in the store: add, read, list, revoke, and the cheap last-used stamp.

Like the repository, functions flush but never commit; the caller owns the transaction. Tokens never reach
this module, only their digests (service.keys.tokens).
"""

from __future__ import annotations

from collections.abc import Collection
from datetime import datetime, timedelta

from sqlalchemy import exists, or_, select, update
from sqlalchemy.orm import Session

from service.store.models import ApiKey, utc_now


def add_key(
    session: Session,
    *,
    key_id: str,
    name: str,
    digest: str,
    admin: bool,
    cameras: Collection[str] | None,
    expires_at: datetime | None,
    created_by: str,
) -> ApiKey:
    if admin and cameras is not None:
        raise ValueError("admin keys cannot be limited to cameras")
    key = ApiKey(
        id=key_id,
        name=name,
        token_digest=digest,
        admin=admin,
        cameras=None if cameras is None else sorted(set(cameras)),
        expires_at=expires_at,
        created_by=created_by,
        created_at=utc_now(),
    )
    session.add(key)
    session.flush()
    return key


def get_key(session: Session, key_id: str) -> ApiKey | None:
    return session.get(ApiKey, key_id)


def list_keys(
    session: Session, *, limit: int = 100, after: str | None = None, include_revoked: bool = False
) -> list[ApiKey]:
    """Keys in id order, a page at a time (pass the last id of a page as `after`); revoked ones on request."""
    stmt = select(ApiKey).order_by(ApiKey.id).limit(limit)
    if after is not None:
        stmt = stmt.where(ApiKey.id > after)
    if not include_revoked:
        stmt = stmt.where(ApiKey.revoked_at.is_(None))
    return list(session.scalars(stmt))


def revoke_key(session: Session, key_id: str, *, now: datetime | None = None) -> ApiKey | None:
    """Mark the key revoked (idempotent: a second revocation keeps the first time); None when there is no such key."""
    key = session.get(ApiKey, key_id, with_for_update=True)
    if key is None:
        return None
    if key.revoked_at is None:
        key.revoked_at = now or utc_now()
        session.flush()
    return key


def touch_key(session: Session, key_id: str, *, now: datetime, min_interval_s: float) -> bool:
    """Set last_used_at to `now` unless it was set within `min_interval_s`: True when a row was written.

    The condition lives in the UPDATE, so several API processes touching one key at once write it once.
    """
    cutoff = now - timedelta(seconds=min_interval_s)
    result = session.execute(
        update(ApiKey)
        .where(ApiKey.id == key_id, or_(ApiKey.last_used_at.is_(None), ApiKey.last_used_at < cutoff))
        .values(last_used_at=now)
    )
    return bool(getattr(result, "rowcount", 0))


def admin_key_ever_stored(session: Session) -> bool:
    """Whether any admin key was ever stored, revoked and expired ones included."""
    return bool(session.scalar(select(exists().where(ApiKey.admin))))
