"""Image uploads: the picture and its frame metadata from a raw `image/*` body or a multipart form.

Cameras and scripts usually POST the JPEG itself (`Content-Type: image/jpeg`, metadata in the query string);
browsers and many HTTP tools send `multipart/form-data` with an `image` file field and optional `timestamp` and
`frame_id` fields. Both arrive here as one `Upload`. The declared type must match the bytes: a mislabelled upload
is the client's bug and gets a 415 that says so, rather than being silently reinterpreted.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from fastapi import Request
from pydantic import TypeAdapter, ValidationError
from starlette.datastructures import UploadFile

from service.frames.images import JPEG, PNG, other_image_format, sniff_content_type
from service.http.problems import ProblemError
from service.http.schemas import CLIENT_FRAME_ID_PATTERN, TIMESTAMP_TEXT_JSON_SCHEMA, TimestampText

MULTIPART = "multipart/form-data"
IMAGE_TYPES = frozenset({JPEG, PNG})
UPLOAD_TYPES = frozenset({*IMAGE_TYPES, MULTIPART})
IMAGE_FIELD = "image"
FORM_FIELDS = frozenset({IMAGE_FIELD, "timestamp", "frame_id"})
# A form carries the image plus two short fields; far more than that is refused while parsing, and any field not
# in FORM_FIELDS after it (like an unknown field of a JSON body: a typo would otherwise be silently ignored).
MAX_FORM_FIELDS = 4
_TIMESTAMP = TypeAdapter(TimestampText)

# The request body as documented in OpenAPI (the route reads the raw request, so FastAPI cannot infer it).
OPENAPI_REQUEST_BODY: dict[str, Any] = {
    "required": True,
    "content": {
        JPEG: {"schema": {"type": "string", "format": "binary"}},
        PNG: {"schema": {"type": "string", "format": "binary"}},
        MULTIPART: {
            "schema": {
                "type": "object",
                "required": [IMAGE_FIELD],
                "properties": {
                    IMAGE_FIELD: {"type": "string", "format": "binary", "description": "The JPEG or PNG file."},
                    "timestamp": {**TIMESTAMP_TEXT_JSON_SCHEMA, "description": "As the query parameter."},
                    "frame_id": {"type": "string", "pattern": CLIENT_FRAME_ID_PATTERN},
                },
                "additionalProperties": False,
            }
        },
    },
}


@dataclass(frozen=True)
class Upload:
    data: bytes
    content_type: str
    """Sniffed from the bytes (and equal to the declared type)."""
    timestamp: datetime
    frame_id: str | None
    timestamp_given: bool = True
    """False when the client sent no timestamp and `timestamp` is the time of receipt (not part of the content a
    retry must repeat)."""


def _bad(detail: str, status: int = 422, kind: str = "invalid-image") -> ProblemError:
    return ProblemError(status, kind, detail)


def _checked_type(data: bytes, declared: str) -> str:
    if not data:
        raise _bad("The image is empty: send the JPEG or PNG bytes as the body (or as the form's `image` file).")
    actual = sniff_content_type(data)
    if actual is None:
        other = other_image_format(data)
        detail = (
            "The body is not a JPEG or PNG image (unrecognised file signature)."
            if other is None
            else f"The body is a {other} image; posemetry reads JPEG and PNG (set the camera or phone to save JPEG, "
            "or convert the picture)."
        )
        raise _bad(detail, 415, "unsupported-media-type")
    if declared in IMAGE_TYPES and declared != actual:
        raise _bad(f"Declared {declared}, but the bytes are a {actual} image.", 415, "unsupported-media-type")
    return actual


def _timestamp(value: str | datetime | None) -> datetime:
    if value is None or value == "":
        return datetime.now(UTC)
    if isinstance(value, datetime):
        return value
    try:
        return _TIMESTAMP.validate_python(value)
    except ValidationError:
        raise _bad(
            f"timestamp {value!r} is not an RFC 3339 date-time with a time zone.", kind="validation-error"
        ) from None


def _frame_id(value: str | None) -> str | None:
    if value is not None and re.fullmatch(CLIENT_FRAME_ID_PATTERN, value) is None:
        raise _bad(
            f"frame_id must match {CLIENT_FRAME_ID_PATTERN} (1-128 letters, digits, '.', '_', ':', '-').",
            kind="validation-error",
        )
    return value


async def read_upload(request: Request, *, timestamp: datetime | None, frame_id: str | None) -> Upload:
    """The upload of an image-frame POST (the body has already passed BodyGuard's size and media-type checks)."""
    declared = request.headers.get("content-type", "").split(";", 1)[0].strip().lower()
    if declared != MULTIPART:
        data = await request.body()
        given = timestamp is not None
        return Upload(data, _checked_type(data, declared), _timestamp(timestamp), _frame_id(frame_id), given)
    try:
        form = await request.form(max_files=1, max_fields=MAX_FORM_FIELDS)
    except Exception as exc:  # the multipart parser raises several types for malformed forms
        raise _bad(f"Malformed multipart form: {exc}", 400, "bad-request") from exc
    try:
        unknown = sorted(set(form.keys()) - FORM_FIELDS)
        if unknown:
            names = ", ".join(repr(name) for name in unknown)
            raise _bad(
                f"Unknown multipart field(s) {names}: the form takes `image`, `timestamp` and `frame_id`.",
                kind="validation-error",
            )
        part = form.get(IMAGE_FIELD)
        if not isinstance(part, UploadFile):
            raise _bad(f"The multipart form needs a file field named `{IMAGE_FIELD}`.")
        data = await part.read()
        form_timestamp = form.get("timestamp")
        form_frame_id = form.get("frame_id")
    finally:
        await form.close()
    part_type = (part.content_type or "").split(";", 1)[0].strip().lower()
    chosen_timestamp = form_timestamp if isinstance(form_timestamp, str) and form_timestamp else timestamp
    return Upload(
        data,
        _checked_type(data, part_type),
        _timestamp(chosen_timestamp),
        _frame_id(form_frame_id if isinstance(form_frame_id, str) and form_frame_id else frame_id),
        chosen_timestamp is not None,
    )
