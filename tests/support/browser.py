"""A real headless browser for the console's tests: Debian's chromium driven through its chromedriver by selenium.

Chromium is required only where POSEMETRY_TESTS_REQUIRE_BROWSER=1 (set by .ci/run, which installs it): there its
absence fails the tests; elsewhere they skip, saying what could not start.
"""

from __future__ import annotations

import base64
import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

REQUIRE_BROWSER_ENV = "POSEMETRY_TESTS_REQUIRE_BROWSER"
CHROMIUM = ("chromium", "chromium-browser", "google-chrome")
HINT = "apt-get install -y chromium chromium-driver (and pip install selenium, in the test extras)"


def _unavailable(problem: str) -> None:
    if os.environ.get(REQUIRE_BROWSER_ENV) == "1":
        pytest.fail(f"a browser is required ({REQUIRE_BROWSER_ENV}=1) but cannot start: {problem}")
    pytest.skip(f"no headless chromium here ({problem}); {HINT}")


def require_chromium() -> tuple[str, str]:
    """(chromium, chromedriver) paths, with selenium importable; else a skip (a failure where required)."""
    try:
        import selenium  # noqa: F401
    except ImportError as exc:
        _unavailable(f"selenium is not installed: {exc}")
    binary = next((path for name in CHROMIUM if (path := shutil.which(name))), None)
    driver_path = shutil.which("chromedriver")
    if binary is None or driver_path is None:
        _unavailable(f"chromium found at {binary}, chromedriver at {driver_path}")
    return binary, driver_path  # type: ignore[return-value]


@contextmanager
def chromium(width_px: int, height_px: int) -> Iterator[Any]:
    """A headless chromium window of this size (a selenium WebDriver), closed afterwards."""
    from selenium import webdriver
    from selenium.common.exceptions import WebDriverException
    from selenium.webdriver.chrome.service import Service

    binary, driver_path = require_chromium()
    options = webdriver.ChromeOptions()
    options.binary_location = binary
    for argument in (
        "--headless=new",
        "--no-sandbox",  # CI runs as root, where chromium's sandbox cannot start
        "--disable-dev-shm-usage",
        "--disable-gpu",
        f"--window-size={width_px},{height_px}",
        "--force-device-scale-factor=1",
    ):
        options.add_argument(argument)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    try:
        driver = webdriver.Chrome(options=options, service=Service(driver_path))
    except WebDriverException as exc:
        _unavailable(f"chromium did not start: {exc.msg}")
    try:
        # The viewport itself this size (a window's size includes what chromium keeps for its own frame), and on a
        # narrow one a phone's: its meta viewport honoured, scroll bars that overlay the page.
        metrics = {"width": width_px, "height": height_px, "deviceScaleFactor": 1, "mobile": width_px < 600}
        driver.execute_cdp_cmd("Emulation.setDeviceMetricsOverride", metrics)
        yield driver
    finally:
        driver.quit()


def save_full_page(driver: Any, path: Path) -> None:
    """A PNG of the whole page, below the fold too, at the viewport's width."""
    width, height = driver.execute_script(
        "return [document.documentElement.clientWidth, document.documentElement.scrollHeight]"
    )
    clip = {"x": 0, "y": 0, "width": width, "height": height, "scale": 1}
    capture = {"format": "png", "captureBeyondViewport": True, "clip": clip}
    shot = driver.execute_cdp_cmd("Page.captureScreenshot", capture)
    path.write_bytes(base64.b64decode(shot["data"]))
