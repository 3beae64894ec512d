"""Curated hostile requests: what attackers, broken clients and bad proxies send, which random generation from the
schema rarely reaches (compressed image bombs, lying image headers, ten thousand people, JSON that is not quite
JSON, traversal and unicode in ids, outsized headers, webhook addresses spelled to slip past an SSRF filter).

Each case states the statuses it may get; every 4xx must be problem+json, and no case may get a 5xx. The cases go
to the real app in process over a copy of the fuzz world (tests/fuzz/world.py) and are counted in the closing table.
"""

from __future__ import annotations

import json
import shutil
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.http.problems import PROBLEM_MEDIA_TYPE
from tests.fuzz.tally import TALLY
from tests.fuzz.world import CAMERA, HEIGHT_PX, WIDTH_PX, WorldTemplate, settings_for
from tests.support.app import ADMIN_KEY, bearer, coco_person
from tests.support.dispatch import RecordingDispatcher

FRAMES = f"/v1/cameras/{CAMERA}/frames"
KEYPOINTS = f"/v1/cameras/{CAMERA}/keypoints"
ACCEPTED = frozenset({200, 201, 202})


@dataclass(frozen=True)
class Hostile:
    name: str
    method: str
    path: str
    expect: frozenset[int]
    content: bytes | None = None
    headers: dict[str, str | bytes] = field(default_factory=dict)


def _encoded(ext: str, image: np.ndarray, params: list[int] | None = None) -> bytes:
    ok, data = cv2.imencode(ext, image, params or [])
    assert ok
    return data.tobytes()


def _noise(channels: int, dtype: type = np.uint8) -> np.ndarray:
    high = 255 if dtype is np.uint8 else 65535
    shape = (HEIGHT_PX, WIDTH_PX) if channels == 1 else (HEIGHT_PX, WIDTH_PX, channels)
    return np.random.default_rng(1).integers(0, high, shape, dtype=dtype)


def _png(width: int, height: int, rows: Iterator[bytes]) -> bytes:
    """A genuine PNG (8-bit grey) of any size whose pixel data compresses to almost nothing: a real bomb, not a
    header that lies."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    compressor = zlib.compressobj(9)
    pixels = b"".join(compressor.compress(row) for row in rows) + compressor.flush()
    header = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", pixels) + chunk(b"IEND", b"")


def png_bomb(width: int, height: int) -> bytes:
    row = b"\x00" * (width + 1)  # filter byte + black pixels
    return _png(width, height, (row for _ in range(height)))


def jpeg_claiming(width: int, height: int, jpeg: bytes) -> bytes:
    """A JPEG whose frame header (SOF0) claims another size than its data holds."""
    at = jpeg.index(b"\xff\xc0")
    return jpeg[: at + 5] + struct.pack(">HH", height, width) + jpeg[at + 9 :]


def image_cases() -> list[Hostile]:
    jpeg = _encoded(".jpg", _noise(3))
    png = _encoded(".png", _noise(3))
    as_jpeg, as_png = {"Content-Type": "image/jpeg"}, {"Content-Type": "image/png"}
    refused_big = frozenset({413})
    return [
        Hostile("PNG bomb 8000x6000 (48 Mpx in ~50 KB)", "POST", FRAMES, refused_big, png_bomb(8000, 6000), as_png),
        Hostile("PNG bomb 6000x6000 (under the pixel limit, wrong size)", "POST", FRAMES, frozenset({422}),
                png_bomb(6000, 6000), as_png),
        Hostile("JPEG header claiming 65000x65000", "POST", FRAMES, refused_big, jpeg_claiming(65000, 65000, jpeg),
                as_jpeg),
        Hostile("JPEG header claiming the camera's size x2", "POST", FRAMES, frozenset({422}),
                jpeg_claiming(2 * WIDTH_PX, 2 * HEIGHT_PX, jpeg), as_jpeg),
        Hostile("JPEG header claiming 0x0", "POST", FRAMES, frozenset({422}), jpeg_claiming(0, 0, jpeg), as_jpeg),
        Hostile("truncated JPEG (half)", "POST", FRAMES, frozenset({422}), jpeg[: len(jpeg) // 2], as_jpeg),
        Hostile("truncated JPEG (SOI only)", "POST", FRAMES, frozenset({415, 422}), jpeg[:2], as_jpeg),
        Hostile("truncated PNG (no IEND)", "POST", FRAMES, frozenset({422}), png[:-12], as_png),
        Hostile("PNG signature only", "POST", FRAMES, frozenset({415, 422}), png[:8], as_png),
        Hostile("empty body as image/jpeg", "POST", FRAMES, frozenset({422}), b"", as_jpeg),
        Hostile("GIF labelled image/jpeg", "POST", FRAMES, frozenset({415}), b"GIF89a" + b"\x00" * 64, as_jpeg),
        Hostile("image/gif", "POST", FRAMES, frozenset({415}), b"GIF89a" + b"\x00" * 64, {"Content-Type": "image/gif"}),
        Hostile("application/octet-stream JPEG", "POST", FRAMES, frozenset({415}), jpeg,
                {"Content-Type": "application/octet-stream"}),
        Hostile("no Content-Type", "POST", FRAMES, frozenset({415}), jpeg),
        Hostile("multipart without boundary", "POST", FRAMES, frozenset({400, 422}), jpeg,
                {"Content-Type": "multipart/form-data"}),
        Hostile("multipart, garbage after boundary", "POST", FRAMES, frozenset({400, 422}),
                b"--x\r\nContent-Disposition: form-data; name=\"image\"\r\n\r\n" + jpeg[:100],
                {"Content-Type": "multipart/form-data; boundary=x"}),
        Hostile("grey JPEG of the camera's size", "POST", FRAMES, ACCEPTED, _encoded(".jpg", _noise(1)), as_jpeg),
        Hostile("progressive JPEG", "POST", FRAMES, ACCEPTED,
                _encoded(".jpg", _noise(3), [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]), as_jpeg),
        Hostile("RGBA PNG", "POST", FRAMES, ACCEPTED, _encoded(".png", _noise(4)), as_png),
        Hostile("16-bit PNG", "POST", FRAMES, ACCEPTED, _encoded(".png", _noise(3, np.uint16)), as_png),
    ]  # fmt: skip


def _frame(people: Any, **extra: Any) -> bytes:
    return json.dumps({"timestamp": "2026-01-01T12:00:00Z", "people": people, **extra}).encode()


def _with_number(literal: str) -> bytes:
    """A frame whose first shoulder x is the raw JSON text `literal` (NaN, 1e309, ...), which json.dumps cannot
    write."""
    return b'{"timestamp": "2026-01-01T12:00:00Z", "people": [{"shoulder": [%s, 100], "ankle": [300, 400]}]}' % (
        literal.encode()
    )


def keypoint_cases() -> list[Hostile]:
    as_json = {"Content-Type": "application/json"}
    person = {"shoulder": [300, 100], "ankle": [300, 400]}
    refused = frozenset({400, 422})
    cases = [
        Hostile("10 000 people in one frame", "POST", KEYPOINTS, frozenset({413}), _frame([person] * 10_000), as_json),
        Hostile("201 people (one over the limit)", "POST", KEYPOINTS, frozenset({413}), _frame([person] * 201),
                as_json),
        Hostile("200 people with full keypoints", "POST", KEYPOINTS, ACCEPTED,
                _frame([{"keypoints": coco_person((300, 100), (300, 400))}] * 200), as_json),
        Hostile("10 MB string", "POST", KEYPOINTS, frozenset({413}), _frame([], frame_id="a" * 10_000_000), as_json),
        Hostile("JSON nested 100 000 deep", "POST", KEYPOINTS, refused, b"[" * 100_000 + b"]" * 100_000, as_json),
        Hostile("invalid UTF-8 in a string", "POST", KEYPOINTS, refused,
                b'{"timestamp": "2026-01-01T12:00:00Z", "frame_id": "\xff\xfe", "people": []}', as_json),
        Hostile("UTF-16 JSON", "POST", KEYPOINTS, refused | {415}, _frame([]).decode().encode("utf-16"), as_json),
        Hostile("JSON with a byte-order mark", "POST", KEYPOINTS, refused, b"\xef\xbb\xbf" + _frame([]),
                as_json),
        Hostile("duplicate keys (the last, invalid, wins)", "POST", KEYPOINTS, refused,
                b'{"timestamp": "2026-01-01T12:00:00Z", "people": [], "people": [1]}', as_json),
        Hostile("a JSON array, not an object", "POST", KEYPOINTS, refused, b"[]", as_json),
        Hostile("a JSON string", "POST", KEYPOINTS, refused, b'"people"', as_json),
        Hostile("null", "POST", KEYPOINTS, refused, b"null", as_json),
        Hostile("trailing garbage", "POST", KEYPOINTS, refused, _frame([]) + b"}}", as_json),
        Hostile("text/plain JSON", "POST", KEYPOINTS, frozenset({415}), _frame([]), {"Content-Type": "text/plain"}),
        Hostile("application/xml", "POST", KEYPOINTS, frozenset({415}), b"<frame/>",
                {"Content-Type": "application/xml"}),
        Hostile("UTF-8 JSON declared UTF-16 (JSON is UTF-8)", "POST", KEYPOINTS, ACCEPTED, _frame([]),
                {"Content-Type": "application/json; charset=utf-16"}),
        Hostile("timestamp before year 1 in UTC", "POST", KEYPOINTS, refused,
                _frame([], timestamp="0001-01-01T00:00:00+01:00"), as_json),
        Hostile("timestamp after year 9999 in UTC", "POST", KEYPOINTS, refused,
                _frame([], timestamp="9999-12-31T23:59:59-01:00"), as_json),
        Hostile("timestamp 1e20 s", "POST", KEYPOINTS, refused, _frame([], timestamp=1e20), as_json),
        Hostile("timestamp true", "POST", KEYPOINTS, refused, _frame([], timestamp=True), as_json),
        Hostile("score 1.0000001", "POST", KEYPOINTS, refused,
                _frame([{"keypoints": [[300, 100, 1.0000001]] * 17}]), as_json),
        Hostile("coordinate true", "POST", KEYPOINTS, refused, _with_number("true"), as_json),
        Hostile("coordinate as a string", "POST", KEYPOINTS, refused, _with_number('"300"'), as_json),
        Hostile("RTL override in frame_id", "POST", KEYPOINTS, refused, _frame([], frame_id="a\u202egnp.exe"),
                as_json),
    ]  # fmt: skip
    for literal in ("NaN", "Infinity", "-Infinity", "1e309", "-1e309", "1e300", "123456789" * 50, "1e-400"):
        expect = ACCEPTED if literal == "1e-400" else refused  # 1e-400 is 0.0: a point on the image's left edge
        cases.append(Hostile(f"coordinate {literal[:20]}", "POST", KEYPOINTS, expect, _with_number(literal), as_json))
    return cases


def camera_id_cases() -> list[Hostile]:
    body = json.dumps({"image_width_px": WIDTH_PX, "image_height_px": HEIGHT_PX}).encode()
    ids = [
        "%CE%BA%CE%B1%CE%BC%CE%B5%CF%81%CE%B1",  # καμερα
        "..%2F..%2Fetc%2Fpasswd",
        "%2E%2E",
        "lobby-1%00",
        "lobby-1%0D%0AX-Injected:%201",
        "%F0%9F%93%B7",  # the camera emoji
        "a%E2%80%AEgnp",  # RTL override
        "a" * 5000,
        "%25",
        "lobby-1%2F..%2Flobby-1",
        "%C0%AE%C0%AE",  # overlong UTF-8 for ".."
        "%FF%FE",  # not UTF-8 at all
    ]
    cases = []
    for camera_id in ids:
        label = camera_id if len(camera_id) < 40 else f"{camera_id[:10]}... ({len(camera_id)} chars)"
        cases.append(Hostile(f"GET camera {label}", "GET", f"/v1/cameras/{camera_id}", frozenset({404, 422})))
        cases.append(
            Hostile(f"PUT camera {label}", "PUT", f"/v1/cameras/{camera_id}", frozenset({404, 422}), body,
                    {"Content-Type": "application/json"})
        )  # fmt: skip
    return cases


def header_cases() -> list[Hostile]:
    many = {f"x-filler-{i}": "y" * 100 for i in range(500)}
    return [
        Hostile("64 KB bearer token", "GET", "/v1/cameras", frozenset({431}),
                headers={"Authorization": "Bearer " + "A" * 65_536}),
        Hostile("bearer token in latin-1", "GET", "/v1/cameras", frozenset({401}),
                headers={"Authorization": b"Bearer pm_\xff\xfe"}),
        Hostile("Basic instead of Bearer", "GET", "/v1/cameras", frozenset({401}),
                headers={"Authorization": "Basic YWRtaW46YWRtaW4="}),
        Hostile("two Authorization schemes in one", "GET", "/v1/cameras", frozenset({401}),
                headers={"Authorization": f"Bearer {ADMIN_KEY} Bearer {ADMIN_KEY}"}),
        Hostile("10 KB X-Request-ID", "GET", "/v1/cameras", ACCEPTED, headers={"X-Request-ID": "r" * 10_240}),
        Hostile("X-Request-ID with markup", "GET", "/v1/cameras", ACCEPTED,
                headers={"X-Request-ID": "<script>alert(1)</script>"}),
        Hostile("500 filler headers (55 KB)", "GET", "/v1/cameras", frozenset({431}), headers=many),
        Hostile("100 filler headers (11 KB)", "GET", "/v1/cameras", ACCEPTED, headers=dict(list(many.items())[:100])),
        Hostile("Content-Length 0 with a JSON type", "POST", KEYPOINTS, frozenset({400, 422}), b"",
                {"Content-Type": "application/json"}),
    ]  # fmt: skip


WEBHOOK_URLS = [
    "http://0x7f000001/",
    "http://2130706433/",
    "http://0177.0.0.1/",
    "http://127.1/",
    "http://[::ffff:127.0.0.1]/",
    "http://[::1]:8080/",
    "http://[fe80::1%25eth0]/",
    "http://169.254.169.254/latest/meta-data/",
    "http://user:pass@127.0.0.1/",
    "http://example.invalid@127.0.0.1/",
    "http://localhost./",
    "http://LOCALHOST/",
    "http://%6c%6f%63%61%6c%68%6f%73%74/",
    "http://\u24db\u24de\u24d2\u24d0\u24db\u24d7\u24de\u24e2\u24e3/",  # ⓛⓞⓒⓐⓛⓗⓞⓢⓣ
    "http://10.0.0.1/",
    "http://[fc00::1]/",
    "http://0.0.0.0/",
    "http://127.0.0.1:6379/",
    "file:///etc/passwd",
    "gopher://127.0.0.1:6379/_FLUSHALL",
    "javascript:alert(1)",
    "http:///nohost",
    "http://a b/",
    "http://127.0.0.1\r\nX-Injected: 1/",
]


def webhook_cases() -> list[Hostile]:
    return [
        Hostile(f"webhook to {url!r}", "POST", "/v1/webhooks", frozenset({422}), json.dumps({"url": url}).encode(),
                {"Content-Type": "application/json"})
        for url in WEBHOOK_URLS
    ]  # fmt: skip


GROUPS = {
    "curated: images": image_cases,
    "curated: keypoint frames": keypoint_cases,
    "curated: camera ids": camera_id_cases,
    "curated: headers": header_cases,
    "curated: webhook URLs (no allow-list)": webhook_cases,
}


@pytest.fixture(scope="module")
def clients(world_template: WorldTemplate, tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, TestClient]]:
    """The fuzz world as configured (loopback webhooks allowed), and the same world with the default SSRF policy."""
    opened: dict[str, TestClient] = {}
    for name, allowed in (("world", None), ("default-policy", ())):
        database = tmp_path_factory.mktemp(f"curated-{name}") / "world.sqlite3"
        shutil.copyfile(world_template.database, database)
        settings = settings_for(database)
        if allowed is not None:
            settings = settings.model_copy(update={"webhook_allowed_networks": allowed})
        opened[name] = TestClient(create_app(settings, dispatcher=RecordingDispatcher())).__enter__()
    yield opened
    for client in opened.values():
        client.__exit__(None, None, None)


def _send(client: TestClient, case: Hostile) -> tuple[int, str, bytes]:
    headers = {**bearer(ADMIN_KEY), **case.headers}
    # The raw path goes out as written: percent-escapes and dots are not normalised away by the client.
    response = client.request(case.method, case.path, content=case.content, headers=headers)
    return response.status_code, response.headers.get("content-type", ""), response.content


@pytest.mark.parametrize("group", list(GROUPS))
def test_hostile_requests_get_clear_4xx(group: str, clients: dict[str, TestClient]) -> None:
    client = clients["default-policy" if "webhook" in group else "world"]
    wrong: list[str] = []
    for case in GROUPS[group]():
        try:
            status, content_type, body = _send(client, case)
        except Exception as exc:  # raised in the app instead of an answer: counted, and a failure
            TALLY.record(group, case.name, kinds=["curated"], status=None, exception=exc)
            TALLY.failed(group, case.name)
            wrong.append(f"{case.name}: raised {type(exc).__name__}: {exc}")
            continue
        TALLY.record(group, case.name, kinds=["curated"], status=status)
        problem = json.loads(body) if content_type.startswith(PROBLEM_MEDIA_TYPE) else None
        if status not in case.expect:
            detail = problem.get("detail") if problem else body[:200]
            wrong.append(f"{case.name}: {status} (expected {sorted(case.expect)}): {detail}")
        elif status >= 400 and not (problem and problem["status"] == status and problem["detail"]):
            wrong.append(f"{case.name}: {status} without a problem document ({content_type})")
        if wrong and wrong[-1].startswith(case.name):
            TALLY.failed(group, case.name)
    assert not wrong, "\n".join(wrong)


def test_request_ids_are_never_echoed_unchecked(clients: dict[str, TestClient]) -> None:
    for value in ("r" * 10_240, "<script>alert(1)</script>"):
        response = clients["world"].get("/v1/cameras", headers={**bearer(ADMIN_KEY), "X-Request-ID": value})
        assert response.headers["x-request-id"] != value and len(response.headers["x-request-id"]) <= 128


def test_traversal_ids_touch_nothing(clients: dict[str, TestClient]) -> None:
    """After every hostile camera id, the cameras are the world's two, unchanged."""
    client = clients["world"]
    for case in camera_id_cases():
        _send(client, case)
    listed = client.get("/v1/cameras", headers=bearer(ADMIN_KEY)).json()
    assert sorted(camera["id"] for camera in listed["items"]) == sorted({CAMERA, "yard-2"})


def test_bombs_are_refused_without_decoding(tmp_path: Path, clients: dict[str, TestClient]) -> None:
    """A 48-megapixel bomb is refused from its header: the answer comes before any decoder could allocate 48 MB."""
    bomb = png_bomb(8000, 6000)
    assert len(bomb) < 100_000
    status, _, body = _send(clients["world"], Hostile("bomb", "POST", FRAMES, frozenset(), bomb,
                                                        {"Content-Type": "image/png"}))  # fmt: skip
    assert status == 413 and b"8000x6000" in body
