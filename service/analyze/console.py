"""What the user sees while `posemetry analyze` runs: a progress bar per stage, notes, and a closing summary.

Progress goes to stderr (so a piped stdout holds only the summary) and draws live bars only on a terminal; the
summary is a rich table of what was analysed, what the calibration rests on, the camera with its 1-sigma
uncertainties, the violations and where the time went.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    SpinnerColumn,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from .analysis import Analysis, Stage
from .errors import AnalyzeError
from .options import AnalyzeOptions
from .run import run_analysis

# Piped output is not cut at 80 columns (the summary's paths and figures would wrap mid-cell).
_PIPED_WIDTH = 160
_DESCRIPTIONS: dict[Stage, str] = {
    "pose": "pose",
    "guided": "guided pose",
    "calibration": "calibrating",
    "results": "measuring",
}
_TIMED: dict[str, str] = {
    "pose": "pose",
    "guided": "guided pose",
    "calibration": "calibration",
    "results": "measuring and writing",
}


class ProgressObserver:
    """A rich progress bar per stage with a running count of people; use as a context manager."""

    def __init__(self, console: Console) -> None:
        self.console = console
        self.progress = Progress(
            SpinnerColumn(),
            TextColumn("[bold]{task.description:<12}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[people]} people"),
            TimeElapsedColumn(),
            TextColumn("eta"),
            TimeRemainingColumn(),
            console=console,
            transient=False,
        )
        self.task: TaskID | None = None
        self.people = 0

    def __enter__(self) -> ProgressObserver:
        return self

    def __exit__(self, *exc: object) -> None:
        self._finish()
        self.progress.stop()

    def _finish(self) -> None:
        if self.task is not None:
            task = self.progress.tasks[self.task]
            # The planned total of a video is the container's estimate: close the bar at what was done.
            self.progress.update(self.task, total=task.completed)
            self.progress.stop_task(self.task)

    def begin(self, stage: Stage, total: int | None) -> None:
        # Started with the first stage, so an error in the input shows as its one line and nothing else.
        self.progress.start()
        self._finish()
        self.people = 0
        self.task = self.progress.add_task(_DESCRIPTIONS[stage], total=total, people=0)

    def advance(self, people: int = 0) -> None:
        if self.task is not None:
            self.people += people
            self.progress.update(self.task, advance=1, people=self.people)

    def note(self, message: str) -> None:
        self.progress.console.print(f"[yellow]note:[/yellow] {message}", highlight=False)


def _pm(value: float | None, std: float | None, fmt: str, unit: str) -> str:
    if value is None:
        return "-"
    text = format(value, fmt)
    if std is not None and math.isfinite(std):
        text += f" ± {format(std, fmt)}"
    return f"{text} {unit}".rstrip()


def _seconds(value: float) -> str:
    return f"{value:.1f} s" if value < 120 else f"{int(value // 60)} min {value % 60:.0f} s"


def summary_table(analysis: Analysis, out_dir: Path, total_s: float) -> Table:
    """The closing summary (see the module docstring)."""
    table = Table(title="posemetry analyze", show_header=False, title_justify="left", box=None, padding=(0, 2))
    table.add_column(style="bold")
    table.add_column()
    source = analysis.source
    frames = len(analysis.frames)
    stride = f", stride {source.stride}" if source.stride > 1 else ""
    skipped = f", {len(analysis.skipped)} skipped" if analysis.skipped else ""
    table.add_row("source", f"{source.path} ({source.kind}, {source.image_size_px[0]}x{source.image_size_px[1]})")
    table.add_row("frames", f"{frames} analysed{stride}{skipped}")
    table.add_row("pose model", analysis.pose_model)
    seen = analysis.people_seen
    usable = len(analysis.evidence)
    table.add_row("people", f"{seen} seen ({seen / max(frames, 1):.1f} per frame), {usable} usable as evidence")
    reasons = analysis.unusable_reasons()
    if reasons:
        table.add_row("not usable", "; ".join(f"{count} {reason}" for reason, count in list(reasons.items())[:3]))
    cal = analysis.calibration
    solve = analysis.solve
    if cal is None:
        table.add_row("calibration", f"[red]failed[/red]: {solve.error or 'no usable people'}")
    else:
        unc = cal.uncertainty
        table.add_row("evidence", f"{solve.people_used} used (repeats collapsed), {cal.num_inliers} inliers")
        if analysis.options.equal_focal:
            focal = _pm(cal.fx, unc.fx_px if unc else None, ".0f", "px")
        else:
            focal = f"fx {_pm(cal.fx, unc.fx_px if unc else None, '.0f', 'px')}, "
            focal += f"fy {_pm(cal.fy, unc.fy_px if unc else None, '.0f', 'px')}"
        table.add_row("focal length", f"{focal} ({cal.focal_source})")
        centre = f"{cal.cx:.1f}, {cal.cy:.1f} px"
        if unc is not None and cal.principal_point_source != "given":
            centre += f" ± {unc.cx_px:.0f}, {unc.cy_px:.0f} px"
        table.add_row("principal point", f"{centre} ({cal.principal_point_source})")
        normal = ", ".join(f"{v:+.4f}" for v in cal.normal)
        table.add_row("ground normal", f"({normal}) ± {unc.normal_deg:.2f}°" if unc else f"({normal})")
        tilt = math.degrees(math.asin(max(-1.0, min(1.0, -float(cal.normal[2])))))
        table.add_row(
            "camera",
            f"{_pm(cal.camera_height_m, unc.rho_m if unc else None, '.2f', 'm')} above the ground, "
            f"looking {tilt:.1f}° down",
        )
        if cal.lens is not None:
            lens = ", ".join(f"{v:+.4g}" for v in cal.lens.coefficients)
        elif cal.distortion_k != 0:
            lens = f"division model k = {cal.distortion_k:+.4f}"
        else:
            lens = "none found" if analysis.options.distortion else "none assumed"
        table.add_row("lens distortion", f"{lens} ({cal.distortion_source})")
        quality = cal.quality
        if quality is not None:
            grade = {"good": "green", "rough": "yellow", "unreliable": "red"}[quality.grade]
            text = f"[{grade}]{quality.grade}[/{grade}]: a 2 m distance at {quality.typical_range_m:.0f} m "
            text += f"± {quality.distance_2sigma_m:.2f} m (2 sigma)"
            if quality.reasons:
                text += "; " + "; ".join(quality.reasons)
            if quality.advice:
                text += "; would help: " + ", ".join(quality.advice)
            table.add_row("quality", text)
        if unc is not None:
            noise = f"{unc.noise_px:.1f} px"
            if unc.noise_per_length > 0:
                noise += f" + {100 * unc.noise_per_length:.1f} % of a person's size"
            table.add_row("keypoint noise", f"{noise} (reprojection rms {cal.reprojection_rms_px:.1f} px)")
        table.add_row("placed", f"{analysis.people_placed} of {seen} people placed on the ground")
        threshold = analysis.options.threshold
        table.add_row(
            "violations",
            f"{analysis.violations} pairs under {threshold} ({analysis.options.threshold_m:.2f} m) "
            f"in {analysis.frames_with_violations} of {frames} frames",
        )
    for warning in analysis.warnings:
        table.add_row("[yellow]warning[/yellow]", warning)
    times = analysis.times_s
    parts = [f"{label} {_seconds(times[name])}" for name, label in _TIMED.items() if name in times]
    table.add_row("time", f"{_seconds(total_s)} ({', '.join(parts)})")
    if frames:
        pose_s = times.get("pose", 0.0) + times.get("guided", 0.0)
        table.add_row("pose speed", f"{1000 * pose_s / frames:.0f} ms per frame")
    table.add_row("written to", str(out_dir))
    return table


def run_command(path: Path, out_dir: Path, options: AnalyzeOptions, console: Console | None = None) -> int:
    """The command's body: run with progress bars, print the summary; the exit status (1 with a one-line error).

    Options are checked inside the run, so a bad option is reported like bad input: one line, exit status 1.
    """
    import time

    console = console or Console(stderr=True)
    # FFmpeg logs its own complaints ("moov atom not found") to stderr; the error below says it in one line.
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")
    started = time.perf_counter()
    try:
        with ProgressObserver(console) as observer:
            analysis = run_analysis(path, out_dir, options, observer)
    except AnalyzeError as exc:
        console.print(f"[red]error:[/red] {exc}", highlight=False, soft_wrap=True)
        return 1
    except KeyboardInterrupt:
        console.print("[red]interrupted[/red]", highlight=False)
        return 130
    out = Console() if Console().is_terminal else Console(width=_PIPED_WIDTH)
    out.print(summary_table(analysis, out_dir, time.perf_counter() - started))
    return 0
