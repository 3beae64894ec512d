"""Bodies of the key-management routes (`/v1/keys`)."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, StrictBool, model_validator
from pydantic_core import PydanticCustomError

from service.http.schemas import CameraId, StrictModel, Timestamp
from service.store.models import API_KEY_NAME_MAX_LENGTH

from .tokens import TOKEN_FORMAT

MAX_SCOPED_CAMERAS = 1000


class KeyCreate(StrictModel):
    """A new key: a name saying who or what holds it, and what it may do."""

    # The schema says what _consistent enforces: an admin key is never limited to cameras.
    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "not": {
                "required": ["admin", "cameras"],
                "properties": {"admin": {"const": True}, "cameras": {"type": "array"}},
            }
        },
    )

    name: str = Field(
        min_length=1,
        max_length=API_KEY_NAME_MAX_LENGTH,
        description="Who or what holds the key (a camera system, a dashboard, a person).",
        examples=["lobby camera gateway"],
    )
    admin: StrictBool = Field(default=False, description="Admin keys manage keys; they are never limited to cameras.")
    cameras: list[CameraId] | None = Field(
        default=None,
        min_length=1,
        max_length=MAX_SCOPED_CAMERAS,
        description="Limit the key to these camera ids (they need not exist yet; the key may create them). Such a "
        "key lists only these cameras and gets 403 for any other. Null: every camera.",
        examples=[["lobby-1", "lobby-2"]],
    )
    expires_at: Timestamp | None = Field(
        default=None, description="When the key stops working (RFC 3339 with zone). Null: never."
    )

    @model_validator(mode="after")
    def _consistent(self) -> KeyCreate:
        if self.admin and self.cameras is not None:
            raise ValueError("an admin key cannot be limited to cameras: leave `cameras` null, or `admin` false")
        if self.expires_at is not None and self.expires_at <= datetime.now(UTC):
            # Its own error type: a rule that depends on the clock, which no schema can state.
            raise PydanticCustomError("expires_in_past", "`expires_at` must be in the future")
        return self


class KeyOut(BaseModel):
    """A stored key as listed: everything but the token, which is shown once, when the key is created."""

    id: str = Field(description="The key's id, also the part after `pm_` in its token.")
    name: str
    admin: bool
    cameras: list[str] | None = Field(description="The cameras the key is limited to; null: every camera.")
    state: Literal["active", "expired", "revoked"]
    created_at: datetime
    created_by: str = Field(description="The key id (or `POSEMETRY_ADMIN_KEY`, or a command) that issued it.")
    last_used_at: datetime | None = Field(
        description="When the key last authenticated a request, to about a minute (written at most once a minute)."
    )
    expires_at: datetime | None
    revoked_at: datetime | None
    url: str


class KeyCreated(KeyOut):
    token: str = Field(
        description=f"The key itself ({TOKEN_FORMAT}), shown only in this response: only a hash of it is stored, "
        "so it cannot be shown again. Send it as `Authorization: Bearer <token>`."
    )


class KeyList(BaseModel):
    """One page of keys in id order; pass `next_after` as `after` for the next page (null: last page)."""

    items: list[KeyOut]
    next_after: str | None


class CallerOut(BaseModel):
    """The key this request was authenticated with."""

    key_id: str | None = Field(description="Null for the admin key configured as POSEMETRY_ADMIN_KEY.")
    name: str
    admin: bool
    cameras: list[str] | None = Field(description="The cameras the key is limited to; null: every camera.")
    expires_at: datetime | None
