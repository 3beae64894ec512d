"""`posemetry analyze` on the real Oxford Town Centre camera: the calibration it lands on, and what it writes.

The clip is 126 frames of 1080p at 25 fps; every 6th frame (21 frames, ~150 usable people) keeps the run near
10 s of pose on 2 cores. Measured with this stride: fx 2809 px (+4.2 % against the published 2696 px) and the
ground normal 1.6 degrees off; the issue's bounds (10 %, 3 degrees) are asserted. The folder run gives the focal
length (`--focal-px`), so 8 frames are enough, and exercises skipped files, JPEG pictures, feet and a video.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from click.testing import Result

from bench.towncentre import TownCentreCalibration, load_calibration
from tests.support.analyze import TOWN_CALIBRATION, TOWN_VIDEO, analyze, write_image

STRIDE = 6
VIDEO_FRAMES = list(range(0, 126, STRIDE))
FOLDER_FRAMES = ["clip_000000.jpg", "clip_000018.jpg", "clip_000036.jpg", "clip_000054.jpg"]
FOLDER_FRAMES += ["clip_000072.jpg", "clip_000090.jpg", "clip_000108.jpg", "clip_000125.jpg"]


@pytest.fixture(scope="module")
def truth(town: Path) -> TownCentreCalibration:
    return load_calibration(TOWN_CALIBRATION)


@pytest.fixture(scope="module")
def video_run(models: Path, town: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Result, Path]:
    out = tmp_path_factory.mktemp("town-video")
    result = analyze(TOWN_VIDEO, "--out", out, "--stride", STRIDE, "--model-dir", models, "--pose-model", "thunder")
    assert result.exit_code == 0, result.output
    return result, out


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(a @ b / np.linalg.norm(a) / np.linalg.norm(b), -1.0, 1.0))))


def _lines(path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def _csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def test_video_calibration_lands_on_the_published_camera(
    video_run: tuple[Result, Path], truth: TownCentreCalibration
) -> None:
    result, out = video_run
    cal = json.loads((out / "calibration.json").read_text())
    assert cal["status"] == "ok" and cal["fx_px"] == cal["fy_px"]
    assert abs(cal["fx_px"] / truth.fx - 1) < 0.10
    assert _angle_deg(np.array(cal["normal"]), truth.ground_normal) < 3.0
    assert 5.0 < cal["rho_m"] < 12.0  # published: 7.8 m; rho scales with the height prior
    assert cal["image_size_px"] == [1920, 1080]
    unc = cal["uncertainty"]
    # Not given, the principal point is the image centre as a prior, moved only where the people say so.
    assert cal["principal_point_source"] in ("estimated", "assumed")
    assert abs(cal["cx_px"] - 960.0) < 2 * unc["cx_std_px"] and abs(cal["cy_px"] - 540.0) < 2 * unc["cy_std_px"]
    assert 0 < unc["fx_std_px"] < 0.1 * cal["fx_px"] and 0 < unc["normal_std_deg"] < 3 and unc["rho_std_m"] > 0
    assert len(unc["covariance"]) == 8 and unc["covariance_parameters"][0] == "fx_px"
    assert cal["quality"]["grade"] in ("good", "rough", "unreliable")
    ev = cal["evidence"]
    assert ev["frames"] == len(VIDEO_FRAMES) and ev["frames_skipped"] == 0
    assert ev["people_seen"] >= ev["usable"] >= ev["used"] >= ev["inliers"] >= 100
    assert ev["people_seen"] - ev["usable"] == sum(ev["unusable_reasons"].values())
    assert cal["options"]["stride"] == STRIDE and cal["options"]["threshold_m"] == pytest.approx(1.8288)
    assert cal["pose_model"].removesuffix("@bf16").endswith("movenet-thunder") and cal["source"]["fps"] == 25.0
    for line in ("focal length", "ground normal", "violations", "inliers"):
        assert line in result.stdout


def test_video_tables_agree_with_each_other(video_run: tuple[Result, Path]) -> None:
    _, out = video_run
    frames = _lines(out / "frames.jsonl")
    assert [f["frame"] for f in frames] == VIDEO_FRAMES
    assert [f["time_s"] for f in frames] == pytest.approx([n / 25 for n in VIDEO_FRAMES])
    people = [p for f in frames for p in f["people"]]
    pairs = [p for f in frames for p in f["pairs"]]
    assert all(len(f["pairs"]) == len(f["people"]) * (len(f["people"]) - 1) // 2 for f in frames)
    cal = json.loads((out / "calibration.json").read_text())
    assert len(people) == cal["evidence"]["people_seen"]
    assert sum(p["usable"] for p in people) == cal["evidence"]["usable"]
    assert sum(p["calibration"] == "inlier" for p in people) == cal["evidence"]["inliers"]
    assert all(p["calibration"] is None for p in people if not p["usable"])
    for person in people:
        assert len(person["keypoints"]) == 17 and len(person["box_px"]) == 4
        assert (person["ground_m"] is None) == (person["placed_from"] is None)
    # Most people are placed. Not all: the detector's regions vote (service/pose/merge.py) and find people half
    # hidden or far away whose keypoints place nobody (measured: 254 of 417 placed before the votes, 260 of 456
    # with them).
    assert sum(p["ground_m"] is not None for p in people) >= 0.55 * len(people)
    for pair in pairs:
        assert pair["violation"] == (pair["distance_m"] is not None and pair["distance_m"] < 1.8288)
        if pair["distance_m"] is not None:
            assert pair["distance_m"] >= 0 and pair["distance_std_m"] > 0
    assert sum(f["violations"] for f in frames) == sum(p["violation"] for p in pairs)

    people_rows, pair_rows, frame_rows = _csv(out / "people.csv"), _csv(out / "pairs.csv"), _csv(out / "frames.csv")
    assert len(people_rows) == len(people) and len(pair_rows) == len(pairs) and len(frame_rows) == len(frames)
    assert [int(r["frame"]) for r in frame_rows] == VIDEO_FRAMES
    first = people[0]
    assert float(people_rows[0]["box_left_px"]) == pytest.approx(first["box_px"][0], rel=1e-5)
    assert people_rows[0]["usable"] == ("true" if first["usable"] else "false")
    for row, pair in zip(pair_rows, pairs, strict=True):
        assert (row["distance_m"] == "") == (pair["distance_m"] is None)
        assert row["violation"] == ("true" if pair["violation"] else "false")
    assert sum(int(r["violations"]) for r in frame_rows) == sum(p["violation"] for p in pairs)


def test_video_pictures_and_videos(video_run: tuple[Result, Path]) -> None:
    _, out = video_run
    names = [f"frame_{n:06d}.png" for n in VIDEO_FRAMES]
    assert sorted(p.name for p in (out / "overlays").iterdir()) == names
    assert sorted(p.name for p in (out / "topdown").iterdir()) == names
    for name in names[:: len(names) // 3]:
        overlay = cv2.imread(str(out / "overlays" / name))
        assert overlay is not None and overlay.shape == (1080, 1920, 3)
        topdown = cv2.imread(str(out / "topdown" / name))
        assert topdown is not None and topdown.shape == (800, 800, 3)
    for video, size in (("overlay.mp4", (1920, 1080)), ("topdown.mp4", (800, 800))):
        capture = cv2.VideoCapture(str(out / video))
        assert capture.isOpened()
        assert capture.get(cv2.CAP_PROP_FPS) == pytest.approx(25 / STRIDE, rel=1e-3)
        assert (capture.get(cv2.CAP_PROP_FRAME_WIDTH), capture.get(cv2.CAP_PROP_FRAME_HEIGHT)) == size
        decoded = 0
        while capture.read()[0]:
            decoded += 1
        capture.release()
        assert decoded == len(VIDEO_FRAMES)


def test_image_folder_with_a_known_focal_length(
    models: Path, town: Path, tmp_path: Path, truth: TownCentreCalibration
) -> None:
    """A folder with two bad files among the frames: they are skipped with the reason, the rest analysed; `--fps`
    gives the images their times (the frames are 18 of the video's apart, 0.72 s; the last one 17), so one walker
    counts once."""
    folder = tmp_path / "frames"
    folder.mkdir()
    for name in FOLDER_FRAMES:
        shutil.copyfile(town / "frames" / name, folder / name)
    (folder / "clip_000126.jpg").write_bytes((town / "frames" / FOLDER_FRAMES[0]).read_bytes()[:20000])
    write_image(folder / "clip_000127.png", (640, 360))
    (folder / "README.txt").write_text("frames of the Oxford Town Centre clip")
    out = tmp_path / "out"
    result = analyze(
        folder,
        "-o",
        out,
        "--model-dir",
        models,
        "--focal-px",
        truth.fx,
        "--image-format",
        "jpg",
        "--unit",
        "ft",
        "--threshold",
        "2 m",
        "--video",
        "--fps",
        25 / 18,
    )
    assert result.exit_code == 0, result.output
    assert "truncated" in result.output and "clip_000127.png" in result.output
    cal = json.loads((out / "calibration.json").read_text())
    assert cal["fx_px"] == pytest.approx(truth.fx) and cal["options"]["focal_px"] == pytest.approx(truth.fx)
    # Eight frames, ~40 usable people: the normal's own 1-sigma is 1.6-2.0 deg, and detector changes that move recall
    # by a person or two moved it between 2.3 and 4.6 deg (docs/benchmarks/pose.md, "Votes across regions"; 4.6 ->
    # 3.7 deg off, 36 people used instead of 42, sigma 2.00 -> 2.02 deg, when keypoints outside their own box lost
    # their trust: "A keypoint outside its own box").
    assert _angle_deg(np.array(cal["normal"]), truth.ground_normal) < 3.0 * cal["uncertainty"]["normal_std_deg"] < 7.5
    assert cal["evidence"]["frames"] == len(FOLDER_FRAMES) and cal["evidence"]["frames_skipped"] == 2
    assert cal["source"]["kind"] == "images" and cal["options"]["threshold_m"] == 2.0
    assert cal["warnings"] == []  # --fps gave the images their times
    frames = _lines(out / "frames.jsonl")
    assert [f["file"] for f in frames] == FOLDER_FRAMES
    assert [f["time_s"] for f in frames] == pytest.approx([0.72 * k for k in range(len(FOLDER_FRAMES))])
    assert cal["source"]["fps"] == pytest.approx(25 / 18) and cal["individuals"] < cal["evidence"]["inliers"]
    for pair in (p for f in frames for p in f["pairs"]):
        assert pair["violation"] == (pair["distance_m"] is not None and pair["distance_m"] < 2.0)
    overlays = sorted((out / "overlays").iterdir())
    assert [p.name for p in overlays] == FOLDER_FRAMES  # named after the images (JPEG here too)
    assert cv2.imread(str(overlays[0])).shape == (1080, 1920, 3)
    capture = cv2.VideoCapture(str(out / "overlay.mp4"))
    assert capture.get(cv2.CAP_PROP_FPS) == pytest.approx(5.0) and int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == 8
    capture.release()
