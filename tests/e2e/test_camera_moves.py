"""A camera that moves, as its user sees it: `posemetry serve`, keypoints posted at 2 frames/s of frame time
(timestamps synthetic, posted as fast as the service takes them), then the camera is panned 10 degrees and tilted
7 degrees down and goes on posting.

The move must be found within 20 s of frame time, said so (epoch 2, moved_at, reason camera_moved, a
`calibration.status_changed` webhook, the moves counter), the new epoch must calibrate to the new pose, and no
frame taken after the move may keep a result of the old epoch's calibration.
"""

from __future__ import annotations

import uuid
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np

from bench.moving_camera import CameraPose, Crowd, CrowdConfig
from tests.support.receiver import Receiver
from tests.support.serving import clean_environment, serve

FPS = 2.0
BEFORE = 360  # 3 minutes of frame time
DETECTION = 40  # 20 s: the move must be found among these frames
AFTER = 240  # 2 minutes more for the new epoch's calibration
PACE = 40
START = datetime(2026, 6, 1, 9, 0, tzinfo=UTC)


def frame_body(k: int, tops: np.ndarray, bottoms: np.ndarray) -> dict[str, object]:
    return {
        "timestamp": (START + timedelta(seconds=k / FPS)).isoformat(),
        "frame_id": f"f{k}",
        "people": [
            {"shoulder": [float(t[0]), float(t[1])], "ankle": [float(b[0]), float(b[1])]}
            for t, b in zip(tops, bottoms, strict=True)
        ],
    }


def test_a_panned_and_tilted_camera_is_found_and_calibrated_again(tmp_path: Path) -> None:
    before = CameraPose()
    after = before.panned(10.0).tilted(7.0)
    crowd = Crowd(CrowdConfig(people=36, region_m=(-20.0, 20.0, 2.0, 36.0)), np.random.default_rng(21))
    receiver = Receiver().start()
    settings = {"webhook_allowed_networks": "127.0.0.0/8"}
    try:
        with serve(tmp_path / "serve", clean_environment(**settings)) as app:
            size = {"image_width_px": before.image_size[0], "image_height_px": before.image_size[1]}
            assert app.http("PUT", "/v1/cameras/door", {**size, "person_height_m": 1.32})[0] == 201
            hook = {"url": f"{receiver.url}/{uuid.uuid4().hex}", "event_types": ["calibration.status_changed"]}
            status, subscription = app.http("POST", "/v1/webhooks", hook)
            assert status == 201, subscription

            urls: list[str] = []

            def post(first: int, count: int, pose: CameraPose) -> None:
                for k in range(first, first + count):
                    tops, bottoms, _ = crowd.seen_by(pose)
                    status, accepted = app.http("POST", "/v1/cameras/door/keypoints", frame_body(k, tops, bottoms))
                    assert status == 202, accepted
                    urls.append(accepted["url"])
                    crowd.step(1.0 / FPS)

            def calibration() -> dict[str, object]:
                return app.http("GET", "/v1/cameras/door/calibration")[1]

            for first in range(0, BEFORE, PACE):
                # In bursts that are measured before the next one comes, so the camera is solved along the way
                # as it would be in real time, not once at the end of a bulk upload.
                post(first, PACE, before)
                app.wait_for(lambda: app.http("GET", urls[-1])[1]["status"] == "done", f"frames up to {first}")
            old = calibration()
            assert (old["status"], old["epoch"], old["moved_at"], old["reason"]) == ("calibrated", 1, None, None)

            post(BEFORE, DETECTION, after)
            # No more frames come until the move is found: it must be found among these 20 s of frames.
            app.wait_for(lambda: calibration()["epoch"] == 2, "the move to be found")
            moved = calibration()
            # Uncalibrated for the move until the new epoch's people (the detection window's already) solve it.
            assert (moved["status"], moved["reason"]) in {("calibrated", None), ("calibrating", "camera_moved")} or (
                moved["status"] == "uncalibrated" and moved["reason"] == "camera_moved"
            ), moved
            moved_at = datetime.fromisoformat(str(moved["moved_at"]).replace("Z", "+00:00"))
            move_time = START + timedelta(seconds=BEFORE / FPS)
            assert move_time - timedelta(seconds=1) <= moved_at <= move_time

            post(BEFORE + DETECTION, AFTER, after)
            app.wait_for(
                lambda: all(app.http("GET", u)[1]["status"] == "done" for u in urls[BEFORE:]), "the new view measured"
            )
            # Solved on what the evidence warranted (no solve due: the next one waits for 1.5 x the people).
            app.wait_for(
                lambda: (c := calibration())["status"] == "calibrated" and c["people_needed"] > 0, "solves to settle"
            )
            new = calibration()
            assert (new["status"], new["epoch"], new["reason"]) == ("calibrated", 2, None)
            assert abs(new["fx_px"] / after.focal_px - 1) < 0.03, (new["fx_px"], after.focal_px)
            angle = np.degrees(np.arccos(np.clip(np.asarray(new["normal"]) @ after.normal, -1.0, 1.0)))
            assert angle < 1.0, angle

            # Versions carry their epoch; frames of the new view were measured with the new epoch's versions only.
            history = app.http("GET", "/v1/cameras/door/calibration/history?limit=1000")[1]["items"]
            epoch_of = {item["version"]: item["epoch"] for item in history}
            assert {1, 2} <= set(epoch_of.values())
            for k, url in enumerate(urls):
                frame = app.http("GET", url)[1]
                if k >= BEFORE:  # taken after the move
                    assert epoch_of[frame["calibration_version"]] == 2, k

            # Said so: a webhook with reason camera_moved, and the moves counter.
            app.wait_for(lambda: len(receiver.received()) >= 2, "the status webhooks")
            changes = [request.verify(subscription["secret"])["data"] for request in receiver.received()]
            assert [(c["previous_status"], c["status"]) for c in changes if c["reason"] == "camera_moved"] == [
                ("calibrated", "uncalibrated")
            ], changes
            metrics = app.raw("GET", "/metrics")[1].decode()
            assert 'posemetry_camera_moves_total{camera="door"} 1.0' in metrics
    finally:
        receiver.stop()
