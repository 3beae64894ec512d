"""How fast the movement detector notices a camera that moved, and how rarely it cries wolf (`posemetry bench
movement`).

Every run is a camera in bench.moving_camera's world: people walk, the camera is calibrated from the first minutes
of them exactly as the service does (service.geometry.evidence.solve_evidence on the pooled people), and then every
frame's people go through the detector (service.calibration.movement) in the batches a measuring job would hand it.
A move changes the camera's pose at a known frame; the delay is counted from there to the alarm, in frames and in
seconds of frame time, and the change point the test estimates is compared with the truth. Static runs count false
alarms over hours of frame time, with the crowd's outliers (people sitting, children), a school class passing as
one group, sparse and dense streets, noisier keypoints, higher frame rates, and a calibration that is slightly off.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from bench.moving_camera import CameraPose, Crowd, CrowdConfig
from service.calibration.movement import (
    THRESHOLD,
    FrameEvidence,
    MovementMonitor,
    ReferenceCamera,
    frames_evidence,
)
from service.geometry import DEFAULT_HEIGHT_STD_M, Calibration, CalibrationProblem
from service.geometry.evidence import solve_evidence

STREET = CrowdConfig(people=36, region_m=(-20.0, 20.0, 2.0, 36.0))
SPARSE = replace(STREET, people=14)
CALIBRATION_FRAMES = 240
"""Frames (2 minutes at 2 fps) whose people calibrate the camera before the detector starts."""
CHUNK = 50
"""Frames per measuring-job batch (service.frames.service.FRAMES_CHUNK)."""


@dataclass(frozen=True)
class Group:
    """A school class: `count` children walking together through the view from `start_s` for `duration_s`."""

    start_s: float
    duration_s: float
    count: int = 15
    heights_m: tuple[float, float] = (0.65, 0.95)


@dataclass(frozen=True)
class Scenario:
    name: str
    crowd: CrowdConfig = STREET
    camera: CameraPose = field(default_factory=CameraPose)
    move: Callable[[CameraPose], CameraPose] | None = None
    move_at_s: float = 300.0
    duration_s: float = 420.0
    fps: float = 2.0
    batch: int = 1
    """Frames per detector update: 1 is a camera measured as it posts; CHUNK a backlog."""
    groups: tuple[Group, ...] = ()
    group_every_s: float | None = None


@dataclass(frozen=True)
class Outcome:
    scenario: str
    seed: int
    frames: int
    alarms: list[tuple[int, int]]
    """(frame of the alarm, estimated change-point frame) for every alarm."""
    max_statistic: float
    calibration: Calibration
    cpu_s: float


def _groups(scenario: Scenario) -> list[Group]:
    if scenario.group_every_s is None:
        return list(scenario.groups)
    starts = np.arange(scenario.group_every_s, scenario.duration_s, scenario.group_every_s)
    return [Group(float(start), 60.0) for start in starts]


def _frames(scenario: Scenario, seed: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """(tops, bottoms) per frame of the whole run."""
    rng = np.random.default_rng(seed)
    crowd = Crowd(scenario.crowd, rng)
    dt = 1.0 / scenario.fps
    frames = round(scenario.duration_s * scenario.fps)
    move_frame = round(scenario.move_at_s * scenario.fps) if scenario.move is not None else frames + 1
    moved = scenario.move(scenario.camera) if scenario.move is not None else scenario.camera
    groups = _groups(scenario)
    events = sorted(
        [(round(g.start_s * scenario.fps), "in", k) for k, g in enumerate(groups)]
        + [(round((g.start_s + g.duration_s) * scenario.fps), "out", k) for k, g in enumerate(groups)],
        key=lambda e: e[0],
    )
    active: dict[int, np.ndarray] = {}
    tops, bottoms = [], []
    for k in range(frames):
        while events and events[0][0] == k:
            _, kind, which = events.pop(0)
            group = groups[which]
            if kind == "in":
                camera = scenario.camera if k < move_frame else moved
                centre = camera.ground_point_at((camera.image_size[0] * 0.3, camera.image_size[1] * 0.8))
                active[which] = crowd.add_group(group.count, (centre[0], centre[1]), group.heights_m)
            else:
                crowd.remove(active.pop(which))
                # Indices after the removed group shift down; groups never overlap in these runs.
        t, b, _ = crowd.seen_by(scenario.camera if k < move_frame else moved)
        tops.append(t)
        bottoms.append(b)
        crowd.step(dt)
    return tops, bottoms


def reference_camera(cal: Calibration) -> ReferenceCamera:
    noise = cal.uncertainty.noise_px if cal.uncertainty is not None else 1.0
    return ReferenceCamera(
        cal.fx,
        cal.fy,
        cal.cx,
        cal.cy,
        tuple(cal.normal),
        noise,
        DEFAULT_HEIGHT_STD_M / cal.height_m,
        log_height=float(np.log(cal.height_m / cal.rho)),
    )


def run(scenario: Scenario, seed: int) -> Outcome:
    """Calibrate on the first CALIBRATION_FRAMES, then detect on every later frame (restarting after an alarm)."""
    tops, bottoms = _frames(scenario, seed)
    pooled_t = np.vstack(tops[:CALIBRATION_FRAMES])
    pooled_b = np.vstack(bottoms[:CALIBRATION_FRAMES])
    dt = 1.0 / scenario.fps
    # Frame times, as the calibration worker passes them: one walker's observations are one individual.
    times_s = np.concatenate([np.full(len(t), k * dt) for k, t in enumerate(tops[:CALIBRATION_FRAMES])])
    problem = CalibrationProblem(scenario.camera.image_size, scenario.crowd.height_m)
    solve = solve_evidence(pooled_t, pooled_b, problem, cap=2000, times_s=times_s)
    if solve.calibration is None:
        raise RuntimeError(f"{scenario.name}: the calibration failed: {solve.error}")
    cal = solve.calibration
    camera = reference_camera(cal)
    started = time.process_time()
    monitor = MovementMonitor.start(camera)
    alarms: list[tuple[int, int]] = []
    max_statistic = 0.0
    for start in range(CALIBRATION_FRAMES, len(tops), CHUNK):
        stop = min(start + CHUNK, len(tops))
        index = np.concatenate([np.full(len(tops[k]), k - start) for k in range(start, stop)])
        evidence = frames_evidence(
            camera, np.vstack(tops[start:stop]), np.vstack(bottoms[start:stop]), index, stop - start
        )
        for first in range(0, stop - start, scenario.batch):
            batch: list[FrameEvidence] = evidence[first : first + scenario.batch]
            ks = range(start + first, start + first + len(batch))
            alarm = monitor.observe(batch, [k.to_bytes(8, "big") for k in ks], [k * dt for k in ks])
            max_statistic = max(max_statistic, monitor.last_statistic)
            if alarm is not None:
                alarms.append((ks[-1], int.from_bytes(alarm.frame_id, "big")))
                monitor = MovementMonitor.start(camera)
    return Outcome(scenario.name, seed, len(tops), alarms, max_statistic, cal, time.process_time() - started)


__all__ = ["THRESHOLD", "Outcome", "Scenario", "run"]


MOVES: dict[str, Callable[[CameraPose], CameraPose]] = {
    "pan 10 + tilt 7": lambda c: c.panned(10.0).tilted(7.0),
    "zoom x1.2": lambda c: c.zoomed(1.2),
    "tilt 2 (nudge)": lambda c: c.tilted(2.0),
    "tilt 1 (nudge)": lambda c: c.tilted(1.0),
    "roll 2 (nudge)": lambda c: c.rolled(2.0),
    "pan 10 alone": lambda c: c.panned(10.0),
}


def movement_lines(seeds: int, static_s: float, move_at_s: float) -> list[str]:
    """The report of `posemetry bench movement`: every move over `seeds` streets, then static runs."""
    lines = [
        f"threshold {THRESHOLD:g}; {CALIBRATION_FRAMES} frames calibrate each camera; the test starts after them; "
        f"moves at {move_at_s:g} s; 2 fps",
        "",
        f"{'move':<18} {'crowd':<7} {'found':>6} {'delay frames (median, max)':>27} {'delay s (max)':>14} "
        f"{'change point - move, frames (min..max)':>40}",
    ]
    for name, move in MOVES.items():
        for crowd_name, crowd in (("street", STREET), ("sparse", SPARSE)):
            scenario = Scenario(name, crowd=crowd, move=move, move_at_s=move_at_s, duration_s=move_at_s + 60.0)
            move_frame = round(move_at_s * scenario.fps)
            delays, errors = [], []
            for seed in range(seeds):
                outcome = run(scenario, seed)
                after = [(a, c) for a, c in outcome.alarms if a >= move_frame - 1]
                if after:
                    delays.append(after[0][0] - move_frame)
                    errors.append(after[0][1] - move_frame)
            found = f"{len(delays)}/{seeds}"
            delay = f"{np.median(delays):.0f}, {max(delays)}" if delays else "-"
            seconds = f"{max(delays) / scenario.fps:.1f}" if delays else "-"
            error = f"{min(errors)}..{max(errors)}" if errors else "-"
            lines.append(f"{name:<18} {crowd_name:<7} {found:>6} {delay:>27} {seconds:>14} {error:>40}")
    lines += ["", f"static cameras, {static_s / 60:.0f} min of frame time each (a school class of 15 every 10 min):"]
    for crowd_name, crowd in (("street", STREET), ("sparse", SPARSE)):
        alarms, peak, cpu = 0, 0.0, 0.0
        for seed in range(seeds):
            outcome = run(Scenario("static", crowd=crowd, duration_s=static_s, group_every_s=600.0), 1000 + seed)
            alarms += len(outcome.alarms)
            peak = max(peak, outcome.max_statistic)
            cpu += outcome.cpu_s
        hours = seeds * (static_s - CALIBRATION_FRAMES / 2.0) / 3600.0
        lines.append(
            f"  {crowd_name:<7} {seeds} runs, {hours:.1f} h tested: {alarms} false moves, highest statistic "
            f"{peak:.1f} (threshold {THRESHOLD:g}); detector CPU {1000 * cpu / (hours * 7200):.2f} ms per frame"
        )
    return lines
