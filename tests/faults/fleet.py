"""Several camera systems posting at once through a fault, and the SQL count that says nothing was lost or doubled.

Each client is well behaved: it posts a frame with a client frame id, and on a 503 it waits (POLL_S, shorter than
the Retry-After a real client honours, so recovery shows to the tenth of a second) and posts the same frame again,
until it is accepted; then the next frame. Every answer is kept, so a test can say what each fault cost the clients
(503s, never a 500) and when posting worked again.
"""

from __future__ import annotations

import json
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

from sqlalchemy import create_engine, text

from tests.faults.harness import Client, SimulatedCamera

POLL_S = 0.1
# Frames a camera the fleet posts to should have people for (SimulatedCamera.draw(frames=...)). The fleet posts for
# as long as a fault takes, as fast as the API answers: up to ~410 frames a camera in one test on the 2-core
# machine, more with a faster API. A camera that runs out stops the fleet (harness.SceneExhaustedError) rather than
# post frames with nobody in them, which are measured with no violation: the Redis-restart test, which counts one
# webhook event per measured frame, once read those as events lost. Ten times the most seen (~1 s to draw a camera).
FLEET_FRAMES = 4000


@dataclass
class Post:
    """One frame as a client experienced it: every answer until it was accepted."""

    camera_id: str
    frame_id: str
    people: int
    statuses: list[int] = field(default_factory=list)
    answered_at: list[float] = field(default_factory=list)
    """time.monotonic() of each answer."""
    problems: list[str] = field(default_factory=list)
    """The problem type of each refusal."""
    accepted_at: float | None = None
    """time.monotonic() of the accepting answer (200 or 202)."""
    url: str | None = None


class Fleet:
    """`clients` threads posting to the cameras in turn, from `start()` until `stop()`; each finishes its frame."""

    def __init__(self, client: Client, cameras: list[SimulatedCamera], clients: int) -> None:
        self.client = client
        self.cameras = cameras
        self.clients = clients
        self.posts: list[Post] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._turn = 0
        self._errors: list[BaseException] = []

    def _next(self) -> tuple[SimulatedCamera, dict[str, Any]]:
        with self._lock:
            camera = self.cameras[self._turn % len(self.cameras)]
            self._turn += 1
            return camera, camera.next_frame()

    def _run(self) -> None:
        """One client; an error of its own (a camera out of people, an answer it cannot read) stops every client
        and is raised by `stop()`, so a test never goes on to count rows after its clients went wrong."""
        try:
            self._post_until_stopped()
        except BaseException as exc:
            with self._lock:
                self._errors.append(exc)
            self._stop.set()

    def _post_until_stopped(self) -> None:
        while not self._stop.is_set():
            camera, body = self._next()
            post = Post(camera.camera_id, body["frame_id"], len(body["people"]))
            with self._lock:
                self.posts.append(post)
            while True:
                answer = self.client.request("POST", f"/v1/cameras/{camera.camera_id}/keypoints", body)
                post.statuses.append(answer.status)
                post.answered_at.append(time.monotonic())
                if answer.status in (200, 202):
                    post.accepted_at, post.url = time.monotonic(), answer.body["url"]
                    break
                post.problems.append(str((answer.body or {}).get("type", "")).rsplit("/", 1)[-1])
                if answer.status != 503:
                    break  # not a fault's answer: the test says what it makes of it
                time.sleep(POLL_S)

    def start(self) -> Fleet:
        self._threads = [threading.Thread(target=self._run, daemon=True) for _ in range(self.clients)]
        for thread in self._threads:
            thread.start()
        return self

    def stop(self, timeout_s: float = 120.0) -> None:
        """Stop the clients once each has its frame accepted; raises the first error a client met."""
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout_s)
            assert not thread.is_alive(), "a client never got its frame accepted"
        if self._errors:
            raise self._errors[0]

    # ----------------------------------------------------------------------------------------- what happened

    def statuses(self) -> Counter[int]:
        return Counter(status for post in self.posts for status in post.statuses)

    def problems(self) -> Counter[str]:
        return Counter(problem for post in self.posts for problem in post.problems)

    def refused_between(self) -> tuple[float, float] | None:
        """When the first and the last refusal (503) were answered."""
        times = [t for post in self.posts for t, s in zip(post.answered_at, post.statuses, strict=True) if s == 503]
        return (min(times), max(times)) if times else None

    def accepted(self) -> list[Post]:
        return [post for post in self.posts if post.accepted_at is not None]

    def first_accepted_after(self, moment: float) -> float:
        """Seconds from `moment` to the first frame accepted after it."""
        return min(post.accepted_at for post in self.accepted() if post.accepted_at > moment) - moment  # type: ignore[operator]

    def summary(self) -> str:
        retried = sum(len(post.statuses) > 1 for post in self.posts)
        return (
            f"{self.clients} clients, {len(self.posts)} frames, {sum(len(p.statuses) for p in self.posts)} posts: "
            f"{dict(sorted(self.statuses().items()))}, refusals {dict(self.problems())}, {retried} frames posted again"
        )


@contextmanager
def posting(fleet: Fleet) -> Iterator[Fleet]:
    fleet.start()
    try:
        yield fleet
    finally:
        fleet.stop()


@dataclass(frozen=True)
class Counts:
    """A camera's rows in SQL, as the fault tests compare them with what the clients were told."""

    frames: Counter[str]
    """Rows per client frame id (each must be 1)."""
    people: dict[str, int]
    """Observation rows per client frame id."""
    statuses: Counter[str]
    usable: int
    evidence_counter: int
    violation_events: int
    violations_listed: int
    """Violations in the stored results of the camera's done frames."""


def _rows(db: Any, query: str, camera_id: str) -> list[Any]:
    return list(db.execute(text(query), {"c": camera_id}).all())


def sql_counts(database_url: str, camera_id: str) -> Counts:
    """Read a camera's rows straight from the database (PostgreSQL or SQLite)."""
    engine = create_engine(database_url.replace("postgresql://", "postgresql+psycopg://", 1))
    try:
        with engine.connect() as db:
            frames = Counter(
                dict(
                    _rows(db, "SELECT client_frame_id, count(*) FROM frames WHERE camera_id = :c GROUP BY 1", camera_id)
                )
            )
            people = dict(
                _rows(
                    db,
                    "SELECT f.client_frame_id, count(o.id) FROM frames f LEFT JOIN observations o ON o.frame_id = f.id "
                    "WHERE f.camera_id = :c GROUP BY f.id, f.client_frame_id",
                    camera_id,
                )
            )
            statuses = Counter(
                dict(_rows(db, "SELECT status, count(*) FROM frames WHERE camera_id = :c GROUP BY 1", camera_id))
            )
            (usable,) = _rows(db, "SELECT count(*) FROM observations WHERE camera_id = :c AND usable", camera_id)[0]
            (counter,) = _rows(db, "SELECT usable_evidence_count FROM cameras WHERE id = :c", camera_id)[0]
            (events,) = _rows(db, "SELECT count(*) FROM violation_events WHERE camera_id = :c", camera_id)[0]
            results = _rows(db, "SELECT result FROM frames WHERE camera_id = :c AND status = 'done'", camera_id)
    finally:
        engine.dispose()
    listed = sum(len((r if isinstance(r, dict) else json.loads(r))["violations"]) for (r,) in results)
    return Counts(frames, people, statuses, int(usable), int(counter), int(events), listed)


def assert_nothing_lost_or_doubled(fleet: Fleet, counts: Counts, camera_id: str) -> None:
    """Every frame the clients were told was accepted is stored once with exactly its people, evidence is counted
    once, and violation events match the stored results."""
    accepted = {post.frame_id: post.people for post in fleet.accepted() if post.camera_id == camera_id}
    assert set(counts.frames.values()) <= {1}, "a frame stored twice"
    missing = set(accepted) - set(counts.frames)
    assert not missing, f"{len(missing)} accepted frames are missing"
    assert all(counts.people[frame_id] == people for frame_id, people in accepted.items()), "people lost or doubled"
    assert counts.evidence_counter == counts.usable, "evidence counted twice, or not at all"
    assert counts.violation_events == counts.violations_listed, "violation events doubled or lost"
