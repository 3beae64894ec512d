"""Hostile input against `posemetry serve` itself: what only a real server and real workers can show.

- Odd but valid images (grey, 16-bit, RGBA, progressive) of a real street go through the real pose workers: each
  is measured, none fails, and no worker process dies or is restarted.
- Abuse below HTTP's application layer (oversized header blocks and request lines, raw `..` in the request
  target, a body shorter than its Content-Length) is answered by the server with a 4xx or a closed connection,
  and the server goes on answering.
"""

from __future__ import annotations

import json
import socket
from collections.abc import Iterator

import cv2
import numpy as np
import psutil
import pytest

from tests.fuzz.tally import TALLY
from tests.support.serving import Served, clean_environment, serve
from tests.support.shared import TOWN_CENTRE, model_dir_path, require_dir

CAMERA = "street"
CATEGORY = "curated: served (real uvicorn and workers)"


def _odd_versions(frame: np.ndarray) -> dict[str, tuple[bytes, str]]:
    """The same street in encodings a camera system might send."""
    grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    rgba = cv2.cvtColor(frame, cv2.COLOR_BGR2BGRA)
    deep = frame.astype(np.uint16) * 257

    def encode(ext: str, image: np.ndarray, params: list[int] | None = None) -> bytes:
        ok, data = cv2.imencode(ext, image, params or [])
        assert ok
        return data.tobytes()

    return {
        "grey JPEG": (encode(".jpg", grey), "image/jpeg"),
        "progressive JPEG": (encode(".jpg", frame, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1]), "image/jpeg"),
        "RGBA PNG": (encode(".png", rgba, [cv2.IMWRITE_PNG_COMPRESSION, 1]), "image/png"),
        "16-bit PNG": (encode(".png", deep, [cv2.IMWRITE_PNG_COMPRESSION, 1]), "image/png"),
    }


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    env = clean_environment(model_dir=str(require_dir(model_dir_path(), "pose model")))
    with serve(tmp_path_factory.mktemp("served-hostile"), env) as app:
        status, _ = app.http("PUT", f"/v1/cameras/{CAMERA}", {"image_width_px": 1920, "image_height_px": 1080})
        assert status == 201
        yield app


def _processes(app: Served) -> set[int]:
    return {child.pid for child in psutil.Process(app.process.pid).children(recursive=False)}


def test_odd_images_go_through_the_real_pose_workers(served: Served) -> None:
    street = cv2.imread(str(require_dir(TOWN_CENTRE, "Town Centre data") / "frames" / "clip_000000.jpg"))
    before = _processes(served)
    urls = {}
    for name, (data, content_type) in _odd_versions(street).items():
        status, content, _ = served.raw("POST", f"/v1/cameras/{CAMERA}/frames", data, content_type)
        TALLY.record(CATEGORY, f"image: {name}", kinds=["curated"], status=status)
        assert status == 202, (name, content)
        urls[name] = json.loads(content)["url"]

    def frame(name: str) -> dict:
        return served.http("GET", urls[name])[1]

    served.wait_for(lambda: all(frame(name)["status"] != "detecting" for name in urls), "pose on every image", 180)
    for name in urls:
        found = frame(name)
        assert found["status"] != "failed", (name, found.get("error"))
        assert found["people"] >= 8, (name, found["people"])  # 13-17 pedestrians in this frame, in every encoding
    assert _processes(served) == before, "a worker died or was restarted"


def _exchange(served: Served, request: bytes) -> bytes:
    """Send raw bytes and return what comes back until the server closes or stops answering."""
    host, port = served.base.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=10) as sock:
        try:
            sock.sendall(request)
            sock.shutdown(socket.SHUT_WR)
        except OSError:  # the server may close while a huge request is still being written
            pass
        chunks = []
        try:
            while chunk := sock.recv(65536):
                chunks.append(chunk)
        except OSError:
            pass
    return b"".join(chunks)


def _status(answer: bytes) -> int | None:
    if not answer.startswith(b"HTTP/1.1 "):
        return None  # closed without an answer
    return int(answer[9:12])


PROTOCOL_CASES = {
    "100 KB header": b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Big: " + b"a" * 100_000 + b"\r\n\r\n",
    "5000 headers": b"GET /healthz HTTP/1.1\r\nHost: x\r\n"
    + b"".join(b"X-%d: y\r\n" % i for i in range(5000))
    + b"\r\n",
    "100 KB request target": b"GET /v1/cameras/" + b"a" * 100_000 + b" HTTP/1.1\r\nHost: x\r\n\r\n",
    "raw .. in the target": b"GET /v1/cameras/../../../etc/passwd HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n",
    "NUL in the target": b"GET /v1/cameras/a\x00b HTTP/1.1\r\nHost: x\r\n\r\n",
    "not HTTP at all": b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03" + b"\x00" * 64,
    "body shorter than Content-Length": b"POST /v1/cameras/street/keypoints HTTP/1.1\r\nHost: x\r\n"
    b'Content-Type: application/json\r\nContent-Length: 100000\r\n\r\n{"people": [',
    "negative Content-Length": b"POST /v1/cameras/street/keypoints HTTP/1.1\r\nHost: x\r\n"
    b"Content-Type: application/json\r\nContent-Length: -1\r\n\r\n{}",
    "two Content-Lengths": b"POST /v1/cameras/street/keypoints HTTP/1.1\r\nHost: x\r\nContent-Length: 2\r\n"
    b"Content-Length: 5\r\nContent-Type: application/json\r\n\r\n{}",
}


@pytest.mark.parametrize("name", list(PROTOCOL_CASES))
def test_protocol_abuse_gets_a_4xx_or_a_closed_connection(served: Served, name: str) -> None:
    status = _status(_exchange(served, PROTOCOL_CASES[name]))
    TALLY.record(CATEGORY, f"protocol: {name}", kinds=["curated"], status=status)
    assert status is None or 400 <= status < 500, f"{name}: answered {status}"
    assert served.http("GET", "/healthz", token="")[0] == 200, f"the server stopped answering after {name}"


def test_data_is_intact_after_the_abuse(served: Served) -> None:
    status, cameras = served.http("GET", "/v1/cameras")
    assert status == 200 and [camera["id"] for camera in cameras["items"]] == [CAMERA]
