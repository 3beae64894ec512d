"""The load benchmark: its parts on known inputs, and `posemetry bench load` end to end on a tiny load (no timings
asserted: the figures are the benchmark's output, not a test's)."""

from __future__ import annotations

import asyncio
import json
import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from bench.frames import coco17_keypoints, walking_cameras
from bench.http_client import Connection, HttpError, serve
from bench.load_calibration import CalibrationWatch
from bench.load_stats import KindStats
from bench.metrics_text import delta_by, parse_metrics
from bench.profile import ProfileSummary
from service.cli import app
from tests.support.shared import TOWN_CENTRE, model_dir_path, require_dir


def _centres(people: list[dict[str, list[list[float]]]]) -> tuple[np.ndarray, np.ndarray]:
    keypoints = np.array([person["keypoints"] for person in people])
    return keypoints[:, 5:7, :2].mean(axis=1), keypoints[:, 15:17, :2].mean(axis=1)


def test_coco17_keypoints_have_the_simulated_shoulder_and_ankle_centres() -> None:
    tops = np.array([[100.0, 200.0], [640.5, 300.25]])
    bottoms = np.array([[104.0, 400.0], [650.0, 610.0]])
    keypoints = coco17_keypoints(tops, bottoms, np.random.default_rng(0))
    assert keypoints.shape == (2, 17, 3)
    np.testing.assert_allclose(keypoints[:, 5:7, :2].mean(axis=1), tops)
    np.testing.assert_allclose(keypoints[:, 15:17, :2].mean(axis=1), bottoms)
    assert np.all((keypoints[:, :, 2] >= 0.6) & (keypoints[:, :, 2] <= 0.99))
    assert np.all(keypoints[:, 0, 1] < keypoints[:, 5, 1])  # the nose above the shoulders (image y down)


def test_walking_people_stay_in_view_and_move_at_walking_pace() -> None:
    body, (camera,) = walking_cameras(1, seed=3, frames=40, fps=6.0, people=12)
    width, height = body["image_width_px"], body["image_height_px"]
    frames = [json.loads(people) for people in camera.people]
    tops, bottoms = zip(*(_centres(people) for people in frames), strict=True)
    for top, bottom in zip(tops, bottoms, strict=True):
        assert len(top) == 12
        # In view, up to the pixel noise on the centres.
        assert np.all((bottom > -10) & (bottom < (width + 10, height + 10)))
        assert np.all(top[:, 1] < bottom[:, 1])
    steps = np.abs(np.diff(np.array(bottoms), axis=0)).max()
    far = np.abs(np.array(bottoms)[-1] - np.array(bottoms)[0]).max()
    assert steps < far  # people walk: the next frame is close, the fortieth is further away
    # The endless walk goes back and forth, never jumping.
    assert camera.frame(39) == camera.people[39]
    assert camera.frame(40) == camera.people[38]
    assert camera.frame(78) == camera.people[0]
    assert camera.frame(79) == camera.people[1]


def test_cameras_are_different_scenes() -> None:
    _body, cameras = walking_cameras(3, seed=0, frames=2, fps=6.0, people=5)
    focal_lengths = {round(camera.scene.fx, 3) for camera in cameras}
    heights = {round(camera.scene.rho, 3) for camera in cameras}
    assert len(focal_lengths) == 3 and len(heights) == 3


def test_http_client_keeps_its_connection_and_reports_a_closed_one() -> None:
    seen: list[tuple[str, str, bytes]] = []

    def handler(method: str, path: str, headers: dict[str, str], body: bytes) -> tuple[int, bytes]:
        seen.append((method, path, body))
        assert headers["authorization"] == "Bearer t0ken"
        return (404, b"") if path == "/missing" else (200, b"echo:" + body)

    async def main() -> None:
        server = await serve(handler)
        port = server.sockets[0].getsockname()[1]
        connection = Connection("127.0.0.1", port, token="t0ken")
        first = await connection.request("POST", "/a", b'{"x":1}')
        protocol = connection._protocol
        second = await connection.request("GET", "/missing")
        assert connection._protocol is protocol  # the same keep-alive connection
        assert (first.status, first.body, second.status) == (200, b'echo:{"x":1}', 404)
        server.close()
        await server.wait_closed()
        connection.close()
        with pytest.raises((HttpError, OSError)):
            await connection.request("GET", "/a")  # nobody listens any more

    asyncio.run(main())
    assert seen == [("POST", "/a", b'{"x":1}'), ("GET", "/missing", b"")]


def test_kind_stats_count_every_non_success_as_an_error() -> None:
    stats = KindStats(expected=202)
    stats.record(0.0, 0.01, 202)
    stats.record(0.5, 0.02, 503)
    stats.record_failure(0.0, 30.0, "timeout")
    stats.skipped = 4
    assert (stats.sent, stats.ok, stats.errors) == (3, 1, 6)
    assert stats.error_summary() == "503 x1, timeout x1, skipped x4"
    assert stats.end_to_end_s() == [0.01, 0.52, 30.0]


def test_calibration_watch_dates_each_due_episode_between_polls_and_pairs_it_with_its_solve() -> None:
    """Evidence crosses the target (evidence + people needed) between polls: the due time is interpolated; the
    solve is the first stored at or after it; an episode open at the end counts as never solved."""
    watch = CalibrationWatch()
    for wall_s, evidence, needed in ((100.0, 80, 20), (102.0, 120, 0), (104.0, 160, 80), (106.0, 240, 0)):
        body = json.dumps({"evidence_count": evidence, "people_needed": needed}).encode()
        watch.record("cam", wall_s, body)
    watch.record("late", 90.0, json.dumps({"evidence_count": 50, "people_needed": 0}).encode())  # due before
    assert watch.due_times("cam") == [(100.0, 101.0), (104.0, 106.0)]
    fresh = watch.freshness({"cam": [103.5], "late": [100.5]}, window=(100.0, 110.0), end_s=120.0)
    assert fresh.solved_s == [2.5, 10.5] and fresh.unsolved_waited_s == [14.0] and fresh.solves_in_window == 2
    # A solve between the last poll that saw the camera not due and the interpolated due time is that episode's
    # (evidence came in a burst just after the poll), counted from that poll; the episode is not left unsolved.
    early = watch.freshness({"cam": [100.6, 104.5], "late": []}, window=(100.0, 110.0), end_s=120.0)
    assert early.solved_s == pytest.approx([0.6, 0.5]) and early.unsolved_waited_s == [30.0]


def test_metrics_deltas_by_label() -> None:
    before = parse_metrics('# TYPE c counter\nc_total{queue="frames"} 3\nc_total{queue="pose"} 1\n')
    after = parse_metrics(
        '# TYPE c counter\nc_total{queue="frames"} 10\nc_total{queue="pose"} 1\nc_total{queue="new"} 2\n'
    )
    assert delta_by(before, after, "c_total", "queue") == {"frames": 7.0, "pose": 0.0, "new": 2.0}


def test_profile_summary_reads_py_spy_raw_stacks(tmp_path: Path) -> None:
    raw = tmp_path / "API-1.txt"
    site = "/venv/lib/python3.11/site-packages"
    raw.write_text(
        f"<module> (service/cli.py:10);_store_keypoints (service/routers/frames.py:90);"
        f"execute ({site}/sqlalchemy/orm/session.py:5) 6\n"
        f"<module> (service/cli.py:10);_store_keypoints (service/routers/frames.py:91) 2\n"
        f"<module> (service/cli.py:10);loads (json/__init__.py:346) 2\n"
    )
    summary = ProfileSummary()
    summary.add_file(raw)
    assert summary.samples == 10
    assert summary.self_by_area == {"sqlalchemy": 6, "service.routers.frames": 2, "json": 2}
    assert summary.inclusive_own["service.routers.frames._store_keypoints"] == 8
    assert summary.share(summary.inclusive_own["service.cli.<module>"]) == 100.0


def test_bench_load_runs_end_to_end_and_prints_its_tables(tmp_path: Path) -> None:
    """A few seconds of tiny mixed load on a real `posemetry serve`: every part runs and is reported."""
    models = require_dir(model_dir_path(), "pose-model")
    frames = require_dir(TOWN_CENTRE / "frames", "Town Centre frames")
    markdown = tmp_path / "load.md"
    # Short cameras' frames (seed 3 x 20 people = 60) are enough for a first calibration.
    arguments = ["bench", "load", "--seconds", "3", "--warmup", "1", "--cameras", "2", "--fps", "3"]
    arguments += ["--image-cameras", "1", "--image-fps", "0.5", "--seed-images", "1", "--dashboards", "1"]
    arguments += [
        "--calibration-polls",
        "2",
        "--distance-queries",
        "2",
        "--follow-every",
        "2",
        "--webhook-cameras",
        "1",
    ]
    arguments += ["--drain", "5", "--max-warmup", "60", "--model-dir", str(models), "--images-dir", str(frames)]
    result = CliRunner().invoke(app, [*arguments, "--markdown", str(markdown)])
    assert result.exit_code == 0, result.output
    output = result.output
    for text in (
        "posemetry load benchmark",
        "load average",
        "Requests in the 3 s window",
        "Queue lag",
        "POST to done",
        "calibration, due to solved",
        "CPU by process",
        "load client",
        "webhooks:",
        "targets: keypoint frames accepted",
    ):
        assert text in output, text
    row = re.search(r"POST keypoints\s*│\s*(\d+)\s*│\s*([\d.]+)", output)
    assert row is not None, output
    assert int(row.group(1)) > 0 and float(row.group(2)) > 0
    for kind in ("POST image", "GET calibration", "POST distances", "GET /metrics"):
        assert kind in output, kind
    written = markdown.read_text()
    assert written.startswith("# Load benchmark")
    assert "| request | sent | ok/s |" in written
