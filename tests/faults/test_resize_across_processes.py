"""A resize holds at once on every API process of a real `posemetry serve` (two API processes), and no person
checked against the old size ends up in the new size's evidence (issue 14).

Eight clients post frames whose people only fit the old 1920x1080 image (x = 1500 px is far outside 640 px) to
both API processes, before, during and after a PUT that makes the camera 640x360. Each process keeps cameras in
memory for a minute here (camera_cache_ttl_s), so nothing but the store's check at commit can stop the old size:
before it, 10-19 of 40-100 posts after the PUT were still accepted, and their people joined the new evidence.
"""

from __future__ import annotations

import json
import shutil
import sqlite3
import tempfile
import threading
import time
import urllib.error
import urllib.request
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.support.serving import Served, clean_environment, serve

OLD = {"image_width_px": 1920, "image_height_px": 1080}
NEW = {"image_width_px": 640, "image_height_px": 360}
CLIENTS = 8


@pytest.fixture(scope="module")
def served() -> Iterator[tuple[Served, Path]]:
    data_dir = Path(tempfile.mkdtemp(prefix="pm-resize-"))
    env = clean_environment(camera_cache_ttl_s="60")
    try:
        with serve(data_dir, env, args=["--api-processes", "2", "--workers", "1"]) as app:
            yield app, data_dir
            assert app.stop() == 0
    finally:
        shutil.rmtree(data_dir, ignore_errors=True)


def person(x: float, y0: float = 300.0) -> dict[str, list[float]]:
    return {"shoulder": [x, y0], "ankle": [x, y0 + 150.0]}


def post(app: Served, body: dict[str, Any]) -> int:
    """A fresh connection per post, so the kernel spreads the posts over both API processes."""
    request = urllib.request.Request(
        f"{app.base}/v1/cameras/door/keypoints",
        data=json.dumps(body).encode(),
        method="POST",
        headers={"Authorization": f"Bearer {app.api_key}", "content-type": "application/json"},
    )
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            return int(response.status)
    except urllib.error.HTTPError as exc:
        return int(exc.code)


def test_posts_around_a_resize_never_store_old_size_people(served: tuple[Served, Path]) -> None:
    app, data_dir = served
    assert app.http("PUT", "/v1/cameras/door", OLD)[0] == 201
    old_frame = {"timestamp": "2026-11-22T10:00:00Z", "people": [person(1500), person(1600), person(300)]}
    # Both processes read the camera and keep it in memory.
    assert {post(app, old_frame) for _ in range(20)} == {202}

    put_done = threading.Event()
    stop = threading.Event()
    answers: list[tuple[bool, int]] = []  # (started after the PUT returned, status)
    lock = threading.Lock()

    def client() -> None:
        while not stop.is_set():
            after = put_done.is_set()
            status = post(app, old_frame)
            with lock:
                answers.append((after, status))

    threads = [threading.Thread(target=client) for _ in range(CLIENTS)]
    for thread in threads:
        thread.start()
    time.sleep(0.5)
    assert app.http("PUT", "/v1/cameras/door", NEW)[0] == 200
    put_done.set()
    time.sleep(1.5)
    stop.set()
    for thread in threads:
        thread.join()

    during = Counter(status for after, status in answers if not after)
    after = Counter(status for after, status in answers if after)
    print(f"\nposts before or during the PUT: {dict(during)}; posts after it: {dict(after)}")
    assert sum(after.values()) >= 40
    assert set(after) == {422}, after  # refused against the new size, by both processes
    assert set(during) <= {202, 422}, during

    # Nothing of the old size is left in the evidence; the frames accepted before the PUT failed with the reason.
    with sqlite3.connect(f"file:{data_dir / 'posemetry.sqlite3'}?mode=ro", uri=True, timeout=30) as db:
        wide = db.execute("SELECT count(*) FROM observations WHERE camera_id = 'door' AND ankle_x_px > 960").fetchone()
        statuses = dict(db.execute("SELECT status, count(*) FROM frames GROUP BY status").fetchall())
    assert wide == (0,)
    assert set(statuses) == {"failed"} and statuses["failed"] == 20 + during[202], statuses

    # The new size works at once, everywhere, and its evidence is its own.
    new_frame = {"timestamp": "2026-11-22T10:01:00Z", "people": [person(300, 100), person(500, 100)]}
    assert {post(app, new_frame) for _ in range(20)} == {202}
    status, camera = app.http("GET", "/v1/cameras/door")
    assert status == 200 and camera["usable_evidence_count"] == 40
