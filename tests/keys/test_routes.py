"""API keys over HTTP: who gets in (401), who may do what (403), the key life cycle, hashing and the key cache."""

from __future__ import annotations

import re
import time
import uuid
from collections.abc import Callable, Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from sqlalchemy import event, text
from sqlalchemy.orm import Session

from service.app import create_app
from service.keys import repository as stored_keys
from service.keys.service import issue_key
from service.keys.tokens import token_digest
from service.settings import Settings
from tests.support.app import ADMIN_KEY, CAMERA, HEIGHT_PX, WIDTH_PX, assert_problem, bearer, frame_body, standing
from tests.support.dispatch import RecordingDispatcher

BOTH = pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
# Anyone may call these: health checks for load balancers, the API's documentation and the operator console's page,
# script and style sheet (no data in any of them: the console's script reads the API with the operator's key).
PUBLIC_PATHS = {"/healthz", "/readyz", "/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json"}
PUBLIC_PATHS |= {"/console", "/console/{name}"}
SAMPLE_PATH_VALUES = {"camera_id": CAMERA, "frame_id": str(uuid.UUID(int=1)), "key_id": "0123456789ab"}
CAMERA_SETTINGS = {"image_width_px": WIDTH_PX, "image_height_px": HEIGHT_PX}


def _routes(app: FastAPI) -> list[tuple[str, str]]:
    """(method, path template) of every route the app serves, included routers and mounts too."""
    try:  # FastAPI >= 0.130 keeps included routers unflattened; this walks into them
        from fastapi.routing import iter_route_contexts

        routes: list[Any] = list(iter_route_contexts(app.routes))
    except ImportError:
        routes = list(app.routes)
    found = []
    for route in routes:
        methods = getattr(route, "methods", None) or {"GET"}  # a mount answers whatever it answers to GET
        found += [(method, route.path) for method in sorted(set(methods) - {"HEAD", "OPTIONS"})]
    return found


def _concrete(path: str) -> str:
    return re.sub(r"\{(\w+)(?::[^}]*)?\}", lambda m: SAMPLE_PATH_VALUES.get(m.group(1), "x"), path)


def _assert_unauthenticated(response: Any, *fragments: str, token_given: bool) -> None:
    assert_problem(response, 401, *fragments)
    challenge = response.headers["www-authenticate"]
    assert challenge.startswith('Bearer realm="posemetry"')
    assert ('error="invalid_token"' in challenge) == token_given, challenge


def new_key(client: TestClient, **body: Any) -> dict[str, Any]:
    response = client.post("/v1/keys", json={"name": "test key", **body})
    assert response.status_code == 201, response.text
    return response.json()


# --------------------------------------------------------------------------------------------------- who gets in


def test_every_route_but_health_and_docs_needs_a_key(app: FastAPI, anonymous: TestClient) -> None:
    """Walks the app's routes, so a route added later without protection fails here."""
    routes = _routes(app)
    assert ("GET", "/v1/cameras") in routes and ("POST", "/v1/keys") in routes and len(routes) > 20
    protected = [(method, path) for method, path in routes if path not in PUBLIC_PATHS]
    for method, path in protected:
        response = anonymous.request(method, _concrete(path))
        assert response.status_code == 401, (method, path, response.status_code, response.text)
        _assert_unauthenticated(response, "Authorization: Bearer", token_given=False)
    assert {path for _, path in routes} - {path for _, path in protected} == PUBLIC_PATHS


def test_health_and_documentation_need_no_key(anonymous: TestClient) -> None:
    assert anonymous.get("/healthz").json() == {"status": "ok"}
    assert anonymous.get("/readyz").status_code == 200
    assert anonymous.get("/openapi.json").json()["components"]["securitySchemes"]["ApiKey"]["scheme"] == "bearer"
    for page in ("/docs", "/redoc"):
        assert anonymous.get(page).status_code == 200


def test_openapi_declares_the_bearer_scheme_and_auth_problems(app: FastAPI) -> None:
    spec = app.openapi()
    scheme = spec["components"]["securitySchemes"]["ApiKey"]
    assert scheme["type"] == "http" and scheme["scheme"] == "bearer" and scheme["bearerFormat"].startswith("pm_")
    for path, operations in spec["paths"].items():
        for method, operation in operations.items():
            public = path in PUBLIC_PATHS
            assert (operation.get("security") == [{"ApiKey": []}]) != public, (method, path)
            if not public:
                for status in ("401", "403"):
                    content = operation["responses"][status]["content"]
                    assert "application/problem+json" in content, (method, path, status)


@pytest.mark.parametrize(
    ("authorization", "fragment", "token_given"),
    [
        (None, "needs an API key", False),
        ("", "needs an API key", False),
        ("Basic dXNlcjpwYXNz", "the Basic scheme", False),
        (f"Token {ADMIN_KEY}", "the Token scheme", False),
        ("Bearer", "no key after `Bearer`", False),
        ("Bearer    ", "no key after `Bearer`", False),
        ("Bearer not-a-key", "not a posemetry api key", True),
        ("Bearer pm_0123456789ab_" + "A" * 43, "unknown api key", True),
        (f"Bearer {ADMIN_KEY}x", "not a posemetry api key", True),
    ],
)
def test_missing_or_malformed_keys_are_refused(
    anonymous: TestClient, authorization: str | None, fragment: str, token_given: bool
) -> None:
    headers = {} if authorization is None else {"Authorization": authorization}
    response = anonymous.get("/v1/cameras", headers=headers)
    _assert_unauthenticated(response, fragment, token_given=token_given)


def test_bodies_of_callers_without_a_key_are_not_read(anonymous: TestClient, settings: Settings, camera: str) -> None:
    """401 comes before the body checks (size, type, JSON), so an anonymous caller cannot make the service read
    a large upload, and learns nothing from a 413, 415 or 400."""
    cases = [
        ("/keypoints", b"x" * (settings.max_body_bytes + 1), "application/json"),  # would be 413
        ("/keypoints", b"{not json", "application/json"),  # 400
        ("/keypoints", b"<xml/>", "application/xml"),  # 415
        ("/frames", b"\xff\xd8" + b"\0" * (settings.max_image_bytes + 100_000), "image/jpeg"),  # 413
    ]
    for suffix, body, content_type in cases:
        response = anonymous.post(f"/v1/cameras/{camera}{suffix}", content=body, headers={"content-type": content_type})
        _assert_unauthenticated(response, "needs an API key", token_given=False)
    assert anonymous.put(f"/v1/cameras/{camera}", content=b"{").status_code == 401


def test_scheme_is_case_insensitive(anonymous: TestClient) -> None:
    assert anonymous.get("/v1/cameras", headers={"Authorization": f"bearer {ADMIN_KEY}"}).status_code == 200
    assert anonymous.get("/v1/cameras", headers={"Authorization": f"BEARER  {ADMIN_KEY} "}).status_code == 200


@BOTH
def test_a_stored_key_with_a_wrong_secret_is_unknown(
    client: TestClient, client_for: Callable[[str], TestClient]
) -> None:
    token = new_key(client)["token"]
    forged = token[:-1] + ("a" if token[-1] != "a" else "b")  # right id, wrong secret
    _assert_unauthenticated(client_for(forged).get("/v1/cameras"), "unknown api key", token_given=True)
    assert client_for(token).get("/v1/cameras").status_code == 200


@BOTH
def test_revoked_and_expired_keys_are_refused(
    client: TestClient, client_for: Callable[[str], TestClient], app: FastAPI
) -> None:
    revoked = new_key(client)
    assert client_for(revoked["token"]).get("/v1/cameras").status_code == 200
    assert client.delete(f"/v1/keys/{revoked['id']}").status_code == 200
    _assert_unauthenticated(client_for(revoked["token"]).get("/v1/cameras"), "was revoked", token_given=True)

    # A key past its expiry date (stored directly: the API only accepts future dates).
    with app.state.session_factory() as session:
        expired = issue_key(session, name="old", expires_at=datetime.now(UTC) - timedelta(seconds=1), created_by="test")
        session.commit()
    _assert_unauthenticated(client_for(expired.token).get("/v1/cameras"), "expired at", token_given=True)
    assert client.get(f"/v1/keys/{expired.key.id}").json()["state"] == "expired"


def test_a_cached_key_stops_working_when_it_expires(
    client: TestClient, client_for: Callable[[str], TestClient]
) -> None:
    expires_at = datetime.now(UTC) + timedelta(seconds=2)
    key = new_key(client, expires_at=expires_at.isoformat())
    holder = client_for(key["token"])
    assert holder.get("/v1/cameras").status_code == 200  # verified and cached for 10 s
    time.sleep(max(0.0, (expires_at - datetime.now(UTC)).total_seconds()) + 0.05)
    _assert_unauthenticated(holder.get("/v1/cameras"), "expired", token_given=True)


# --------------------------------------------------------------------------------------------------- what a key may do


def test_only_admin_keys_manage_keys(client: TestClient, client_for: Callable[[str], TestClient]) -> None:
    plain = new_key(client)
    holder = client_for(plain["token"])
    target = new_key(client, name="someone else")
    for method, path, body in (
        ("POST", "/v1/keys", {"name": "mine"}),
        ("GET", "/v1/keys", None),
        ("GET", f"/v1/keys/{target['id']}", None),
        ("DELETE", f"/v1/keys/{target['id']}", None),
        ("DELETE", f"/v1/keys/{plain['id']}", None),
    ):
        response = holder.request(method, path, json=body)
        assert_problem(response, 403, "only admin keys")
        assert response.json()["type"].endswith("/admin-key-required")
        assert 'error="insufficient_scope"' in response.headers["www-authenticate"]
    assert client.get(f"/v1/keys/{target['id']}").json()["state"] == "active"
    # Any key may ask who it is.
    assert holder.get("/v1/keys/current").json() == {
        "key_id": plain["id"],
        "name": "test key",
        "admin": False,
        "cameras": None,
        "expires_at": None,
    }


def test_only_admin_keys_manage_webhooks_and_read_metrics(
    client: TestClient, client_for: Callable[[str], TestClient]
) -> None:
    """A subscription sends camera data to an outside URL: an operator's decision, so camera keys get 403."""
    holder = client_for(new_key(client)["token"])
    subscription = client.post("/v1/webhooks", json={"url": "https://93.184.216.34/hook"}).json()
    for method, path, body in (
        ("POST", "/v1/webhooks", {"url": "https://93.184.216.34/mine"}),
        ("GET", "/v1/webhooks", None),
        ("GET", f"/v1/webhooks/{subscription['id']}", None),
        ("GET", f"/v1/webhooks/{subscription['id']}/deliveries", None),
        ("DELETE", f"/v1/webhooks/{subscription['id']}", None),
    ):
        assert_problem(holder.request(method, path, json=body), 403, "admin keys")
    assert [item["id"] for item in client.get("/v1/webhooks").json()["items"]] == [subscription["id"]]
    # /metrics names every camera: admins (and the Prometheus that holds an admin key) only.
    assert_problem(holder.get("/metrics"), 403, "admin keys")
    assert client.get("/metrics").status_code == 200


def test_admin_keys_made_over_http_manage_keys_too(client: TestClient, client_for: Callable[[str], TestClient]) -> None:
    admin = client_for(new_key(client, name="second admin", admin=True)["token"])
    made = new_key(admin, name="made by the second admin")
    assert made["created_by"] == admin.get("/v1/keys/current").json()["key_id"]
    assert new_key(client)["created_by"] == "POSEMETRY_ADMIN_KEY"
    assert admin.delete(f"/v1/keys/{made['id']}").json()["state"] == "revoked"


@BOTH
def test_a_camera_scoped_key_sees_and_uses_only_its_cameras(
    client: TestClient, client_for: Callable[[str], TestClient]
) -> None:
    for camera in ("a-1", "b-2", "c-3"):
        assert client.put(f"/v1/cameras/{camera}", json=CAMERA_SETTINGS).status_code == 201
    key = new_key(client, cameras=["b-2", "a-1", "a-1", "d-4"])
    assert key["cameras"] == ["a-1", "b-2", "d-4"]
    scoped = client_for(key["token"])
    assert [c["id"] for c in scoped.get("/v1/cameras").json()["items"]] == ["a-1", "b-2"]
    assert [c["id"] for c in scoped.get("/v1/cameras", params={"limit": 1}).json()["items"]] == ["a-1"]
    assert [c["id"] for c in client.get("/v1/cameras").json()["items"]] == ["a-1", "b-2", "c-3"]
    assert scoped.get("/v1/cameras/a-1").status_code == 200
    assert scoped.post("/v1/cameras/b-2/keypoints", json=frame_body(standing(3))).status_code == 202
    # d-4 does not exist yet; the key may create it.
    assert scoped.put("/v1/cameras/d-4", json=CAMERA_SETTINGS).status_code == 201
    # Outside the scope: 403 whether the camera exists (c-3) or not (z-9), so existence does not leak.
    for camera in ("c-3", "z-9"):
        response = scoped.get(f"/v1/cameras/{camera}")
        assert_problem(response, 403, "limited to other cameras", camera)
        assert response.json()["type"].endswith("/camera-out-of-scope")
    assert scoped.get("/v1/cameras/c-3/calibration").status_code == 403
    assert scoped.delete("/v1/cameras/c-3").status_code == 403
    assert client.get("/v1/cameras/c-3").status_code == 200
    assert scoped.get("/v1/keys/current").json()["cameras"] == ["a-1", "b-2", "d-4"]


def test_every_camera_route_enforces_the_scope(
    app: FastAPI, client: TestClient, client_for: Callable[[str], TestClient]
) -> None:
    """Walks the routes: any route with a {camera_id} (including later ones) refuses a camera outside the scope."""
    scoped = client_for(new_key(client, cameras=["elsewhere"])["token"])
    camera_routes = [(m, p) for m, p in _routes(app) if "{camera_id}" in p]
    assert len(camera_routes) >= 15
    for method, path in camera_routes:
        # An empty body passes every route's body checks (which, for a valid key, come before the scope check:
        # JSON routes take an empty body of any type, the image route wants an image type).
        response = scoped.request(method, _concrete(path), content=b"", headers={"content-type": "image/jpeg"})
        assert response.status_code == 403, (method, path, response.text)
        assert response.json()["type"].endswith("/camera-out-of-scope")


@pytest.mark.parametrize(
    ("body", "fragment"),
    [
        ({"name": "x", "admin": True, "cameras": ["a"]}, "admin key cannot be limited"),
        ({"name": "x", "cameras": []}, "at least 1 item"),
        ({"name": "x", "cameras": ["../etc"]}, "string should match pattern"),
        ({"name": "x", "expires_at": "2020-01-01T00:00:00Z"}, "must be in the future"),
        ({"name": "x", "expires_at": "2099-01-01T00:00:00"}, "timezone"),
        ({"name": ""}, "at least 1 character"),
        ({"name": "x", "scope": "all"}, "extra inputs"),
    ],
)
def test_invalid_key_requests_are_422(client: TestClient, body: dict[str, Any], fragment: str) -> None:
    assert_problem(client.post("/v1/keys", json=body), 422, fragment)


# --------------------------------------------------------------------------------------------------- life cycle


@BOTH
def test_key_life_cycle_over_http(client: TestClient, client_for: Callable[[str], TestClient]) -> None:
    response = client.post(
        "/v1/keys", json={"name": "gateway", "cameras": ["lobby"], "expires_at": "2099-01-01T00:00:00Z"}
    )
    assert response.status_code == 201, response.text
    created = response.json()
    key_id, token = created["id"], created["token"]
    assert re.fullmatch(r"pm_[0-9a-f]{12}_[0-9A-Za-z]{43}", token) and token.startswith(f"pm_{key_id}_")
    assert response.headers["location"] == created["url"] == f"/v1/keys/{key_id}"
    assert created["state"] == "active" and created["last_used_at"] is None and created["revoked_at"] is None
    assert created["expires_at"].startswith("2099-01-01T00:00:00")

    # The token is shown once: never in the key's reads or listings.
    shown = client.get(f"/v1/keys/{key_id}").json()
    assert "token" not in shown and shown == {k: v for k, v in created.items() if k != "token"}
    listed = client.get("/v1/keys").json()
    assert [k["id"] for k in listed["items"]] == [key_id] and token not in str(listed)

    assert client_for(token).get("/v1/cameras").status_code == 200
    used = client.get(f"/v1/keys/{key_id}").json()["last_used_at"]
    assert used is not None and datetime.fromisoformat(used) > datetime.now(UTC) - timedelta(minutes=1)

    revoked = client.delete(f"/v1/keys/{key_id}")
    assert revoked.status_code == 200 and revoked.json()["state"] == "revoked"
    again = client.delete(f"/v1/keys/{key_id}").json()
    assert again["revoked_at"] == revoked.json()["revoked_at"]  # idempotent: the first revocation time stays
    assert client.get("/v1/keys").json()["items"] == []
    assert [k["id"] for k in client.get("/v1/keys", params={"include_revoked": True}).json()["items"]] == [key_id]
    _assert_unauthenticated(client_for(token).get("/v1/cameras"), "revoked", token_given=True)

    assert_problem(client.get("/v1/keys/0123456789ab"), 404, "no api key")
    assert_problem(client.delete("/v1/keys/0123456789ab"), 404, "no api key")
    # Only key ids route to a key: anything else is no resource at all, and `current` is its own.
    assert_problem(client.get("/v1/keys/NOT-AN-ID"), 404, "no such resource")
    refused = client.delete("/v1/keys/current")
    assert_problem(refused, 405)
    assert refused.headers["allow"] == "GET"


def test_keys_are_listed_a_page_at_a_time(client: TestClient) -> None:
    ids = sorted(new_key(client, name=f"k{i}")["id"] for i in range(5))
    first = client.get("/v1/keys", params={"limit": 3}).json()
    second = client.get("/v1/keys", params={"limit": 3, "after": first["next_after"]}).json()
    assert [k["id"] for k in first["items"] + second["items"]] == ids
    assert second["next_after"] is None


@BOTH
def test_only_a_keyed_hash_of_the_token_is_stored(client: TestClient, app: FastAPI) -> None:
    created = new_key(client, name="hashing")
    token, secret = created["token"], created["token"].rsplit("_", 1)[1]
    with app.state.engine.connect() as connection:
        row = connection.execute(text("SELECT * FROM api_keys WHERE id = :id"), {"id": created["id"]}).one()
    stored = " ".join(str(value) for value in row)
    assert token not in stored and secret not in stored
    assert row.token_digest == token_digest(token) != token
    assert re.fullmatch(r"[0-9a-f]{64}", row.token_digest)


# --------------------------------------------------------------------------------------------------- the key cache


def _app(settings: Settings, **changes: Any) -> FastAPI:
    return create_app(settings.model_copy(update=changes), dispatcher=RecordingDispatcher())


class KeyQueries:
    """The first word of every SQL statement on api_keys that the watched engines run."""

    def __init__(self) -> None:
        self.seen: list[str] = []
        self._engines: list[Any] = []

    def _record(self, _conn: Any, _cursor: Any, statement: str, *_args: Any) -> None:
        if "api_keys" in statement:
            self.seen.append(statement.split(None, 1)[0].upper())

    def watch(self, engine: Any) -> None:
        event.listen(engine, "before_cursor_execute", self._record)
        self._engines.append(engine)

    def close(self) -> None:
        for engine in self._engines:
            event.remove(engine, "before_cursor_execute", self._record)


@pytest.fixture
def key_queries(app: FastAPI) -> Iterator[KeyQueries]:
    queries = KeyQueries()
    queries.watch(app.state.engine)
    yield queries
    queries.close()


def test_a_cached_key_costs_no_database_round_trip(
    client: TestClient, client_for: Callable[[str], TestClient], key_queries: KeyQueries
) -> None:
    seen = key_queries.seen
    holder = client_for(new_key(client)["token"])
    seen.clear()
    for _ in range(20):
        assert holder.get("/v1/keys/current").status_code == 200
    # One read when the key is first seen, and one stamp of last_used_at; nothing for the other 19 requests.
    assert seen == ["SELECT", "UPDATE"]


def test_last_used_is_stamped_at_most_once_a_minute(
    app: FastAPI, client: TestClient, client_for: Callable[[str], TestClient], key_queries: KeyQueries
) -> None:
    seen = key_queries.seen
    key = new_key(client)
    # Another process will read the key from the database; it finds last_used_at fresh and does not write it.
    other = _app(app.state.settings, api_key_cache_ttl_s=0.0)
    key_queries.watch(other.state.engine)
    assert client_for(key["token"]).get("/v1/cameras").status_code == 200
    stamped = client.get(f"/v1/keys/{key['id']}").json()["last_used_at"]
    seen.clear()
    with TestClient(other, headers=bearer(key["token"])) as other_client:
        for _ in range(3):
            assert other_client.get("/v1/cameras").status_code == 200
    assert seen == ["SELECT"] * 3  # TTL 0: read on every request, but never written within the minute
    assert client.get(f"/v1/keys/{key['id']}").json()["last_used_at"] == stamped


@BOTH
def test_revocation_reaches_every_api_process_within_the_cache_ttl(
    settings: Settings, migrated_url: str, app: FastAPI, client: TestClient
) -> None:
    """Two apps on one database stand for two API processes; the key is revoked through the first."""
    ttl_s = 2.0  # long enough that a loaded machine still makes the in-between checks within it
    first, second = _app(settings, api_key_cache_ttl_s=ttl_s), _app(settings, api_key_cache_ttl_s=ttl_s)
    key = new_key(client)
    with (
        TestClient(first, headers=bearer(ADMIN_KEY)) as admin,
        TestClient(first, headers=bearer(key["token"])) as via_first,
        TestClient(second, headers=bearer(key["token"])) as via_second,
    ):
        assert via_first.get("/v1/cameras").status_code == 200
        assert via_second.get("/v1/cameras").status_code == 200  # now cached by the second process
        cached_at = time.monotonic()
        assert admin.delete(f"/v1/keys/{key['id']}").status_code == 200
        assert via_first.get("/v1/cameras").status_code == 401  # the revoking process forgets it at once
        assert via_second.get("/v1/cameras").status_code == 200  # the other trusts its cache until the TTL
        assert time.monotonic() < cached_at + ttl_s
        time.sleep(max(0.0, cached_at + ttl_s - time.monotonic()) + 0.05)
        _assert_unauthenticated(via_second.get("/v1/cameras"), "revoked", token_given=True)


def test_revocation_by_another_process_is_seen_after_the_ttl_not_before(
    settings: Settings, client: TestClient, app: FastAPI
) -> None:
    ttl_s = 1.5
    api = _app(settings, api_key_cache_ttl_s=ttl_s)
    key = new_key(client)
    with TestClient(api, headers=bearer(key["token"])) as holder:
        assert holder.get("/v1/cameras").status_code == 200
        verified_at = time.monotonic()
        with Session(app.state.engine) as session:  # `posemetry keys revoke`, say
            stored_keys.revoke_key(session, key["id"])
            session.commit()
        for _ in range(3):
            assert holder.get("/v1/cameras").status_code == 200
        assert time.monotonic() < verified_at + ttl_s  # the 200s above were within the TTL
        time.sleep(max(0.0, verified_at + ttl_s - time.monotonic()) + 0.05)
        _assert_unauthenticated(holder.get("/v1/cameras"), "revoked", token_given=True)


def test_a_configured_admin_key_needs_no_database(client: TestClient, key_queries: KeyQueries) -> None:
    for _ in range(3):
        assert client.get("/v1/keys/current").json()["name"] == "POSEMETRY_ADMIN_KEY"
    assert key_queries.seen == []


def test_without_an_admin_setting_only_stored_keys_get_in(settings: Settings, app: FastAPI, client: TestClient) -> None:
    key = new_key(client, name="stored admin", admin=True)
    plain = _app(settings, admin_key=None)
    with TestClient(plain, headers=bearer(ADMIN_KEY)) as old_admin:
        _assert_unauthenticated(old_admin.get("/v1/cameras"), "not a posemetry api key", token_given=True)
    with TestClient(plain, headers=bearer(key["token"])) as admin:
        assert admin.get("/v1/keys").status_code == 200


def test_a_camera_created_by_the_admin_is_usable_by_a_key_made_later(
    client: TestClient, client_for: Callable[[str], TestClient], camera: str
) -> None:
    scoped = client_for(new_key(client, cameras=[camera])["token"])
    assert scoped.get(f"/v1/cameras/{camera}/calibration").json()["status"] == "uncalibrated"


def test_a_key_that_cannot_be_checked_is_a_503_not_a_500(settings: Settings, tmp_path: Path) -> None:
    """The database fails the look-up (here: it lacks the schema): the caller is told to retry, not let in."""
    broken = _app(settings, database_url=f"sqlite:///{tmp_path / 'unmigrated.sqlite3'}")
    with TestClient(broken, headers=bearer("pm_0123456789ab_" + "A" * 43)) as caller:
        assert_problem(caller.get("/v1/cameras"), 503, "cannot be checked")
    with TestClient(broken, headers=bearer(ADMIN_KEY)) as admin:  # the configured admin key needs no database
        assert admin.get("/v1/keys/current").status_code == 200
