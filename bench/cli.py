"""`posemetry bench`: the benchmarks as commands, beside the product (the service never imports bench).

The group is registered with the `posemetry` command through the `posemetry.commands` entry point (pyproject.toml),
so `pip install -e .` puts `posemetry bench ...` on the command line. Heavy imports happen inside the commands, so
`posemetry --help` stays fast.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.console import Console

from service.runtime import SPLIT_HELP, default_process_split

if TYPE_CHECKING:
    from bench.report import ReportTable

bench_app = typer.Typer(help="Benchmarks: accuracy against the paper's protocol, and speed.", no_args_is_help=True)

QUICK_TRIALS = 50
DEFAULT_TRIALS = 1000
_PIPED_WIDTH = 220


def print_report(
    title: str, header: Sequence[str], tables: Sequence[ReportTable], footer: Sequence[str], markdown: Path | None
) -> None:
    """A benchmark's header lines, tables and footer lines on stdout, and optionally as a Markdown file."""
    from bench.report import markdown_document, to_rich

    console = Console()
    if not console.is_terminal:
        # Piped or captured output would otherwise be cut at 80 columns and truncate the tables' cells.
        console = Console(width=_PIPED_WIDTH)
    console.print(f"posemetry {title[0].lower()}{title[1:]}", style="bold")
    for line in header:
        console.print(line, highlight=False)
    for table in tables:
        console.print()
        console.print(to_rich(table))
    if footer:
        console.print()
    for line in footer:
        console.print(line, highlight=False)
    if markdown is not None:
        markdown.parent.mkdir(parents=True, exist_ok=True)
        markdown.write_text(markdown_document(title, [*header, *footer], tables))
        console.print(f"\nwrote {markdown}", highlight=False)


@bench_app.command("geometry")
def bench_geometry(
    trials: int | None = typer.Option(
        None, min=1, help=f"Monte Carlo trials per setting (default {DEFAULT_TRIALS}; {QUICK_TRIALS} with --quick)."
    ),
    seed: int = typer.Option(0, min=0, help="Root seed; every scene derives from it, so runs are reproducible."),
    workers: int = typer.Option(2, min=1, help="Processes for the accuracy experiments (timing runs in one)."),
    quick: bool = typer.Option(False, "--quick", help=f"Smoke run: {QUICK_TRIALS} trials per setting."),
    only: str | None = typer.Option(
        None,
        help="Comma-separated experiments: noise-free, table1, table2, table3, outliers, distance, "
        "surveillance, distortion, realistic, timing (default: all).",
    ),
    repeats: int = typer.Option(50, min=1, help="Timed calls per timing case."),
    markdown: Path | None = typer.Option(None, help="Also write the tables as Markdown to this file."),
) -> None:
    """Accuracy of calibrate() on simulated scenes (paper Sect. 4.1, Tables 1-3) and its speed."""
    from bench.geometry import BenchmarkOptions, parse_only, run_benchmark

    try:
        selected = parse_only(only)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--only") from None
    options = BenchmarkOptions(
        trials=trials if trials is not None else (QUICK_TRIALS if quick else DEFAULT_TRIALS),
        seed=seed,
        workers=workers,
        only=selected,
        repeats=repeats,
    )
    log = Console(stderr=True)
    report = run_benchmark(options, progress=lambda message: log.print(f"[dim]{message}[/dim]", highlight=False))
    print_report("Geometry benchmark", report.header, report.tables, [], markdown)
    if report.unexpected_errors:
        for line in report.unexpected_errors:
            log.print(f"[red]unexpected exception[/red] {line}", highlight=False)
        raise typer.Exit(1)


@bench_app.command("ingest")
def bench_ingest(
    seconds: float = typer.Option(20.0, min=1.0, help="Measured ingest time."),
    concurrency: int = typer.Option(16, min=1, help="Client threads posting frames, each on its own connection."),
    cameras: int = typer.Option(4, min=1, help="Cameras the frames are spread over."),
    workers: int | None = typer.Option(
        None, min=1, help="Worker processes of the `posemetry serve` under test. " + SPLIT_HELP
    ),
    api_processes: int | None = typer.Option(
        None, min=1, help="API processes of the `posemetry serve` under test. " + SPLIT_HELP
    ),
    payload: str = typer.Option("coco17", help="Person format: coco17 (17 keypoints) or centres (shoulder/ankle)."),
    warmup: float = typer.Option(2.0, min=0.0, help="Unmeasured ingest before the measured run, in seconds."),
    big: bool = typer.Option(False, "--big", help="Also time the calibration job at 10^6 stored observations."),
    skip_ingest: bool = typer.Option(False, "--skip-ingest", help="Only the calibration-job timings."),
    skip_calibration: bool = typer.Option(False, "--skip-calibration", help="Only the ingest figures."),
    repeats: int = typer.Option(3, min=1, help="Calibration jobs timed per evidence size."),
    seed: int = typer.Option(0, min=0, help="Seed of the simulated scenes."),
) -> None:
    """Keypoint-frame ingest throughput and latency of `posemetry serve`, and calibration-job time vs evidence."""
    from bench.ingest import PAYLOADS, ingest_lines, run_ingest

    default_api, default_workers = default_process_split()
    workers, api_processes = workers or default_workers, api_processes or default_api

    if payload not in PAYLOADS:
        raise typer.BadParameter(f"choose from {', '.join(PAYLOADS)}", param_hint="--payload")
    log = Console(stderr=True)

    def progress(message: str) -> None:
        log.print(f"[dim]{message}[/dim]", highlight=False)

    typer.echo(f"posemetry ingest benchmark ({os.cpu_count()} CPUs, Python {sys.version.split()[0]})")
    if not skip_ingest:
        result = run_ingest(
            seconds=seconds,
            concurrency=concurrency,
            cameras=cameras,
            workers=workers,
            api_processes=api_processes,
            payload=payload,
            seed=seed,
            warmup_s=warmup,
            progress=progress,
        )
        typer.echo(
            "\n".join(
                ingest_lines(
                    result,
                    concurrency=concurrency,
                    cameras=cameras,
                    workers=workers,
                    api_processes=api_processes,
                    payload=payload,
                )
            )
        )
    if not skip_calibration:
        # The job under test belongs to the workers package, which the service never imports: run it as a process.
        sizes = ["1000", "100000"] + (["1000000"] if big else [])
        command = [sys.executable, "-m", "bench.calibration_job", "--sizes", *sizes, "--repeats", str(repeats)]
        code = subprocess.run([*command, "--seed", str(seed)], check=False).returncode
        if code:
            raise typer.Exit(code)


@bench_app.command("load")
def bench_load(
    seconds: float = typer.Option(60.0, min=1.0, help="Measured window, after the warm-up."),
    warmup: float = typer.Option(10.0, min=0.0, help="Least warm-up, in seconds; it also waits for calibrations."),
    cameras: int = typer.Option(50, min=1, help="Cameras posting keypoint frames, each its own simulated scene."),
    fps: float = typer.Option(6.0, min=0.01, help="Keypoint frames per second per camera (open loop)."),
    people: int = typer.Option(20, min=1, help="Walking people per camera (all in every frame)."),
    payload: str = typer.Option("coco17", help="Person format: coco17 (17 keypoints) or centres (shoulder/ankle)."),
    image_cameras: int = typer.Option(3, min=0, help="Cameras posting Town Centre JPEGs (0: no pose work)."),
    image_fps: float = typer.Option(0.2, min=0.01, help="JPEGs per second per image camera."),
    dashboards: int = typer.Option(5, min=1, help="Dashboards polling calibration status (one connection each)."),
    calibration_polls: float = typer.Option(25.0, min=0.0, help="Calibration status polls per second, in all."),
    distance_queries: float = typer.Option(10.0, min=0.0, help="POST .../distances per second."),
    follow_every: int = typer.Option(20, min=1, help="Follow one keypoint frame in N to `done` (GET frame)."),
    webhook_cameras: int = typer.Option(2, min=0, help="Cameras a webhook subscription covers (0: no webhook)."),
    workers: int | None = typer.Option(
        None, min=1, help="Worker processes of the `posemetry serve` under test. " + SPLIT_HELP
    ),
    api_processes: int | None = typer.Option(
        None, min=1, help="API processes of the `posemetry serve` under test. " + SPLIT_HELP
    ),
    database_url: str | None = typer.Option(
        None, help="Serve on this database (e.g. PostgreSQL) instead of SQLite; with --url: read its backlog."
    ),
    url: str | None = typer.Option(None, help="Load an already running deployment (http://HOST:PORT) instead."),
    admin_key: str | None = typer.Option(
        None, envvar="POSEMETRY_ADMIN_KEY", help="Admin key of the --url deployment (POSEMETRY_ADMIN_KEY)."
    ),
    model_dir: Path | None = typer.Option(None, help="Pose models (default: POSEMETRY_MODEL_DIR, else ../shared)."),
    images_dir: Path | None = typer.Option(None, help="JPEG frames (default: the Town Centre frames in ../shared)."),
    seed_frames: int = typer.Option(
        3, min=0, help="Frames each keypoint camera posts before the load, for a first calibration (0: cold start)."
    ),
    seed_images: int = typer.Option(6, min=0, help="The same for each image camera."),
    max_warmup: float = typer.Option(120.0, min=0.0, help="Longest wait for the cameras' first calibrations."),
    drain: float = typer.Option(60.0, min=0.0, help="After the window, wait this long for the workers to catch up."),
    profile: Path | None = typer.Option(None, help="py-spy every API and worker process into this folder."),
    markdown: Path | None = typer.Option(None, help="Also write the tables as Markdown to this file."),
    seed: int = typer.Option(0, min=0, help="Seed of the simulated scenes."),
) -> None:
    """Mixed load on `posemetry serve`: keypoint cameras, image cameras, dashboards, distance queries, webhooks."""
    from bench.frames import PAYLOADS
    from bench.load import run_load
    from bench.load_options import LoadOptions
    from bench.load_report import footer, header, tables

    if payload not in PAYLOADS:
        raise typer.BadParameter(f"choose from {', '.join(PAYLOADS)}", param_hint="--payload")
    default_api, default_workers = default_process_split()
    options = LoadOptions(
        seconds=seconds,
        warmup_s=warmup,
        max_warmup_s=max_warmup,
        seed_frames=seed_frames,
        seed_images=seed_images,
        drain_s=drain,
        keypoint_cameras=cameras,
        keypoint_fps=fps,
        people=people,
        payload=payload,
        image_cameras=image_cameras,
        image_fps=image_fps,
        dashboards=dashboards,
        calibration_polls_per_s=calibration_polls,
        distance_queries_per_s=distance_queries,
        follow_every=follow_every,
        webhook_cameras=min(webhook_cameras, cameras),
        workers=workers or default_workers,
        api_processes=api_processes or default_api,
        database_url=database_url,
        url=url,
        admin_key=admin_key if url else None,
        model_dir=model_dir,
        images_dir=images_dir,
        profile_dir=profile,
        seed=seed,
    )
    log = Console(stderr=True)
    result = run_load(options, progress=lambda message: log.print(f"[dim]{message}[/dim]", highlight=False))
    print_report("Load benchmark", header(result), tables(result), footer(result), markdown)


@bench_app.command("pose")
def bench_pose(
    frames: Path | None = typer.Option(
        None, help="Folder of frames (default: the Oxford Town Centre clip frames in ../shared/data)."
    ),
    models: str = typer.Option("lightning,auto,thunder", help="Pose models to time, comma-separated."),
    plans: str = typer.Option(
        "uncalibrated,later,calibrated",
        help="Detector plans to time, comma-separated: a camera's first frame, its later frames, calibrated.",
    ),
    repeats: int = typer.Option(2, min=1, help="Passes over the frames per configuration."),
    threads: int | None = typer.Option(None, min=1, help="Inference threads (default: every core)."),
    runtimes: str = typer.Option(
        "auto", help="MoveNet runtimes to time, comma-separated: auto, onnxruntime, openvino (pose/sessions.py)."
    ),
    markdown: Path | None = typer.Option(None, help="Also write the report to this Markdown file."),
) -> None:
    """Pose cost per frame: detector / tiling / pose split (CPU and wall), per runtime, pose model and plan."""
    from bench.pose import PLANS, pose_lines, run_pose_benchmark
    from service.pose.model_files import POSE_CHOICES
    from service.settings import get_settings

    settings = get_settings()
    frames_dir = frames or Path(__file__).resolve().parents[1].parent / "shared/data/oxford_town_centre/frames"
    chosen = [name.strip() for name in models.split(",") if name.strip()]
    unknown = sorted(set(chosen) - set(POSE_CHOICES))
    if unknown:
        raise typer.BadParameter(
            f"unknown {', '.join(unknown)}; choose {', '.join(POSE_CHOICES)}", param_hint="--models"
        )
    chosen_plans = [name.strip() for name in plans.split(",") if name.strip()]
    if not chosen_plans or set(chosen_plans) - set(PLANS):
        raise typer.BadParameter(f"choose from {', '.join(PLANS)}", param_hint="--plans")
    chosen_runtimes = [name.strip() for name in runtimes.split(",") if name.strip()]
    if not chosen_runtimes or set(chosen_runtimes) - {"auto", "onnxruntime", "openvino"}:
        raise typer.BadParameter("choose from auto, onnxruntime, openvino", param_hint="--runtimes")
    log = Console(stderr=True)
    result = run_pose_benchmark(
        Path(settings.model_dir).expanduser(),
        frames_dir,
        chosen,  # type: ignore[arg-type]
        repeats,
        lambda message: log.print(f"[dim]{message}[/dim]", highlight=False),
        plans=chosen_plans,
        threads=threads or settings.inference_threads,
        detector_input_px=settings.detector_input_px,
        runtimes=chosen_runtimes,  # type: ignore[arg-type]
    )
    lines = [f"posemetry pose benchmark ({os.cpu_count()} CPUs, Python {sys.version.split()[0]})", *pose_lines(result)]
    typer.echo("\n".join(lines))
    if markdown is not None:
        markdown.write_text("```\n" + "\n".join(lines) + "\n```\n")


@bench_app.command("recall")
def bench_recall(
    policies: str = typer.Option(
        "plain,uncalibrated,later,calibrated", help="Detector policies to compare, comma-separated (bench/recall.py)."
    ),
    atrium_calibration: Path | None = typer.Option(
        None, help="A calibration.json (from `posemetry analyze`) to run the calibrated policy on the atrium too."
    ),
    threads: int | None = typer.Option(None, min=1, help="Inference threads (default: every core)."),
    clip_frames: int | None = typer.Option(
        None,
        min=0,
        help="How many of the Town Centre clip video's other frames (not the 22 JPEG frames) to check too, evenly "
        "spread (default: all 104; 0: none).",
    ),
    markdown: Path | None = typer.Option(None, help="Also write the report to this Markdown file."),
) -> None:
    """Detection recall by person size on Town Centre, and against the atrium annotation, per detector policy."""
    from bench.recall import POLICIES, recall_lines, run_recall_benchmark
    from service.settings import get_settings

    chosen = [name.strip() for name in policies.split(",") if name.strip()]
    unknown = sorted(set(chosen) - set(POLICIES))
    if unknown:
        raise typer.BadParameter(
            f"unknown {', '.join(unknown)}; choose from {', '.join(POLICIES)}", param_hint="--policies"
        )
    shared = Path(__file__).resolve().parents[1].parent / "shared/data"
    log = Console(stderr=True)
    result = run_recall_benchmark(
        Path(get_settings().model_dir).expanduser(),
        shared / "oxford_town_centre",
        shared / "mot3d_atrium/frames",
        Path(__file__).resolve().parents[1] / "tests/pose/data/atrium_annotations.json",
        chosen,
        lambda message: log.print(f"[dim]{message}[/dim]", highlight=False),
        atrium_calibration=atrium_calibration,
        threads=threads or get_settings().inference_threads,
        clip_frames=clip_frames,
    )
    lines = recall_lines(result)
    typer.echo("\n".join(lines))
    if markdown is not None:
        markdown.write_text("```\n" + "\n".join(lines) + "\n```\n")


@bench_app.command("movement")
def bench_movement(
    seeds: int = typer.Option(3, min=1, help="Streets (random seeds) per move and per static crowd."),
    static_minutes: float = typer.Option(50.0, min=5.0, help="Frame time of each static run, minutes."),
    move_at_s: float = typer.Option(300.0, min=150.0, help="When the camera moves, seconds of frame time."),
) -> None:
    """How fast camera moves are found (pan + tilt, zoom, nudges, a pure pan) and how rarely a static camera with
    children, sitting people and school classes raises a false move."""
    from bench.movement import movement_lines

    typer.echo(f"posemetry movement benchmark ({os.cpu_count()} CPUs, Python {sys.version.split()[0]})")
    typer.echo("\n".join(movement_lines(seeds, static_minutes * 60.0, move_at_s)))


@bench_app.command("telemetry")
def bench_telemetry(
    requests: int = typer.Option(20000, min=100, help="Requests per timed round."),
    rounds: int = typer.Option(5, min=1, help="Rounds per configuration (the minimum is reported)."),
) -> None:
    """CPU cost per request of the request-id, metrics and access-log middleware."""
    from bench.telemetry import telemetry_lines

    typer.echo(f"posemetry telemetry benchmark ({os.cpu_count()} CPUs, Python {sys.version.split()[0]})")
    typer.echo("\n".join(telemetry_lines(requests, rounds)))
