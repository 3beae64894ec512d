"""A simulated camera streams frames into `posemetry serve`, one POST at a time, on SQLite and on PostgreSQL.

This is the product's promise end to end: from nothing but people walking by, the camera is calibrated (and
re-calibrated as evidence grows), every frame gets its people's positions and pair distances back, frames that
arrived before any calibration are answered once one exists, and the 6 ft verdicts match the truth.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

from bench.simulate import SceneConfig, draw_scene
from tests.support.app import coco_person
from tests.support.jobs import FRAME_SPACING_S
from tests.support.serving import clean_environment, serve

FRAMES = 40
PEOPLE_PER_FRAME = 10
THRESHOLD_M = 1.8288
START = datetime(2026, 3, 1, 8, 0, tzinfo=UTC)


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_streamed_frames_calibrate_the_camera_and_come_back_measured(
    backend: str, request: pytest.FixtureRequest, tmp_path: Path
) -> None:
    settings = {"calibration_min_people": "30", "calibration_growth_factor": "1.5"}
    if backend == "postgresql":
        settings["database_url"] = request.getfixturevalue("migrated_url")
    # A surveillance camera (square pixels, 1.5 px keypoint noise, 7 cm spread of people's heights).
    scene = draw_scene(SceneConfig.surveillance(n_people=FRAMES * PEOPLE_PER_FRAME), np.random.default_rng(11))
    with serve(tmp_path / "serve", clean_environment(**settings)) as app:
        camera = {"image_width_px": scene.image_size[0], "image_height_px": scene.image_size[1], "person_height_m": 1.7}
        assert app.http("PUT", "/v1/cameras/street", camera)[0] == 201

        urls, statuses_on_arrival = [], []
        for k in range(FRAMES):
            people = slice(k * PEOPLE_PER_FRAME, (k + 1) * PEOPLE_PER_FRAME)
            body = {
                "timestamp": (START + timedelta(seconds=FRAME_SPACING_S * k)).isoformat(),
                "frame_id": f"street-{k}",
                "people": [
                    {"keypoints": coco_person(tuple(top), tuple(bottom))}
                    for top, bottom in zip(scene.tops_px[people], scene.bottoms_px[people], strict=True)
                ],
            }
            status, accepted = app.http("POST", "/v1/cameras/street/keypoints", body)
            assert status == 202, accepted
            urls.append(accepted["url"])
            statuses_on_arrival.append(app.http("GET", accepted["url"])[1]["status"])
            if k >= 3:
                # Paced like a camera, not a bulk upload: each frame is answered before the next one comes, so
                # the calibration is re-solved along the way rather than once at the end.
                app.wait_for(lambda url=accepted["url"]: app.http("GET", url)[1]["status"] == "done", f"frame {k}")
            if k == 0:
                # A client retry of the same frame is the same frame, not more evidence.
                retry_status, retry = app.http("POST", "/v1/cameras/street/keypoints", body)
                assert retry_status == 200 and retry["frame_id"] == accepted["frame_id"]

        # The first two frames (20 people) are below the 30 needed: they wait for a calibration.
        assert statuses_on_arrival[0] == statuses_on_arrival[1] == "pending"
        app.wait_for(lambda: all(app.http("GET", url)[1]["status"] == "done" for url in urls), "every frame measured")
        # Solves follow the evidence by factors of 1.5 (30, 45, ... 342 people); a forced one takes it all.
        assert app.http("POST", "/v1/cameras/street/calibration")[0] == 202
        usable = app.http("GET", "/v1/cameras/street")[1]["usable_evidence_count"]
        assert 0.9 * FRAMES * PEOPLE_PER_FRAME <= usable <= FRAMES * PEOPLE_PER_FRAME  # a few touch the border
        app.wait_for(
            lambda: app.http("GET", "/v1/cameras/street/calibration")[1]["solved_evidence_count"] == usable,
            "a solve on all the evidence",
        )
        status, calibration = app.http("GET", "/v1/cameras/street/calibration")
        assert status == 200 and calibration["status"] == "calibrated"

        # Converged on the truth: 400 people pin the focal length to a few percent and the ground to a degree.
        assert abs(calibration["fx_px"] / scene.fx - 1) < 0.03, (calibration["fx_px"], scene.fx)
        normal = np.array(calibration["normal"])
        assert np.degrees(np.arccos(np.clip(normal @ scene.normal, -1, 1))) < 1.5
        assert abs(calibration["rho_m"] / scene.rho - 1) < 0.05
        # ... by re-solving as evidence grew (30, 45, 68, ... people), each version kept in the history.
        history = app.http("GET", "/v1/cameras/street/calibration/history")[1]["items"]
        assert len(history) >= 3
        assert calibration["version"] == max(item["version"] for item in history)
        evidence = [item["evidence_count"] for item in sorted(history, key=lambda item: item["version"])]
        assert evidence == sorted(evidence) and evidence[0] >= 30

        # Every frame, those that waited included, carries positions, distances and verdicts near the truth.
        errors, verdicts, violations = [], [], 0
        for k, url in enumerate(urls):
            result = app.http("GET", url)[1]["result"]
            assert result is not None and len(result["people"]) == PEOPLE_PER_FRAME
            truth = scene.points_bottom[k * PEOPLE_PER_FRAME : (k + 1) * PEOPLE_PER_FRAME]
            flagged = {(v["i"], v["j"]) for v in result["violations"]}
            violations += len(flagged)
            for pair in result["pairs"]:
                true_m = float(np.linalg.norm(truth[pair["i"]] - truth[pair["j"]]))
                errors.append(abs(pair["distance_m"] / true_m - 1))
                assert pair["distance_std_m"] > 0
                if abs(true_m - THRESHOLD_M) > 0.3:  # clear of the threshold: the verdict must be right
                    verdicts.append(((pair["i"], pair["j"]) in flagged) == (true_m < THRESHOLD_M))
        assert np.median(errors) < 0.05
        assert np.mean(verdicts) > 0.95
        assert violations > 0  # the scene is crowded enough for the check above to mean something

        # The dashboard's counts agree with the frames' own violations.
        since, until = (t.isoformat().replace("+00:00", "Z") for t in (START, START + timedelta(hours=1)))
        counts = app.http("GET", f"/v1/cameras/street/violations?since={since}&until={until}&bucket=minute")[1]
        assert counts["total"] == sum(bucket["count"] for bucket in counts["buckets"]) == violations

        # Synchronous measurement of the last frame's people with the current calibration agrees with the
        # stored result when that frame was measured with the same version.
        last = app.http("GET", urls[-1])[1]
        if last["calibration_version"] == calibration["version"]:
            people = slice((FRAMES - 1) * PEOPLE_PER_FRAME, FRAMES * PEOPLE_PER_FRAME)
            body = {
                "people": [
                    {"keypoints": coco_person(tuple(top), tuple(bottom))}
                    for top, bottom in zip(scene.tops_px[people], scene.bottoms_px[people], strict=True)
                ]
            }
            status, direct = app.http("POST", "/v1/cameras/street/distances", body)
            assert status == 200
            stored = {(p["i"], p["j"]): p["distance_m"] for p in last["result"]["pairs"]}
            for pair in direct["pairs"]:
                assert pair["distance_m"] == pytest.approx(stored[(pair["i"], pair["j"])], rel=1e-9)
        assert app.stop() == 0
