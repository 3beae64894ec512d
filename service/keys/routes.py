"""API keys: admins create, list, read and revoke them; any key can ask who it is."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated

from fastapi import APIRouter, Path, Query, Request, Response, status
from starlette.convertors import Convertor, register_url_convertor

from service.http.dependencies import ReadSessionDep, SessionDep
from service.http.problems import ProblemError
from service.keys import repository
from service.keys.authenticator import Authenticator
from service.keys.dependencies import AdminDep, PrincipalDep
from service.keys.principal import SETTINGS_ADMIN_NAME
from service.keys.schemas import CallerOut, KeyCreate, KeyCreated, KeyList, KeyOut
from service.keys.service import issue_key
from service.keys.tokens import KEY_ID_PATTERN
from service.store.models import ApiKey

router = APIRouter(prefix="/v1/keys", tags=["keys"])

KeyIdPath = Annotated[str, Path(pattern=KEY_ID_PATTERN, description="The key's id (12 hex digits).")]


class _KeyIdConvertor(Convertor[str]):
    """Routes `/v1/keys/{key_id}` to key ids only, so `/v1/keys/current` is one resource: DELETE on it is 405 with
    `Allow: GET`, not an attempt to revoke a key called "current". Other non-ids are 404."""

    regex = KEY_ID_PATTERN.removeprefix("^").removesuffix("$")

    def convert(self, value: str) -> str:
        return value

    def to_string(self, value: str) -> str:
        return value


register_url_convertor("key_id", _KeyIdConvertor())


def key_url(key_id: str) -> str:
    return f"/v1/keys/{key_id}"


def key_out(key: ApiKey) -> KeyOut:
    if key.revoked_at is not None:
        state = "revoked"
    elif key.expires_at is not None and key.expires_at <= datetime.now(UTC):
        state = "expired"
    else:
        state = "active"
    return KeyOut(
        id=key.id,
        name=key.name,
        admin=key.admin,
        cameras=key.cameras,
        state=state,
        created_at=key.created_at,
        created_by=key.created_by,
        last_used_at=key.last_used_at,
        expires_at=key.expires_at,
        revoked_at=key.revoked_at,
        url=key_url(key.id),
    )


def _key_not_found(key_id: str) -> ProblemError:
    return ProblemError(404, "key-not-found", f"No API key {key_id!r}.")


@router.post("", status_code=status.HTTP_201_CREATED, response_model=KeyCreated)
def create_key(body: KeyCreate, response: Response, session: SessionDep, caller: AdminDep) -> KeyCreated:
    """Create a key and return its token, once: only a hash is stored, so store the token now."""
    issued = issue_key(
        session,
        name=body.name,
        admin=body.admin,
        cameras=body.cameras,
        expires_at=body.expires_at,
        created_by=caller.key_id or SETTINGS_ADMIN_NAME,
    )
    session.commit()
    response.headers["Location"] = key_url(issued.key.id)
    return KeyCreated(**key_out(issued.key).model_dump(), token=issued.token)


@router.get("", response_model=KeyList)
def list_keys(
    session: ReadSessionDep,
    _caller: AdminDep,
    limit: Annotated[int, Query(ge=1, le=1000, description="Keys per page.")] = 100,
    after: Annotated[str | None, Query(max_length=64, description="Last id of the previous page.")] = None,
    include_revoked: Annotated[bool, Query(description="Also list revoked keys.")] = False,
) -> KeyList:
    """Keys in id order, a page at a time; revoked ones only on request. Tokens are never shown again."""
    keys = repository.list_keys(session, limit=limit, after=after, include_revoked=include_revoked)
    return KeyList(items=[key_out(k) for k in keys], next_after=keys[-1].id if len(keys) == limit else None)


@router.get("/current", response_model=CallerOut)
def get_current_key(caller: PrincipalDep) -> CallerOut:
    """The key this request is authenticated with: any key may ask (whether it is an admin, its cameras)."""
    return CallerOut(
        key_id=caller.key_id,
        name=caller.name,
        admin=caller.admin,
        cameras=None if caller.cameras is None else sorted(caller.cameras),
        expires_at=caller.expires_at,
    )


@router.get("/{key_id:key_id}", response_model=KeyOut)
def get_key(key_id: KeyIdPath, session: ReadSessionDep, _caller: AdminDep) -> KeyOut:
    key = repository.get_key(session, key_id)
    if key is None:
        raise _key_not_found(key_id)
    return key_out(key)


@router.delete("/{key_id:key_id}", response_model=KeyOut)
def revoke_key(key_id: KeyIdPath, request: Request, session: SessionDep, _caller: AdminDep) -> KeyOut:
    """Revoke a key (idempotent). This API process refuses it at once; the others within `api_key_cache_ttl_s`.

    The key stays listed (with `include_revoked`) with its revocation time, for audits.
    """
    key = repository.revoke_key(session, key_id)
    if key is None:
        raise _key_not_found(key_id)
    session.commit()
    authenticator: Authenticator = request.app.state.authenticator
    authenticator.forget(key_id)
    return key_out(key)
