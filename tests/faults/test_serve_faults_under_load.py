"""Faults of `posemetry serve` (embedded: SQLite, its own Redis) with several clients posting all through each one.

- SQLite's write lock held by another process for longer than the busy timeout: posts are 503 meanwhile, then
  accepted, each stored once.
- the worker killed in the middle of a measuring run: every frame measured once, violation events not doubled.
- serve's Redis killed: posts are 503 until serve has started it again (empty), each frame stored once. (Last: the
  workers' registrations go with the old Redis, and the test above finds the worker to kill by its registration.)

After each, the rows are counted in SQL (tests/faults/fleet.py), and the recovery time printed.
"""

from __future__ import annotations

import os
import shutil
import signal
import sqlite3
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import redis

from service.embedded_redis import EMBEDDED_DIR_NAME, EMBEDDED_PID_FILE, embedded_socket_path
from tests.faults.fleet import FLEET_FRAMES, Fleet, assert_nothing_lost_or_doubled, posting, sql_counts
from tests.faults.harness import Client, SimulatedCamera, create_camera, kill_worker_running, post_frames, wait_until
from tests.support.serving import Served, clean_environment, serve

BUSY_TIMEOUT_S = 1
CLIENTS = 6
RECOVERY_DEADLINE_S = 90.0


@pytest.fixture(scope="module")
def served() -> Iterator[tuple[Served, Path]]:
    data_dir = Path(tempfile.mkdtemp(prefix="pm-load-"))  # short: the embedded Redis's socket lives in it
    env = clean_environment(calibration_min_people=str(10**9), database_busy_timeout_s=str(BUSY_TIMEOUT_S))
    try:
        with serve(data_dir, env, output=data_dir / "serve.log") as app:
            yield app, data_dir
            assert app.stop() == 0
    finally:
        shutil.rmtree(data_dir, ignore_errors=True)


@pytest.fixture
def client(served: tuple[Served, Path]) -> Client:
    return Client(served[0].base, served[0].api_key or "")


def database_url(data_dir: Path) -> str:
    return f"sqlite:///{data_dir / 'posemetry.sqlite3'}"


def calibrated(client: Client, camera_id: str, seed: int) -> SimulatedCamera:
    camera = SimulatedCamera.draw(camera_id, frames=FLEET_FRAMES, people_per_frame=6, seed=seed)
    create_camera(client, camera)
    urls = post_frames(client, camera, 5)
    assert client.request("POST", f"/v1/cameras/{camera_id}/calibration").status == 202
    wait_until(lambda: all(client.get(url)["status"] == "done" for url in urls), f"{camera_id} calibrated")
    return camera


def all_measured(data_dir: Path, camera_ids: list[str]) -> bool:
    return all(set(sql_counts(database_url(data_dir), c).statuses) == {"done"} for c in camera_ids)


def test_sqlite_locked_past_the_busy_timeout_with_clients_posting(served: tuple[Served, Path], client: Client) -> None:
    _, data_dir = served
    cameras = [calibrated(client, "dock", seed=9), calibrated(client, "quay", seed=10)]
    with posting(Fleet(client, cameras, CLIENTS)) as fleet:
        time.sleep(0.5)
        blocker = sqlite3.connect(data_dir / "posemetry.sqlite3", isolation_level=None, timeout=30)
        try:
            blocker.execute("BEGIN IMMEDIATE")
            locked_at = time.monotonic()
            time.sleep(2.5 * BUSY_TIMEOUT_S)
        finally:
            blocker.execute("ROLLBACK")
            blocker.close()
        released_at = time.monotonic()
        time.sleep(1.0)
    last_post = time.monotonic()
    print(f"\nSQLite locked for {released_at - locked_at:.1f} s: {fleet.summary()}")
    statuses = fleet.statuses()
    assert set(statuses) <= {200, 202, 503} and statuses[503] >= CLIENTS, statuses
    assert set(fleet.problems()) == {"database-unavailable"}
    accepted_again = fleet.first_accepted_after(released_at)
    wait_until(lambda: all_measured(data_dir, ["dock", "quay"]), "every frame measured", timeout_s=RECOVERY_DEADLINE_S)
    measured = time.monotonic() - last_post
    for camera in cameras:
        assert_nothing_lost_or_doubled(fleet, sql_counts(database_url(data_dir), camera.camera_id), camera.camera_id)
    print(f"recovery: accepted again {accepted_again:.1f} s after the lock went; all measured {measured:.1f} s after")


def test_worker_killed_mid_measuring_with_clients_posting(served: tuple[Served, Path], client: Client) -> None:
    _, data_dir = served
    cameras = [calibrated(client, "hall", seed=11), calibrated(client, "lane", seed=12)]
    connection = redis.Redis(unix_socket_path=str(embedded_socket_path(data_dir)))
    try:
        with posting(Fleet(client, cameras, CLIENTS)) as fleet:
            time.sleep(0.5)
            _, pid, killed_at = kill_worker_running(connection, "frames")
            time.sleep(1.0)
        last_post = time.monotonic()
    finally:
        connection.close()
    print(f"\nworker {pid} killed mid-measuring: {fleet.summary()}")
    assert set(fleet.statuses()) <= {200, 202}, fleet.statuses()
    wait_until(lambda: all_measured(data_dir, ["hall", "lane"]), "every frame measured", timeout_s=RECOVERY_DEADLINE_S)
    measured = time.monotonic()
    for camera in cameras:
        assert_nothing_lost_or_doubled(fleet, sql_counts(database_url(data_dir), camera.camera_id), camera.camera_id)
    print(
        f"recovery: every frame measured {measured - killed_at:.1f} s after the kill ({measured - last_post:.1f} s "
        "after the last post)"
    )


def test_serves_redis_killed_with_clients_posting(served: tuple[Served, Path], client: Client) -> None:
    _, data_dir = served
    cameras = [calibrated(client, "gate", seed=7), calibrated(client, "yard", seed=8)]
    pid_file = data_dir / EMBEDDED_DIR_NAME / EMBEDDED_PID_FILE
    redis_pid = int(pid_file.read_text())
    connection = redis.Redis(unix_socket_path=str(embedded_socket_path(data_dir)))
    with posting(Fleet(client, cameras, CLIENTS)) as fleet:
        time.sleep(0.5)
        os.kill(redis_pid, signal.SIGKILL)
        killed_at = time.monotonic()
        wait_until(lambda: _answers(connection), "serve to start its Redis again", poll_s=0.01)
        back_at = time.monotonic()
        time.sleep(1.0)
    last_post = time.monotonic()
    connection.close()
    print(f"\nserve's Redis killed, back {back_at - killed_at:.1f} s later: {fleet.summary()}")
    assert int(pid_file.read_text()) != redis_pid
    assert set(fleet.statuses()) <= {200, 202, 503}, fleet.statuses()
    assert set(fleet.problems()) <= {"queue-unavailable"}
    wait_until(lambda: all_measured(data_dir, ["gate", "yard"]), "every frame measured", timeout_s=RECOVERY_DEADLINE_S)
    measured = time.monotonic() - last_post
    for camera in cameras:
        assert_nothing_lost_or_doubled(fleet, sql_counts(database_url(data_dir), camera.camera_id), camera.camera_id)
    print(
        f"recovery: frames accepted {fleet.first_accepted_after(back_at):.1f} s after Redis was back; all measured "
        f"{measured:.1f} s after the last post"
    )


def _answers(connection: redis.Redis) -> bool:
    try:
        return bool(connection.ping())
    except (redis.ConnectionError, redis.TimeoutError, OSError):
        return False
