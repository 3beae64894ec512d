"""The console's page over HTTP: public but empty of data, locked down by its headers, no inline script anywhere."""

from __future__ import annotations

import re
from html.parser import HTMLParser

from fastapi.testclient import TestClient

from service.console.routes import ASSETS
from tests.support.app import assert_problem


class _Tags(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict[str, str | None]]] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append((tag, dict(attrs)))


def test_the_page_needs_no_key_and_holds_no_data(anonymous: TestClient, client: TestClient, camera: str) -> None:
    page = anonymous.get("/console")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert camera not in page.text  # the cameras come from the API, with a key, never with the page
    assert "set-cookie" not in page.headers


def test_a_strict_policy_and_no_inline_script(anonymous: TestClient) -> None:
    page = anonymous.get("/console")
    policy = dict(part.strip().split(" ", 1) for part in page.headers["content-security-policy"].split(";"))
    assert policy["default-src"] == "'none'" and policy["script-src"] == "'self'" and policy["style-src"] == "'self'"
    assert policy["connect-src"] == "'self'" and policy["frame-ancestors"] == "'none'"
    assert policy["form-action"] == "'none'" and "unsafe" not in page.headers["content-security-policy"]
    assert page.headers["x-content-type-options"] == "nosniff" and page.headers["referrer-policy"] == "no-referrer"
    tags = _Tags()
    tags.feed(page.text)
    scripts = [attrs for tag, attrs in tags.tags if tag == "script"]
    assert scripts == [{"src": "/console/console.js", "defer": None}]
    assert not [attrs for _, attrs in tags.tags if any(name.startswith("on") for name in attrs)]  # no handlers
    assert not [attrs for tag, attrs in tags.tags if tag == "style" or "style" in attrs]
    # Every file the page names is served, with its type.
    for name in re.findall(r'(?:src|href)="/console/([^"]+)"', page.text):
        asset = anonymous.get(f"/console/{name}")
        assert asset.status_code == 200 and asset.headers["content-type"].startswith(ASSETS[name].split(";")[0])


def test_the_script_keeps_the_key_out_of_urls_and_cookies(anonymous: TestClient) -> None:
    script = anonymous.get("/console/console.js").text
    assert "sessionStorage" in script and "Authorization: `Bearer ${key}`" in script
    assert "localStorage" not in script and "document.cookie" not in script and "innerHTML" not in script


def test_only_the_console_files_are_served(anonymous: TestClient) -> None:
    for name in ("page.py", "..%2Froutes.py", "static", "console.jsx"):
        assert_problem(anonymous.get(f"/console/{name}"), 404)
