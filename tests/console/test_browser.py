"""The operator console in a real headless chromium against a real `posemetry serve` holding real data.

A simulated camera streams frames until it is calibrated (several versions), a second camera waits for people, a
webhook subscription fails against a closed port. An operator types the key and sees the cameras, the calibration
history charts, the latest frame's top-down map, the violations and the heat map, and the failing deliveries; a
key limited to one camera sees only that one; a wrong key gets an error. The key never shows up in a URL or a
cookie. Screenshots are written to $POSEMETRY_CONSOLE_SCREENSHOTS (default: /tmp/posemetry-console).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bench.simulate import SceneConfig, draw_scene
from tests.support.app import coco_person
from tests.support.browser import chromium, require_chromium, save_full_page
from tests.support.serving import ADMIN_KEY, Served, clean_environment, free_port, serve
from tests.support.shared import TOWN_CENTRE, model_dir_path

FRAMES = 12
PEOPLE_PER_FRAME = 10
WAIT_S = 30


@dataclass(frozen=True)
class Console:
    app: Served
    scoped_key: str
    """A key limited to the camera `lobby`."""
    frame: dict[str, Any]
    """The body of a frame `street` was sent, to send again."""
    photo: bool
    """Whether `street`'s latest frame is a photo it kept (where the real frames and models are at hand)."""


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Console]:
    """The running service with its data."""
    require_chromium()  # before starting anything
    settings = {
        "calibration_min_people": "30",
        "calibration_growth_factor": "1.5",
        "webhook_max_attempts": "1",
        "webhook_allowed_networks": "127.0.0.0/8",
        "console_refresh_s": "2",
    }
    town_frames = sorted((TOWN_CENTRE / "frames").glob("*.jpg"))
    models = model_dir_path()
    image = town_frames[0] if town_frames and models.is_dir() else None
    if image is not None:
        settings["model_dir"] = str(models)
    with serve(tmp_path_factory.mktemp("console"), clean_environment(**settings)) as app:
        assert app.http("PUT", "/v1/cameras/lobby", {"image_width_px": 1280, "image_height_px": 720})[0] == 201
        # Nothing listens on a port just freed: every delivery to it fails at once (connection refused).
        hook = {"url": f"http://127.0.0.1:{free_port()}/hooks", "event_types": ["violation.detected"]}
        assert app.http("POST", "/v1/webhooks", hook)[0] == 201
        frame = _stream(app, "street")
        if image is not None:
            _post_image(app, "street", image)
        status, scoped = app.http("POST", "/v1/keys", {"name": "lobby screen", "cameras": ["lobby"]})
        assert status == 201, scoped
        yield Console(app, scoped["token"], frame, image is not None)


def _post_image(app: Served, camera_id: str, image: Path) -> None:
    """A real photo, newest of all, to a camera that keeps its images: its overlay is the latest frame's picture."""
    now = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    path = f"/v1/cameras/{camera_id}/frames?frame_id={camera_id}-photo&timestamp={now}"
    status, body, _ = app.raw("POST", path, image.read_bytes(), "image/jpeg")
    assert status == 202, body
    url = json.loads(body)["url"]
    app.wait_for(lambda: app.http("GET", url)[1]["status"] == "done", "the photo measured")


def _stream(app: Served, camera_id: str, frame_prefix: str | None = None, create: bool = True) -> dict[str, Any]:
    """Frames of a simulated surveillance camera over the last minutes, until they are all measured (`create`: the
    camera first); the last frame's body."""
    scene = draw_scene(SceneConfig.surveillance(n_people=FRAMES * PEOPLE_PER_FRAME), np.random.default_rng(5))
    size = {
        "image_width_px": scene.image_size[0],
        "image_height_px": scene.image_size[1],
        "person_height_m": 1.7,
        "keep_images": True,
    }
    if create:
        assert app.http("PUT", f"/v1/cameras/{camera_id}", size)[0] == 201
    now = datetime.now(UTC)
    urls = []
    for k in range(FRAMES):
        people = slice(k * PEOPLE_PER_FRAME, (k + 1) * PEOPLE_PER_FRAME)
        body = {
            "timestamp": (now - timedelta(minutes=2 * (FRAMES - k))).isoformat(),
            "frame_id": f"{frame_prefix or camera_id}-{k}",
            "people": [
                {"keypoints": coco_person(tuple(top), tuple(bottom))}
                for top, bottom in zip(scene.tops_px[people], scene.bottoms_px[people], strict=True)
            ],
        }
        status, accepted = app.http("POST", f"/v1/cameras/{camera_id}/keypoints", body)
        assert status == 202, accepted
        urls.append(accepted["url"])
        if k >= 3:  # paced like a camera, so the calibration is solved again as evidence grows
            app.wait_for(lambda url=accepted["url"]: app.http("GET", url)[1]["status"] == "done", f"frame {k}")
    app.wait_for(lambda: all(app.http("GET", url)[1]["status"] == "done" for url in urls), "every frame measured")

    def failed_deliveries() -> list[Any]:
        hooks = app.http("GET", "/v1/webhooks")[1]["items"]
        return app.http("GET", f"/v1/webhooks/{hooks[0]['id']}/deliveries?status=failed")[1]["items"]

    app.wait_for(lambda: len(failed_deliveries()) > 0, "a failed webhook delivery")
    return body


def _screenshots() -> Path:
    folder = Path(os.environ.get("POSEMETRY_CONSOLE_SCREENSHOTS") or "/tmp/posemetry-console")
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def _open(driver: Any, base: str, key: str) -> None:
    from selenium.webdriver.common.by import By

    driver.get(f"{base}/console")
    field = driver.find_element(By.ID, "key")
    assert field.get_attribute("type") == "password"
    field.send_keys(key)
    driver.find_element(By.CSS_SELECTOR, "#key-form button[type=submit]").click()


def _wait(driver: Any, script: str, what: str) -> Any:
    """Until the JavaScript expression `script` is truthy in the page; its value."""
    from selenium.common.exceptions import TimeoutException
    from selenium.webdriver.support.ui import WebDriverWait

    try:
        return WebDriverWait(driver, WAIT_S, poll_frequency=0.2).until(lambda d: d.execute_script(f"return {script}"))
    except TimeoutException:
        error = driver.execute_script("return document.getElementById('error').textContent")
        refreshed = driver.execute_script("return document.getElementById('refreshed').textContent")
        raise AssertionError(f"waited {WAIT_S} s for {what}; page error {error!r}, status {refreshed!r}") from None


def _picture_loaded(img_id: str) -> str:
    """A JavaScript expression: the picture's width once it is shown and decoded."""
    found = f"document.getElementById('{img_id}')"
    return f"(!{found}.hidden && {found}.complete && {found}.naturalWidth)"


def _assert_key_kept_privately(driver: Any, key: str) -> None:
    """In this tab's sessionStorage only: not in the address, no cookie, no request URL carried it."""
    assert key not in driver.current_url
    assert driver.get_cookies() == []
    assert driver.execute_script("return document.cookie") == ""
    assert driver.execute_script("return sessionStorage.getItem('posemetry.key')") == key
    assert driver.execute_script("return localStorage.length") == 0
    requested = driver.execute_script("return performance.getEntriesByType('resource').map(e => e.name)")
    assert requested and not any(key in url for url in requested), requested


def _assert_no_browser_errors(driver: Any) -> None:
    """No script error and no Content-Security-Policy violation in the browser's console."""
    problems = [entry for entry in driver.get_log("browser") if entry["level"] == "SEVERE"]
    assert problems == [], problems


def test_an_admin_sees_cameras_history_pictures_and_failing_webhooks(served: Console) -> None:
    app = served.app
    with chromium(1400, 900) as driver:
        _open(driver, app.base, ADMIN_KEY)
        _wait(driver, "document.querySelectorAll('#cameras tbody tr').length === 2", "both cameras listed")
        rows = driver.execute_script(
            "return [...document.querySelectorAll('#cameras tbody tr')].map(r => [...r.cells].map(c => c.textContent))"
        )
        by_camera = {row[0]: row for row in rows}
        assert by_camera["lobby"][1] == "uncalibrated" and by_camera["lobby"][3] == "30"
        street = by_camera["street"]
        assert street[1] == "calibrated" and street[2].split(" · ")[0] in ("good", "fair", "poor"), street
        assert street[4].endswith(" px") and street[5].endswith(" m")
        # `lobby` is first in id order and selected; picking `street` shows its history and pictures.
        driver.execute_script("document.querySelector('#cameras tr[data-camera=street] button').click()")
        _wait(driver, "document.getElementById('history-camera').textContent === 'street'", "street's history")
        charts = _wait(driver, "document.querySelectorAll('#history svg').length", "the history charts")
        assert charts == 4
        # Several solves as the evidence grew: each chart has its line through every version.
        points = driver.execute_script(
            "return [...document.querySelectorAll('#history svg')].map(s => s.querySelectorAll('circle').length)"
        )
        assert min(points) >= 3 and len(set(points)) == 1, points
        titles = driver.execute_script(
            "return [...document.querySelectorAll('#history .chart-title')].map(t => t.textContent)"
        )
        assert titles == ["focal length f", "tilt below horizon", "camera height", "evidence (people)"]
        assert driver.execute_script("return document.querySelectorAll('#history .band').length") == 3  # +-1 sigma
        width = _wait(driver, _picture_loaded("frame-picture"), "the latest frame's picture")
        caption = driver.execute_script("return document.getElementById('frame-caption').textContent")
        if served.photo:  # the photo, drawn over: as wide as the camera's frames
            assert width == 1920 and caption.endswith("· overlay"), caption
        else:
            assert width > 100 and "10 people" in caption and caption.endswith("· top-down map"), caption
        assert _wait(driver, _picture_loaded("heatmap"), "the heat map") == 640
        bars = driver.execute_script("return document.querySelectorAll('#violations rect.bar').length")
        assert bars in (24, 25)
        total = driver.execute_script("return document.getElementById('violations-total').textContent")
        assert total != "0 in all", total
        failing = _wait(driver, "document.querySelector('#webhooks tbody tr td:last-child').textContent", "webhooks")
        assert "failed" in failing and "/hooks" in driver.find_element("css selector", "#webhooks td.url").text
        _assert_key_kept_privately(driver, ADMIN_KEY)
        _assert_no_browser_errors(driver)
        driver.save_screenshot(str(_screenshots() / "console-desktop.png"))
        save_full_page(driver, _screenshots() / "console-desktop-full.png")

        # It refreshes itself: a new frame shows up without anyone touching the page.
        before = driver.execute_script("return document.getElementById('frame-caption').textContent")
        again = {**served.frame, "frame_id": "street-again", "timestamp": datetime.now(UTC).isoformat()}
        status, accepted = app.http("POST", "/v1/cameras/street/keypoints", again)
        assert status == 202, accepted
        _wait(driver, f"document.getElementById('frame-caption').textContent !== {before!r}", "the refreshed frame")
        caption = driver.execute_script("return document.getElementById('frame-caption').textContent")
        assert "10 people" in caption and caption.endswith("· top-down map"), caption  # keypoints: no photo
        _wait(driver, _picture_loaded("frame-picture"), "the new frame's top-down map")


def test_a_key_limited_to_one_camera_sees_only_it_in_a_narrow_window(served: Console) -> None:
    app, scoped_key = served.app, served.scoped_key
    with chromium(390, 844) as driver:
        _open(driver, app.base, scoped_key)
        _wait(driver, "document.querySelectorAll('#cameras tbody tr').length === 1", "the one camera")
        assert driver.execute_script("return document.querySelector('#cameras tbody tr').dataset.camera") == "lobby"
        assert "lobby" in driver.find_element("id", "who").text
        note = _wait(driver, "document.getElementById('webhooks-note').textContent", "the webhooks note")
        assert "admin" in note
        assert driver.execute_script("return document.getElementById('no-frame').hidden") is False
        # The page fits the phone's width: nothing scrolls sideways but inside its own card.
        assert driver.execute_script("return document.documentElement.scrollWidth") <= 390
        _assert_key_kept_privately(driver, scoped_key)
        _assert_no_browser_errors(driver)
        driver.save_screenshot(str(_screenshots() / "console-narrow.png"))
        save_full_page(driver, _screenshots() / "console-narrow-full.png")
        # The key is typed once: a reload in the same tab signs in again by itself; "Forget key" forgets it.
        driver.refresh()
        _wait(driver, "document.querySelectorAll('#cameras tbody tr').length === 1", "the camera after a reload")
        driver.find_element("id", "sign-out").click()
        assert driver.execute_script("return sessionStorage.length") == 0
        assert driver.find_element("id", "login").is_displayed()
        assert driver.execute_script("return document.querySelectorAll('#cameras tbody tr').length") == 0
        # The admin's full view on the phone: charts and pictures stacked, still no sideways scrolling.
        _open(driver, app.base, ADMIN_KEY)
        _wait(driver, "document.querySelectorAll('#cameras tbody tr').length === 2", "both cameras listed")
        driver.execute_script("document.querySelector('#cameras tr[data-camera=street] button').click()")
        _wait(driver, _picture_loaded("frame-picture") + " && " + _picture_loaded("heatmap"), "street's pictures")
        _wait(driver, "document.querySelectorAll('#history svg').length === 4", "street's history")
        assert driver.execute_script("return document.documentElement.scrollWidth") <= 390
        save_full_page(driver, _screenshots() / "console-narrow-admin-full.png")


def test_a_wrong_key_is_refused_with_a_message(served: Console) -> None:
    app = served.app
    wrong = "pm_0123456789ab_" + "A" * 43
    with chromium(1400, 900) as driver:
        _open(driver, app.base, wrong)
        message = _wait(driver, "document.getElementById('error').textContent", "the error message")
        assert "refused" in message and "unknown api key" in message.lower(), message
        assert not driver.find_element("id", "dashboard").is_displayed()
        assert driver.execute_script("return sessionStorage.length") == 0
        assert wrong not in driver.current_url and driver.get_cookies() == []
        driver.save_screenshot(str(_screenshots() / "console-wrong-key.png"))


def test_a_reset_camera_says_why_and_its_history_marks_the_new_epoch(served: Console) -> None:
    """Runs last: it resets `street` and calibrates it again from the same people, in epoch 2."""
    app = served.app
    assert app.http("DELETE", "/v1/cameras/street/calibration")[0] in (200, 202, 204)
    with chromium(1400, 900) as driver:
        _open(driver, app.base, ADMIN_KEY)
        status = "document.querySelector('#cameras tr[data-camera=street] td:nth-child(2)')"
        text = _wait(driver, f"{status} && {status}.textContent", "street's status")
        assert text == "uncalibrated: calibration reset · epoch 2", text
        _stream(app, "street", frame_prefix="street-epoch2", create=False)
        _wait(driver, f"{status}.textContent.startsWith('calibrated · epoch 2')", "street calibrated again")
        driver.execute_script("document.querySelector('#cameras tr[data-camera=street] button').click()")
        marks = _wait(driver, "document.querySelectorAll('#history line.epoch').length", "the epoch marks")
        assert marks == 4  # one per chart
        texts = driver.execute_script("return [...document.querySelectorAll('#history text')].map(t => t.textContent)")
        labels = [text for text in texts if text.startswith("epoch")]
        assert labels == ["epoch 2"] * 4
        # Each epoch its own line and 1-sigma band: the solves before the reset are not joined to those after.
        assert driver.execute_script("return document.querySelectorAll('#history polyline').length") == 8
        assert driver.execute_script("return document.querySelectorAll('#history .band').length") == 6
        _assert_no_browser_errors(driver)
        driver.save_screenshot(str(_screenshots() / "console-epochs.png"))
