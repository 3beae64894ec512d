"""The wire vocabulary every room's bodies are written in (pydantic v2): strict numbers, ids, timestamps.

Requests are strict because everything a client posts ends up as calibration evidence: unknown fields are
refused (a typo such as `anklee` would otherwise silently drop a person's ankle), numbers must be finite (Python's
JSON parser accepts `NaN` and `Infinity`, and `1e999` overflows to infinity), scores lie in [0, 1], and a COCO-17
person has exactly 17 keypoints. Checks that need the camera (coordinates within a margin of its image) or the
settings (people per frame) happen in the rooms' services, which report them in the same error format.

Names carry units (`_px`, `_m`, `_deg`, `_s`) so that a client never has to guess one. Each room's own bodies are
in its `schemas` module (service.cameras.schemas, service.frames.schemas, ...).
"""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Annotated

from pydantic import AfterValidator, AwareDatetime, BaseModel, BeforeValidator, ConfigDict, Field, WithJsonSchema
from pydantic_core import PydanticCustomError

CAMERA_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"
CLIENT_FRAME_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._:-]{0,127}$"
# A posted person's track id (service.frames.schemas.PersonObservation): a tracker's number, or one prefixed with the
# tracker's start (`2026-01-01T12:00:00Z:17`), fits in 64.
CLIENT_TRACK_ID_MAX_LENGTH = 64
CLIENT_TRACK_ID_PATTERN = rf"^[A-Za-z0-9][A-Za-z0-9._:-]{{0,{CLIENT_TRACK_ID_MAX_LENGTH - 1}}}$"


def _not_a_boolean(value: object) -> object:
    if isinstance(value, bool):
        raise PydanticCustomError("bool_not_number", "Input should be a number, not true or false")
    return value


# JSON true/false and strings are not numbers, but pydantic's lax mode reads them as numbers (a width of `true`
# pixels, a score of "0.5"). Strict floats refuse both (in Rust: keypoints hold a thousand per frame); strict
# integers would also refuse 640.0, which JSON Schema calls an integer, so integers only refuse booleans.
Number = Annotated[float, Field(strict=True)]
Integer = Annotated[int, BeforeValidator(_not_a_boolean)]
Score = Annotated[float, Field(ge=0.0, le=1.0, allow_inf_nan=False, strict=True)]
CameraId = Annotated[str, Field(pattern=CAMERA_ID_PATTERN, examples=["lobby-1"])]
# Timestamps are RFC 3339 with a zone, or Unix seconds: a JSON number (pydantic reads magnitudes above 2e10 as
# milliseconds, as JavaScript clients send them) or, in a query string or form, its digits. The JSON schema says
# exactly that, so that what the contract calls valid is what the API accepts. Every instant must exist in UTC
# (years 1-9999): "0001-01-01T00:00:00+01:00" is a valid RFC 3339 text for a moment before year 1, and converting
# it made the store, the violation window and key expiry fail with an OverflowError (a 500) before this check.
UNIX_SECONDS_TEXT_PATTERN = r"^-?[0-9]{1,13}(\.[0-9]+)?$"
_UNIX_MS_MIN, _UNIX_MS_END = -62_135_596_800_000, 253_402_300_800_000  # 0001-01-01 and 10000-01-01, in ms
TIMESTAMP_JSON_SCHEMA = {
    "anyOf": [
        {"type": "string", "format": "date-time"},
        {"type": "number", "minimum": _UNIX_MS_MIN, "exclusiveMaximum": _UNIX_MS_END},
        {"type": "string", "pattern": UNIX_SECONDS_TEXT_PATTERN},
    ]
}


def _exists_in_utc(value: datetime) -> datetime:
    try:
        value.astimezone(UTC)
    except OverflowError:
        raise PydanticCustomError(
            "timestamp_out_of_range",
            "{timestamp} is outside the years 1-9999 once converted to UTC",
            {"timestamp": value.isoformat()},
        ) from None
    return value


Timestamp = Annotated[AwareDatetime, AfterValidator(_exists_in_utc), WithJsonSchema(TIMESTAMP_JSON_SCHEMA)]
# In a query string or a form everything is text.
TIMESTAMP_TEXT_JSON_SCHEMA = {"anyOf": [TIMESTAMP_JSON_SCHEMA["anyOf"][0], TIMESTAMP_JSON_SCHEMA["anyOf"][2]]}
TimestampText = Annotated[AwareDatetime, AfterValidator(_exists_in_utc), WithJsonSchema(TIMESTAMP_TEXT_JSON_SCHEMA)]


class StrictModel(BaseModel):
    """Base of every request body: unknown fields are an error, not silently ignored."""

    model_config = ConfigDict(extra="forbid")
