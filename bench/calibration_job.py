"""Calibration-job timing against stored evidence: `python -m bench.calibration_job` (run by `posemetry bench ingest`).

It times the real job, `workers.jobs.calibrate_camera`, so it imports the workers package, which the service never
does: `posemetry bench ingest` runs this module as a process and passes its output through.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from bench.ingest import PEOPLE_PER_FRAME
from workers import jobs

if TYPE_CHECKING:
    from sqlalchemy import Engine

TARGET_CALIBRATION_S = 1.0
TARGET_CALIBRATION_AT = 1_000_000
INSERT_BATCH = 20_000

Progress = Callable[[str], None]


@dataclass
class CalibrationTiming:
    observations: int
    insert_s: float
    key_s: float
    job_s: list[float]
    sample_s: list[float]
    solve_s: list[float]
    outcome: str
    people_used: int
    fx_px: float | None
    fx_true_px: float

    @staticmethod
    def median(values: Sequence[float]) -> float:
        return float(np.median(values)) if values else float("nan")


def _insert_evidence(engine: Engine, camera_id: str, observations: int, seed: int) -> float:
    """Write `observations` usable people (20 per frame) straight through the Core tables, unkeyed as the API
    stores them; returns fx truth."""
    from sqlalchemy import insert, update
    from sqlalchemy.orm import Session

    from bench.simulate import SceneConfig, draw_scene
    from service.cameras.repository import upsert_camera as _upsert
    from service.geometry.evidence import grid_cells
    from service.store import Camera, Frame, Observation

    rng = np.random.default_rng(seed)
    # One camera; its people are drawn in chunks (draw_scene needs them all visible), so a scene is redrawn with
    # the camera held fixed by drawing once and re-using its pixels with fresh noise.
    config = SceneConfig.surveillance(n_people=min(observations, 20_000))
    scene = draw_scene(config, rng)
    width, height = scene.image_size
    with Session(engine) as session, session.begin():
        _upsert(session, camera_id, image_width_px=width, image_height_px=height, person_height_m=config.height_mean_m)
    frames_table, observations_table = Frame.__table__, Observation.__table__
    now = datetime.now(UTC)
    written = 0
    with engine.begin() as connection:
        while written < observations:
            n = min(INSERT_BATCH, observations - written)
            pick = rng.integers(0, len(scene.tops_px), n)
            tops = scene.tops_px[pick] + rng.normal(0.0, config.noise_px, (n, 2))
            bottoms = scene.bottoms_px[pick] + rng.normal(0.0, config.noise_px, (n, 2))
            cells = grid_cells(bottoms, (width, height)).tolist()
            frame_rows, rows = [], []
            for start in range(0, n, PEOPLE_PER_FRAME):
                frame_id = uuid.uuid4()
                count = min(PEOPLE_PER_FRAME, n - start)
                frame_rows.append(
                    {
                        "id": frame_id,
                        "camera_id": camera_id,
                        "timestamp": now,
                        "received_at": now,
                        "source": "keypoints",
                        "status": "done",
                        "people": count,
                    }
                )
                for index in range(count):
                    (sx, sy), (ax, ay) = tops[start + index].tolist(), bottoms[start + index].tolist()
                    rows.append(
                        {
                            "camera_id": camera_id,
                            "frame_id": frame_id,
                            "person_index": index,
                            "shoulder_x_px": sx,
                            "shoulder_y_px": sy,
                            "ankle_x_px": ax,
                            "ankle_y_px": ay,
                            "keypoints_f32": None,
                            "usable": True,
                            "unusable_reason": None,
                            "cell": cells[start + index],
                            "sample_key": None,
                        }
                    )
            connection.execute(insert(frames_table), frame_rows)
            connection.execute(insert(observations_table), rows)
            written += n
        connection.execute(
            update(Camera.__table__).where(Camera.id == camera_id).values(usable_evidence_count=observations)
        )
    return float(scene.fx)


def run_calibration(sizes: Sequence[int], *, repeats: int, seed: int, progress: Progress) -> list[CalibrationTiming]:
    """For each size: a fresh SQLite database with that many observations, then `calibrate_camera` timed."""
    from sqlalchemy.orm import Session

    from service.calibration.evidence import sample_evidence
    from service.calibration.repository import current_calibration
    from service.calibration.service import key_camera_evidence
    from service.embedded_redis import EmbeddedRedis
    from service.settings import get_settings
    from service.store import make_engine, sessions
    from service.store.migrate import upgrade

    timings = []
    saved_env = {key: value for key, value in os.environ.items() if key.startswith("POSEMETRY_")}
    with tempfile.TemporaryDirectory(prefix="posemetry-bench-") as tmp:
        data_dir = Path(tmp)
        redis = EmbeddedRedis(data_dir).start()
        try:
            jobs.preload()
            for size in sizes:
                url = f"sqlite:///{data_dir / f'calibration-{size}.sqlite3'}"
                for key in saved_env:
                    os.environ.pop(key, None)
                os.environ.update(
                    POSEMETRY_DATA_DIR=str(data_dir), POSEMETRY_DATABASE_URL=url, POSEMETRY_REDIS_URL=redis.url
                )
                get_settings.cache_clear()
                settings = get_settings()
                upgrade(url, "head", script_location=settings.migrations_dir)
                engine = make_engine(url)
                camera_id = f"bench-{size}"
                progress(f"calibration: inserting {size:,} observations")
                started = time.perf_counter()
                fx_true = _insert_evidence(engine, camera_id, size, seed)
                insert_s = time.perf_counter() - started
                # What the first solve of a store this size would do first: key the whole backlog.
                started = time.perf_counter()
                key_camera_evidence(settings, camera_id)
                key_s = time.perf_counter() - started
                job_s, sample_s, solve_s = [], [], []
                outcome = ""
                for _ in range(repeats):
                    started = time.perf_counter()
                    outcome = jobs.calibrate_camera(camera_id, forced=True)
                    job_s.append(time.perf_counter() - started)
                    with Session(engine) as session:
                        started = time.perf_counter()
                        sample = sample_evidence(session, camera_id, cap=settings.calibration_sample_cap)
                        sample_s.append(time.perf_counter() - started)
                        current = current_calibration(session, camera_id)
                    if current is not None and current.duration_s is not None:
                        solve_s.append(float(current.duration_s))
                progress(f"calibration: {size:,} observations, job {np.median(job_s):.3f} s ({outcome})")
                timings.append(
                    CalibrationTiming(
                        size,
                        insert_s,
                        key_s,
                        job_s,
                        sample_s,
                        solve_s,
                        outcome,
                        len(sample),
                        None if current is None else current.fx_px,
                        fx_true,
                    )
                )
                sessions.dispose_engines()
                engine.dispose()
        finally:
            redis.stop()
            for key in [key for key in os.environ if key.startswith("POSEMETRY_")]:
                del os.environ[key]
            os.environ.update(saved_env)
            get_settings.cache_clear()
    return timings


def calibration_lines(timings: Sequence[CalibrationTiming], cap: int) -> list[str]:
    lines = [
        f"calibration job (workers.jobs.calibrate_camera, forced; sample cap {cap}; SQLite), median of runs:",
        f"  {'stored':>10}  {'insert':>8}  {'key':>8}  {'job':>8}  {'sample':>8}  {'solve':>8}  {'people':>6}  "
        f"{'fx/fx_true':>10}  outcome",
    ]
    for t in timings:
        ratio = f"{t.fx_px / t.fx_true_px:10.3f}" if t.fx_px else f"{'-':>10}"
        lines.append(
            f"  {t.observations:>10,}  {t.insert_s:7.1f}s  {t.key_s:7.1f}s  {t.median(t.job_s):7.3f}s  "
            f"{t.median(t.sample_s):7.3f}s  "
            f"{t.median(t.solve_s):7.3f}s  {t.people_used:>6}  {ratio}  {t.outcome}"
        )
    at_target = [t for t in timings if t.observations >= TARGET_CALIBRATION_AT]
    if at_target:
        ok = all(t.median(t.job_s) <= TARGET_CALIBRATION_S for t in at_target)
        lines.append(f"  -> {_verdict(ok)} (<= {TARGET_CALIBRATION_S:g} s at {TARGET_CALIBRATION_AT:,})")
    else:
        lines.append(f"  target: <= {TARGET_CALIBRATION_S:g} s at {TARGET_CALIBRATION_AT:,} (run with --big)")
    return lines


def _verdict(ok: bool) -> str:
    return "meets target" if ok else "MISSES target"


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1_000, 100_000], help="stored observations")
    parser.add_argument("--repeats", type=int, default=3, help="jobs timed per size")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    from service.settings import get_settings

    timings = run_calibration(
        args.sizes, repeats=args.repeats, seed=args.seed, progress=lambda m: print(m, file=sys.stderr, flush=True)
    )
    print("\n".join(calibration_lines(timings, get_settings().calibration_sample_cap)), flush=True)


if __name__ == "__main__":
    main()
