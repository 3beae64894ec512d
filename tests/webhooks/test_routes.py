"""Webhook subscriptions over HTTP: CRUD, validation, the SSRF policy when subscribing, secret rotation, the
delivery log and redelivery, and the calibration-status events the API itself raises (reset, new image size)."""

from __future__ import annotations

import base64
import uuid
from pathlib import Path
from typing import Any

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from service.app import create_app
from service.calibration.repository import add_calibration
from service.settings import Settings
from service.store import WebhookEvent
from service.webhooks import repository as store
from service.webhooks.signing import generate_secret
from tests.support.app import ADMIN_KEY, HEIGHT_PX, MIN_PEOPLE, WIDTH_PX, assert_problem, bearer, solved
from tests.support.dispatch import RecordingDispatcher

LOOPBACK_HOOK = "http://127.0.0.1:9/hook"
PUBLIC_HOOK = "https://93.184.216.34/hook"


@pytest.fixture
def settings(migrated_url: str, tmp_path: Path) -> Settings:
    """The API's test settings, with loopback opened to webhooks (the receivers of these tests are local)."""
    return Settings(
        database_url=migrated_url,
        data_dir=tmp_path,
        calibration_min_people=MIN_PEOPLE,
        webhook_allowed_networks=["127.0.0.0/8"],
        admin_key=ADMIN_KEY,
    )


def subscribe(client: TestClient, **fields: Any) -> dict[str, Any]:
    response = client.post("/v1/webhooks", json={"url": LOOPBACK_HOOK, **fields})
    assert response.status_code == 201, response.text
    return response.json()


def _event(app: FastAPI, subscription_ids: list[str], camera_id: str = "cam-1") -> list[uuid.UUID]:
    """Raise an event straight in the store (as a worker would) for these subscriptions."""
    with app.state.session_factory() as session:
        subscriptions = [store.get_subscription(session, uuid.UUID(s)) for s in subscription_ids]
        body = '{"type":"calibration.updated","timestamp":"2026-01-01T00:00:00Z","data":{"camera_id":"cam-1"}}'
        ids = store.raise_event(
            session, event_type="calibration.updated", camera_id=camera_id, body=body, subscriptions=subscriptions
        )
        session.commit()
    return ids


# --------------------------------------------------------------------------------------------------- CRUD


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_create_read_list_delete(client: TestClient) -> None:
    created = subscribe(client, camera_ids=["lobby", "door-2"], description="ops pager")
    assert created["secret"].startswith("whsec_") and len(base64.b64decode(created["secret"][6:])) == 32
    assert created["event_types"] == ["violation.detected", "calibration.updated", "calibration.status_changed"]
    assert created["camera_ids"] == ["lobby", "door-2"] and created["enabled"] is True
    url = created["links"]["self"]
    assert url == f"/v1/webhooks/{created['id']}"
    got = client.get(url).json()
    assert "secret" not in got  # shown once, at creation
    assert got == {k: v for k, v in created.items() if k != "secret"}
    second = subscribe(client, event_types=["violation.detected"])
    assert second["camera_ids"] is None  # every camera
    page = client.get("/v1/webhooks", params={"limit": 1}).json()
    assert [s["id"] for s in page["items"]] == [created["id"]] and page["next_after"] == created["id"]
    rest = client.get("/v1/webhooks", params={"limit": 1, "after": page["next_after"]}).json()
    assert [s["id"] for s in rest["items"]] == [second["id"]]
    assert client.delete(url).status_code == 204
    assert_problem(client.get(url), 404, "no webhook subscription")
    assert_problem(client.delete(url), 404)
    assert [s["id"] for s in client.get("/v1/webhooks").json()["items"]] == [second["id"]]


def test_a_client_secret_is_kept(client: TestClient) -> None:
    secret = generate_secret()
    assert subscribe(client, secret=secret)["secret"] == secret


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"url": LOOPBACK_HOOK, "event_types": ["violation.started"]}, "event_types"),
        ({"url": LOOPBACK_HOOK, "event_types": []}, "event_types"),
        ({"url": LOOPBACK_HOOK, "camera_ids": []}, "camera_ids"),
        ({"url": LOOPBACK_HOOK, "camera_ids": ["../etc"]}, "camera_ids"),
        ({"url": LOOPBACK_HOOK, "secret": "hunter2"}, "secret"),
        ({"url": LOOPBACK_HOOK, "secret": "whsec_" + base64.b64encode(b"too short").decode()}, "secret"),
        ({"url": LOOPBACK_HOOK, "description": "x" * 501}, "description"),
        ({"url": LOOPBACK_HOOK, "colour": "red"}, "colour"),
        ({"url": "http://127.0.0.1/" + "a" * 2048}, "url"),
        ({}, "url"),
    ],
)
def test_bad_subscriptions_are_422_with_the_field(client: TestClient, body: dict[str, Any], field: str) -> None:
    problem = assert_problem(client.post("/v1/webhooks", json=body), 422)
    assert any(field in error["field"] for error in problem["errors"]), problem


def test_non_json_and_bad_ids_are_4xx(client: TestClient) -> None:
    assert_problem(client.post("/v1/webhooks", content=b"url=x", headers={"content-type": "text/plain"}), 415)
    assert_problem(client.post("/v1/webhooks", content=b"{", headers={"content-type": "application/json"}), 400)
    assert_problem(client.get("/v1/webhooks/not-a-uuid"), 422)
    assert_problem(client.get(f"/v1/webhooks/{uuid.uuid4()}"), 404)
    assert_problem(client.get("/v1/webhooks", params={"after": str(uuid.uuid4())}), 400, "after")


@pytest.mark.parametrize(
    ("url", "fragment"),
    [
        ("http://127.0.0.1:8000/hook", "loopback"),
        ("http://localhost/hook", "loopback"),
        ("http://[::1]/hook", "loopback"),
        ("http://[::ffff:127.0.0.1]/hook", "loopback"),
        ("http://10.0.0.7/hook", "private"),
        ("http://192.168.1.20/hook", "private"),
        ("http://[fd00::7]/hook", "private"),
        ("http://169.254.169.254/latest/meta-data/", "link-local"),
        ("http://[fe80::1]/hook", "link-local"),
        ("http://239.1.1.1/hook", "multicast"),
        ("http://240.0.0.1/hook", "reserved"),
        ("http://0.0.0.0/hook", "unspecified"),
        ("http://[::]/hook", "unspecified"),
        ("ftp://93.184.216.34/hook", "scheme"),
        ("https://me:pw@93.184.216.34/hook", "credentials"),
        ("https://nowhere.invalid/hook", "does not resolve"),
    ],
)
def test_subscribing_to_a_refused_address_is_422(migrated_url: str, tmp_path: Path, url: str, fragment: str) -> None:
    strict = create_app(
        Settings(database_url=migrated_url, data_dir=tmp_path, admin_key=ADMIN_KEY), dispatcher=RecordingDispatcher()
    )
    with TestClient(strict, headers=bearer(ADMIN_KEY)) as client:
        problem = assert_problem(client.post("/v1/webhooks", json={"url": url}), 422, fragment)
        assert problem["type"].endswith("/webhook-url-refused") and problem["errors"][0]["field"] == "body.url"
        assert client.get("/v1/webhooks").json()["items"] == []
        assert client.post("/v1/webhooks", json={"url": PUBLIC_HOOK}).status_code == 201


def test_the_allow_setting_opens_its_ranges_only(client: TestClient) -> None:
    subscribe(client)  # 127.0.0.1 is in the test settings' allow-list
    assert_problem(client.post("/v1/webhooks", json={"url": "http://10.0.0.7/hook"}), 422, "private")
    assert_problem(client.post("/v1/webhooks", json={"url": "http://[::1]/hook"}), 422, "loopback")


# --------------------------------------------------------------------------------------------------- changes


def test_patch_changes_only_what_is_given(client: TestClient) -> None:
    created = subscribe(client, camera_ids=["lobby"], description="first")
    url = created["links"]["self"]
    changed = client.patch(url, json={"event_types": ["violation.detected"], "description": None}).json()
    assert changed["event_types"] == ["violation.detected"] and changed["description"] is None
    assert changed["camera_ids"] == ["lobby"] and changed["url"] == LOOPBACK_HOOK
    assert client.patch(url, json={"camera_ids": None}).json()["camera_ids"] is None
    assert_problem(client.patch(url, json={"url": "http://10.1.1.1/x"}), 422, "private")
    assert_problem(client.patch(url, json={"url": None}), 422)
    assert_problem(client.patch(url, json={"enabled": None}), 422)
    assert_problem(client.patch(url, json={"secret": generate_secret()}), 422)  # rotation has its own route
    assert client.patch(url, json={"url": "http://127.0.0.2:9/other"}).json()["url"] == "http://127.0.0.2:9/other"
    assert_problem(client.patch(f"/v1/webhooks/{uuid.uuid4()}", json={"enabled": False}), 404)


def test_rotating_the_secret_keeps_the_old_one_signing_for_a_while(client: TestClient, app: FastAPI) -> None:
    created = subscribe(client)
    url = created["links"]["self"]
    rotated = client.post(f"{url}/secret", json={}).json()
    assert rotated["secret"].startswith("whsec_") and rotated["secret"] != created["secret"]
    assert rotated["previous_secret_valid_until"] is not None
    [delivery] = _event(app, [created["id"]])
    with app.state.session_factory() as session:
        claim = store.claim_attempt(session, delivery, 1, lease_s=60)
        session.rollback()
    assert not isinstance(claim, str)
    assert claim.secrets == (rotated["secret"], created["secret"])
    immediate = client.post(f"{url}/secret", json={"secret": generate_secret(), "previous_valid_for_s": 0}).json()
    assert immediate["previous_secret_valid_until"] is None
    with app.state.session_factory() as session:
        claim = store.claim_attempt(session, delivery, 1, lease_s=60)
    assert not isinstance(claim, str) and claim.secrets == (immediate["secret"],)
    assert_problem(client.post(f"{url}/secret", json={"secret": "whsec_!!"}), 422)


# --------------------------------------------------------------------------------------------------- the log


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_delivery_log_and_redelivery(client: TestClient, app: FastAPI, dispatcher: RecordingDispatcher) -> None:
    created = subscribe(client)
    other = subscribe(client)
    first = _event(app, [created["id"], other["id"]])
    second = _event(app, [created["id"]])
    log_url = f"/v1/webhooks/{created['id']}/deliveries"
    log = client.get(log_url).json()
    assert [d["id"] for d in log["items"]] == [str(second[0]), str(first[0])]  # newest first
    entry = log["items"][1]
    assert entry["status"] == "pending" and entry["attempts"] == 0 and entry["event_type"] == "calibration.updated"
    with app.state.session_factory() as session:
        event = session.get(WebhookEvent, uuid.UUID(entry["webhook_id"]))
        assert event is not None
    assert client.get(log_url, params={"limit": 1}).json()["next_before"] == str(second[0])
    assert [d["id"] for d in client.get(log_url, params={"limit": 1, "before": str(second[0])}).json()["items"]] == [
        str(first[0])
    ]
    assert client.get(log_url, params={"status": "delivered"}).json()["items"] == []
    detail = client.get(entry["url"]).json()
    assert detail["attempt_log"] == [] and detail["payload"]["data"]["camera_id"] == "cam-1"
    # Another subscription's delivery is not found under this one.
    other_delivery = client.get(f"/v1/webhooks/{other['id']}/deliveries").json()["items"][0]
    assert_problem(client.get(f"{log_url}/{other_delivery['id']}"), 404)

    again = client.post(f"{entry['url']}/redeliver")
    assert again.status_code == 202, again.text
    body = again.json()
    assert body["redelivery_of"] == entry["id"] and body["webhook_id"] == entry["webhook_id"]
    assert body["status"] == "pending" and again.headers["location"] == body["url"]
    assert dispatcher.deliveries[-1] == (uuid.UUID(body["id"]), 1, None)
    assert_problem(client.post(f"{log_url}/{uuid.uuid4()}/redeliver"), 404)

    client.patch(created["links"]["self"], json={"enabled": False})
    assert_problem(client.post(f"{entry['url']}/redeliver"), 409, "disabled")
    queued = len(dispatcher.deliveries)
    client.patch(created["links"]["self"], json={"enabled": True})
    # Re-enabling sends what waited: the three pending deliveries of this subscription.
    assert len(dispatcher.deliveries) == queued + 3
    dispatcher.fail = True
    down = client.post(f"{entry['url']}/redeliver")
    assert_problem(down, 503, "stored")
    assert len(client.get(log_url).json()["items"]) == 4  # stored all the same, for the workers to pick up


# --------------------------------------------------------------------------------------------------- API events


def _calibrate(app: FastAPI, camera: str) -> None:
    with app.state.session_factory() as session:
        add_calibration(session, camera, solved(10), make_current=True)
        session.commit()


def test_reset_raises_status_changed(
    client: TestClient, app: FastAPI, camera: str, dispatcher: RecordingDispatcher
) -> None:
    everything = subscribe(client)
    other_camera = subscribe(client, camera_ids=["elsewhere"])
    only_updates = subscribe(client, event_types=["calibration.updated"])
    client.delete(f"/v1/cameras/{camera}/calibration")
    assert dispatcher.deliveries == []  # it was not calibrated: nothing changed
    _calibrate(app, camera)
    client.delete(f"/v1/cameras/{camera}/calibration")
    [(delivery_id, attempt, at)] = dispatcher.deliveries
    assert attempt == 1 and at is None
    detail = client.get(f"/v1/webhooks/{everything['id']}/deliveries/{delivery_id}").json()
    payload = detail["payload"]
    assert payload["type"] == "calibration.status_changed"
    assert payload["data"]["status"] == "uncalibrated" and payload["data"]["previous_status"] == "calibrated"
    assert payload["data"]["reason"] == "reset" and payload["data"]["fx_px"] is None
    for quiet in (other_camera, only_updates):
        assert client.get(f"/v1/webhooks/{quiet['id']}/deliveries").json()["items"] == []


def test_a_new_image_size_raises_status_changed(
    client: TestClient, app: FastAPI, camera: str, dispatcher: RecordingDispatcher
) -> None:
    subscription = subscribe(client, event_types=["calibration.status_changed"])
    _calibrate(app, camera)
    same = client.put(f"/v1/cameras/{camera}", json={"image_width_px": WIDTH_PX, "image_height_px": HEIGHT_PX})
    assert same.status_code == 200 and dispatcher.deliveries == []
    client.put(f"/v1/cameras/{camera}", json={"image_width_px": 1280, "image_height_px": 720})
    [item] = client.get(f"/v1/webhooks/{subscription['id']}/deliveries").json()["items"]
    payload = client.get(item["url"]).json()["payload"]
    assert payload["data"]["reason"] == "image size changed" and payload["data"]["status"] == "uncalibrated"
    assert [d[0] for d in dispatcher.deliveries] == [uuid.UUID(item["id"])]
