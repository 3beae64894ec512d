"""A burst of good and poisoned frames from several keys and cameras at once, against a real `posemetry serve`:
zero 5xx, every good frame stored exactly once (issue 14's definition of done).

Before the fix, in a burst of 400 posts with 20 frames whose first keypoint was [1e39, 0, 0], 148 of the 380 good
frames were refused with 500 (the poisoned frame failed its whole write batch), and a key limited to its own camera,
posting bad frames, made 189 of 360 posts to another camera fail. Here every camera has its own key: one key posts
nothing but poison to its camera while the others post good frames (and true retries of them) to theirs.
"""

from __future__ import annotations

import json
import random
import shutil
import sqlite3
import tempfile
import time
from collections import Counter
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest

from tests.support.serving import Served, clean_environment, serve

CAMERAS = ("east", "west", "north", "south")
POISONER = "south"  # its key posts only poisoned frames
POSTS = 600
CLIENTS = 12


@pytest.fixture(scope="module")
def served() -> Iterator[tuple[Served, Path]]:
    data_dir = Path(tempfile.mkdtemp(prefix="pm-burst-"))
    try:
        with serve(data_dir, clean_environment(), output=data_dir / "serve.log") as app:
            yield app, data_dir
            assert app.stop() == 0
    finally:
        shutil.rmtree(data_dir, ignore_errors=True)


def keypoints(x: float) -> list[list[float]]:
    """17 rows as in the issue: [x, 300 + 10 i, 0.9]."""
    return [[x, 300.0 + 10 * i, 0.9] for i in range(17)]


def good_frame(k: int, rng: random.Random) -> str:
    people = [{"keypoints": keypoints(200.0 + 150 * p)} for p in range(rng.randint(1, 8))]
    return json.dumps(
        {"timestamp": f"2026-11-22T10:{k // 60 % 60:02d}:{k % 60:02d}Z", "frame_id": f"g-{k}", "people": people}
    )


def poisoned_frame(rng: random.Random) -> str:
    """The issue's frame, and the rest of what validation must stop (written as raw JSON: NaN and Infinity too)."""
    issue = keypoints(900.0)
    issue[0] = [1e39, 0, 0]
    good = [{"keypoints": keypoints(500.0)}]
    return rng.choice(
        [
            json.dumps({"timestamp": "2026-11-22T10:00:00Z", "people": [{"keypoints": issue}]}),
            json.dumps(
                {"timestamp": "2026-11-22T10:00:00Z", "people": [*good, {"shoulder": [1e300, 5], "ankle": None}]}
            ),
            '{"timestamp": "2026-11-22T10:00:00Z", "people": [{"shoulder": [NaN, 5], "ankle": [5, 90]}]}',
            '{"timestamp": "2026-11-22T10:00:00Z", "people": [{"keypoints": [[Infinity, 0, 0]'
            + ", [1, 1, 1]" * 16
            + "]}]}",
            json.dumps({"timestamp": "2026-11-22T10:00:00Z", "people": [{"keypoints": keypoints(5000.0)}]}),
            json.dumps({"timestamp": "2026-11-22T10:00:00Z", "people": [{"keypoints": keypoints(500.0)[:16]}]}),
            json.dumps({"timestamp": "0001-01-01T00:00:00+01:00", "people": good}),
            json.dumps({"timestamp": "2026-11-22T10:00:00Z", "people": good * 600}),
            '{"timestamp": "2026-11-22T10:00:00Z", "people": [',
        ]
    )


def test_a_burst_of_good_and_poisoned_frames_from_several_keys_and_cameras(served: tuple[Served, Path]) -> None:
    app, data_dir = served
    tokens = {}
    for camera in CAMERAS:
        assert app.http("PUT", f"/v1/cameras/{camera}", {"image_width_px": 1920, "image_height_px": 1080})[0] == 201
        status, key = app.http("POST", "/v1/keys", {"name": camera, "cameras": [camera]})
        assert status == 201
        tokens[camera] = key["token"]

    rng = random.Random(1414)
    posts: list[tuple[str, str, bool]] = []  # camera, body, good
    for k in range(POSTS):
        camera = rng.choice(CAMERAS)
        if camera == POISONER or rng.random() < 0.1:
            posts.append((camera, poisoned_frame(rng), False))
        else:
            posts.append((camera, good_frame(k, rng), True))
            if rng.random() < 0.05:
                posts.append((camera, posts[-1][1], True))  # a true retry: 200, the same frame
    rng.shuffle(posts)

    def send(item: tuple[str, str, bool]) -> tuple[int, float]:
        camera, body, _good = item
        started = time.perf_counter()
        status, _content, _type = app.raw(
            "POST", f"/v1/cameras/{camera}/keypoints", body.encode(), "application/json", token=tokens[camera]
        )
        return status, time.perf_counter() - started

    started = time.perf_counter()
    with ThreadPoolExecutor(CLIENTS) as pool:
        answers = list(pool.map(send, posts))
    elapsed = time.perf_counter() - started

    by_kind = Counter(
        ("good" if good else "poisoned", status) for (_, _, good), (status, _) in zip(posts, answers, strict=True)
    )
    latencies = sorted(seconds for _, seconds in answers)
    good_bodies = {json.loads(body)["frame_id"]: body for _, body, good in posts if good}
    print(
        f"\nburst: {len(posts)} posts ({len(good_bodies)} good frames, {sum(not g for *_, g in posts)} poisoned) from "
        f"{len(CAMERAS)} keys and {CLIENTS} clients in {elapsed:.1f} s ({len(posts) / elapsed:.0f} posts/s); "
        f"answers {dict(sorted(by_kind.items()))}; latency p50 {latencies[len(latencies) // 2] * 1000:.0f} ms, "
        f"max {latencies[-1] * 1000:.0f} ms"
    )
    assert not [kind for kind in by_kind if kind[1] >= 500], by_kind
    assert {status for (kind, status) in by_kind if kind == "good"} <= {200, 202}, by_kind
    assert {status for (kind, status) in by_kind if kind == "poisoned"} <= {400, 413, 422}, by_kind

    # Every good frame stored exactly once, with exactly its people, and counted once as evidence.
    with sqlite3.connect(f"file:{data_dir / 'posemetry.sqlite3'}?mode=ro", uri=True, timeout=30) as db:
        stored = Counter(row[0] for row in db.execute("SELECT client_frame_id FROM frames"))
        people = dict(db.execute("SELECT client_frame_id, people FROM frames").fetchall())
        observations = db.execute("SELECT count(*), sum(usable) FROM observations").fetchone()
        counters = db.execute("SELECT sum(usable_evidence_count) FROM cameras").fetchone()[0]
    assert set(stored) == set(good_bodies) and set(stored.values()) == {1}
    assert all(people[frame_id] == len(json.loads(body)["people"]) for frame_id, body in good_bodies.items())
    assert observations[0] == sum(people.values()) and counters == observations[1]
    assert by_kind[("good", 202)] == len(good_bodies)  # each created once; the retries were 200
