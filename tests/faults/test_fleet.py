"""The fault tests' clients themselves (tests/faults/harness.py, fleet.py), without a stack: what they post must be
what the tests' counts assume.

The Redis-restart test under load (test_faults_under_load.py) expects one webhook event per measured frame of a
camera whose every pair is a violation. It failed 2 runs in 6 once the API answered faster (400 events for 411
measured frames): its fleet had posted past the 400 frames its alarm camera's scene had people for, and the frames
after those carried nobody, so they were measured with no violation and raised no event, as they should. A scene
that runs out now stops the fleet with an error instead.
"""

from __future__ import annotations

import json
import threading
from typing import Any

import pytest

from tests.faults.fleet import Fleet, posting
from tests.faults.harness import Answer, Client, SceneExhaustedError, SimulatedCamera, wait_until


class AcceptingClient(Client):
    """Accepts every post at once (202) and keeps the bodies, with no API behind it."""

    def __init__(self) -> None:
        super().__init__("http://unused.invalid", "key")
        self.bodies: list[dict[str, Any]] = []
        self._lock = threading.Lock()

    def request(self, method: str, path: str, body: Any = None, timeout_s: float = 30.0) -> Answer:
        with self._lock:
            self.bodies.append(json.loads(json.dumps(body)))
            url = f"/v1/cameras/x/frames/{len(self.bodies)}"
        return Answer(202, {"content-type": "application/json"}, {"url": url})


def test_a_simulated_camera_posts_each_frame_of_its_scene_with_its_people_then_refuses() -> None:
    camera = SimulatedCamera.draw("alarm", frames=3, people_per_frame=4, seed=31)
    assert camera.frames == 3
    bodies = [camera.next_frame() for _ in range(3)]
    assert [len(body["people"]) for body in bodies] == [4, 4, 4]
    assert [body["frame_id"] for body in bodies] == ["alarm-0", "alarm-1", "alarm-2"]
    with pytest.raises(SceneExhaustedError, match="alarm has posted all 3 frames"):
        camera.next_frame()  # it used to hand out frames with nobody in them
    assert camera.posted == 3 and camera.frame_ids == ["alarm-0", "alarm-1", "alarm-2"]


def test_a_fleet_whose_camera_runs_out_of_people_stops_with_that_error_and_never_posts_an_empty_frame() -> None:
    client = AcceptingClient()
    cameras = [
        SimulatedCamera.draw(name, frames=20, people_per_frame=2, seed=seed) for name, seed in (("a", 1), ("b", 2))
    ]
    with pytest.raises(SceneExhaustedError), posting(Fleet(client, cameras, clients=3)) as fleet:
        wait_until(lambda: len(client.bodies) >= 40, "every frame of both scenes posted", timeout_s=30)
    assert len(client.bodies) == len(fleet.accepted()) == 40
    assert all(len(body["people"]) == 2 for body in client.bodies), "a frame with nobody in it was posted"
