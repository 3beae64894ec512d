"""Bad input to `posemetry analyze`: one clear line and exit status 1, never a traceback; what can be kept is kept."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import pytest

from service.analyze.errors import AnalyzeError
from service.analyze.options import Threshold, parse_threshold
from service.analyze.run import NO_TIMES_WARNING
from tests.support.analyze import analyze, write_image
from tests.support.shared import SHARED_DATA


def _one_line_error(output: str) -> str:
    lines = [line for line in output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), output
    assert "Traceback" not in output
    return lines[0]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["{tmp}/missing.mp4"], "does not exist"),
        (["{tmp}/empty"], "no images in"),
        (["{tmp}/clip.mp4"], "cannot read"),
        (["{tmp}/empty", "--threshold", "6"], "with a unit"),
        (["{tmp}/empty", "--threshold", "-2m"], "with a unit"),
        (["{tmp}/empty", "--pose-model", "huge"], "--pose-model must be one of thunder, lightning"),
        (["{tmp}/empty", "--height", "4"], "height prior must be between"),
        (["{tmp}/empty", "--stride", "0"], "stride must be at least 1"),
        (["{tmp}/empty", "--focal-px", "-5"], "focal length must be a positive"),
        (["{tmp}/empty", "--unit", "yd"], "--unit must be one of m, ft"),
    ],
)
def test_bad_input_is_one_line_and_exit_1(tmp_path: Path, args: list[str], message: str) -> None:
    (tmp_path / "empty").mkdir()
    (tmp_path / "clip.mp4").write_text("not a video")
    result = analyze(*(a.format(tmp=tmp_path) for a in args), "--out", tmp_path / "out")
    assert result.exit_code == 1
    assert message in _one_line_error(result.output)


def test_missing_models_name_the_fix(tmp_path: Path) -> None:
    write_image(tmp_path / "a.png")
    result = analyze(tmp_path / "a.png", "--out", tmp_path / "out", "--model-dir", tmp_path / "no-models")
    assert result.exit_code == 1
    line = _one_line_error(result.output)
    assert "rtmdet_nano_person_320.onnx" in line and "posemetry models fetch" in line


def test_an_output_folder_that_cannot_be_written(tmp_path: Path) -> None:
    write_image(tmp_path / "a.png")
    (tmp_path / "taken").write_text("a file where the folder should go")
    result = analyze(tmp_path / "a.png", "--out", tmp_path / "taken")
    assert result.exit_code == 1 and "cannot write to" in _one_line_error(result.output)


def test_no_people_fails_the_calibration_but_keeps_what_was_found(models: Path, tmp_path: Path) -> None:
    frames = tmp_path / "frames"
    frames.mkdir()
    for n in range(2):
        write_image(frames / f"empty_{n}.jpg", (640, 480), value=40 + 80 * n)
    out = tmp_path / "out"
    result = analyze(frames, "--out", out, "--model-dir", models)
    assert result.exit_code == 1
    assert "Traceback" not in result.output
    assert "error: calibration failed: no people found in 2 frames" in result.output
    cal = json.loads((out / "calibration.json").read_text())
    assert cal["status"] == "failed" and cal["fx_px"] is None and cal["evidence"]["frames"] == 2
    # Images without --fps: one person in several images would count as several; said during the run and kept.
    assert cal["warnings"] == [NO_TIMES_WARNING]
    assert "note: the images have no times (give --fps" in " ".join(result.output.split())
    assert len((out / "frames.jsonl").read_text().splitlines()) == 2
    assert not (out / "overlays").exists()


def test_one_person_cannot_calibrate(models: Path, town: Path, tmp_path: Path) -> None:
    """A crop of a real frame around one pedestrian: pose finds them, calibration refuses with its reason."""
    frame = cv2.imread(str(town / "frames" / "clip_000000.jpg"))
    crop = tmp_path / "one.png"
    cv2.imwrite(str(crop), frame[560:1080, 1500:1900])  # the pedestrian bottom right, walking towards the camera
    out = tmp_path / "out"
    result = analyze(crop, "--out", out, "--model-dir", models, "--no-images")
    assert result.exit_code == 1 and "Traceback" not in result.output
    assert "error: calibration failed:" in result.output
    cal = json.loads((out / "calibration.json").read_text())
    assert cal["status"] == "failed" and cal["reason"] and cal["evidence"]["people_seen"] >= 1


def test_thresholds_need_a_unit() -> None:
    assert parse_threshold("6ft") == Threshold(6.0, "ft") and parse_threshold("6 ft").metres == pytest.approx(1.8288)
    assert parse_threshold("1.5 metres") == Threshold(1.5, "m") and parse_threshold("2M").metres == 2.0
    for bad in ("6", "ft", "six feet", "0m", "1e9 m", "nan m"):
        with pytest.raises(AnalyzeError):
            parse_threshold(bad)


def test_camera_options_are_parsed_and_checked() -> None:
    from service.analyze.options import AnalyzeOptions, parse_numbers

    assert parse_numbers("960.5, 540", "--principal-point", (2,)) == (960.5, 540.0)
    assert parse_numbers(None, "--lens", (4, 5)) is None
    with pytest.raises(AnalyzeError, match="--focal-px must be 1 or 2"):
        parse_numbers("1,2,3", "--focal-px", (1, 2))
    with pytest.raises(AnalyzeError, match="--lens"):
        parse_numbers("a,b,c,d", "--lens", (4, 5))
    options = AnalyzeOptions(
        principal_point_px=(950.0, 530.0), focal_px=(2700.0, 2710.0), lens=(-0.1, 0.02, 0.0, 0.0), camera_height_m=7.8
    ).checked()
    problem = options.problem((1920, 1080))
    assert problem.principal_point_px == (950.0, 530.0) and problem.known_focal_px == (2700.0, 2710.0)
    assert problem.lens is not None and problem.lens.k1 == -0.1 and problem.camera_height_m == 7.8
    with pytest.raises(AnalyzeError, match="lens needs 4 or 5"):
        AnalyzeOptions(lens=(0.1, 0.2)).checked()
    with pytest.raises(AnalyzeError, match="camera height"):
        AnalyzeOptions(camera_height_m=-1.0).checked()


def test_a_handful_of_usable_people_is_refused_not_calibrated(models: Path, tmp_path: Path) -> None:
    """The steep atrium view: the detector finds the people (9-20 a frame), but MoveNet trusts both ankles of few
    of them from that high; a camera from a handful of people looked solved and was not (a 360 px focal length
    from 5 people), so analyze refuses below --min-people and says what to do."""
    atrium = SHARED_DATA / "mot3d_atrium" / "frames"
    if not atrium.is_dir():
        pytest.skip(f"atrium frames directory {atrium} is absent")
    frames = tmp_path / "frames"
    frames.mkdir()
    for name in ("frame_49650.jpg", "frame_49670.jpg", "frame_49690.jpg"):
        (frames / name).write_bytes((atrium / name).read_bytes())
    out = tmp_path / "out"
    result = analyze(frames, "--out", out, "--model-dir", models, "--no-images", "--pose-model", "lightning")
    assert result.exit_code == 1 and "Traceback" not in result.output
    assert "usable people, at least 30 needed" in result.output and "--min-people" in result.output
    cal = json.loads((out / "calibration.json").read_text())
    assert cal["status"] == "failed" and cal["fx_px"] is None
    people = [len(json.loads(line)["people"]) for line in (out / "frames.jsonl").read_text().splitlines()]
    assert len(people) == 3 and min(people) >= 9  # the detector at 640 px alone found 3-4 in each
