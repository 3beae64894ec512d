"""The properties every answer of the API must have, as schemathesis checks `(ctx, response, case) -> None`.

On top of schemathesis' own checks (no 5xx, status codes, content types and bodies as documented, schema-invalid
requests refused, the `Allow` header of a 405, ...):

- `errors_are_problems`: every 4xx and 5xx is `application/problem+json` with `type`, `title`, `status` (the
  response's) and `detail`.
- `valid_input_refused_only_for_stated_reasons` replaces schemathesis' positive_data_acceptance: a request the
  schema calls valid may still be refused, but only for a reason the schema cannot state (a camera that does not
  exist, a point far outside the camera's image, a window of too many buckets, an address the SSRF policy
  refuses, bytes that are not an image...), each with its own problem type or error type listed below. Anything
  else, a pydantic error on a schema-valid body in particular, means the published schema is wrong.
- `no_key_gets_nothing`: without a valid key no protected operation answers 2xx (nor reveals whether a camera
  exists).
- `scope_is_kept`: a key limited to one camera gets nothing from other cameras, not even a 404, and nothing from
  admin-only operations.
"""

from __future__ import annotations

import json
from typing import Any

from schemathesis import Case, CheckContext, Response

from service.http.problems import PROBLEM_MEDIA_TYPE, TYPE_BASE

# Problem types for refusals of schema-valid requests that depend on state or on data no schema can describe.
STATED_PROBLEM_TYPES = frozenset(
    {
        "camera-not-found",
        "frame-not-found",
        "webhook-not-found",
        "delivery-not-found",
        "key-not-found",
        "not-found",
        "bad-cursor",  # `after` names a subscription that does not exist
        "invalid-window",  # `since` not before `until`
        "window-too-large",  # more than 10 000 buckets
        "webhook-url-refused",  # the SSRF policy, after DNS resolution
        "unsupported-media-type",  # binary bytes that are not a JPEG or PNG
        "invalid-image",  # bytes that start like an image but do not decode
        "image-size-mismatch",  # a real image of another size than the camera's
        "image-too-large",
        "body-too-large",
        "too-many-people",
    }
)
# Error types (`errors[].type` of a validation problem) for the same kind of reason.
STATED_ERROR_TYPES = frozenset(
    {
        "coordinate_out_of_image",  # depends on the camera's image size
        "intrinsics_out_of_image",  # a principal point or focal length that does not fit the image size
        "timestamp_out_of_range",  # a valid RFC 3339 text for an instant before year 1 or after 9999 in UTC
        "expires_in_past",  # depends on the clock
        "duplicate_track_id",  # two people of one frame with one track_id: no schema states uniqueness of a property
    }
)
# Statuses that schema-valid requests may get whatever the reason (schemathesis' own list for this check).
ALWAYS_ALLOWED = frozenset({401, 403, 404, 405, 409, 429})


def _problem(response: Response) -> dict[str, Any] | None:
    try:
        body = json.loads(response.content)
    except ValueError:
        return None
    return body if isinstance(body, dict) else None


def _media_type(response: Response) -> str:
    values = response.headers.get("content-type") or [""]
    return values[0].split(";", 1)[0].strip().lower()


def is_positive(case: Case) -> bool:
    """Whether every part of the request is valid under the schema, as generated."""
    meta = case.meta
    if meta is None:
        return False
    return not meta.generation.mode.is_negative and not any(c.mode.is_negative for c in meta.components.values())


def errors_are_problems(ctx: CheckContext, response: Response, case: Case) -> None:
    if response.status_code < 400:
        return
    assert _media_type(response) == PROBLEM_MEDIA_TYPE, (
        f"{response.status_code} answered with Content-Type {_media_type(response) or 'none'}, not {PROBLEM_MEDIA_TYPE}"
    )
    body = _problem(response)
    assert body is not None, f"{response.status_code} problem body is not a JSON object"
    missing = [name for name in ("type", "title", "status", "detail") if not body.get(name)]
    assert not missing, f"problem document without {', '.join(missing)}: {body}"
    assert body["status"] == response.status_code, f"problem status {body['status']} != {response.status_code}"
    assert str(body["type"]).startswith(TYPE_BASE), f"problem type {body['type']!r} outside {TYPE_BASE}"


def valid_input_refused_only_for_stated_reasons(ctx: CheckContext, response: Response, case: Case) -> None:
    """For requests valid under the schema as generated (tests/fuzz/test_schemathesis.py applies it to those)."""
    status = response.status_code
    if status < 400 or status >= 500 or status in ALWAYS_ALLOWED:
        return
    body = _problem(response) or {}
    kind = str(body.get("type", "")).removeprefix(TYPE_BASE)
    if kind in STATED_PROBLEM_TYPES:
        return
    errors = body.get("errors") or []
    if kind == "validation-error" and errors and all(e.get("type") in STATED_ERROR_TYPES for e in errors):
        return
    raise AssertionError(
        f"a request valid under the published schema was refused with {status} {kind!r}: {body.get('detail')} "
        "(the schema and the validation disagree)"
    )


def no_key_gets_nothing(ctx: CheckContext, response: Response, case: Case) -> None:
    if case.operation.path in ("/healthz", "/readyz"):
        return
    assert response.status_code in (401, 404, 405), (
        f"{case.operation.label} without a valid key answered {response.status_code}, not 401"
    )
    if response.status_code == 401:
        assert response.headers.get("www-authenticate"), "401 without WWW-Authenticate"


ADMIN_ONLY_PREFIXES = ("/v1/webhooks", "/metrics")


def scope_is_kept(camera: str) -> Any:
    """The check for a key limited to `camera`."""

    def check(ctx: CheckContext, response: Response, case: Case) -> None:
        operation, status = case.operation, response.status_code
        admin_only = operation.path.startswith(ADMIN_ONLY_PREFIXES) or (
            operation.path.startswith("/v1/keys") and operation.path != "/v1/keys/current"
        )
        other_camera = (case.path_parameters or {}).get("camera_id", camera) != camera
        if admin_only or other_camera:
            assert status >= 400, f"a key limited to {camera!r} got {status} from {operation.label}"
        if other_camera and status == 404:
            kind = str((_problem(response) or {}).get("type", "")).removeprefix(TYPE_BASE)
            assert kind != "camera-not-found", "a key limited to another camera learned whether a camera exists"

    check.__name__ = "scope_is_kept"
    return check
