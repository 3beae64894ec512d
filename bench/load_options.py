"""What `posemetry bench load` runs and what it reports: the load's options, the kinds of request, the deployment
under test (`Target`) and the figures of a run (`LoadResult`); bench.load runs it, bench.load_report prints it."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

from .http_client import HttpError
from .load_calibration import Freshness
from .load_stats import BacklogSample, Followed, KindStats
from .profile import ProfileSummary
from .server import Server, free_port

TARGET_FRAMES_PER_S = 300.0
TARGET_P99_MS = 100.0

POST_KEYPOINTS = "POST keypoints"
POST_IMAGE = "POST image"
GET_CALIBRATION = "GET calibration"
POST_DISTANCES = "POST distances"
GET_FRAME = "GET frame"
GET_METRICS = "GET /metrics"
KINDS = (POST_KEYPOINTS, POST_IMAGE, GET_CALIBRATION, POST_DISTANCES, GET_FRAME, GET_METRICS)
EXPECTED_STATUS = {POST_KEYPOINTS: 202, POST_IMAGE: 202}

IMAGE_SIZE_PX = (1920, 1080)  # the Town Centre frames
BACKLOG_EVERY_S = 1.0
MAX_SEND_LAG_S = 1.0
LOOP_PROBE_S = 0.01
WEBHOOK_PATH = "/hook"
LOOPBACK = "127.0.0.0/8"
TRANSPORT_ERRORS = (HttpError, OSError, TimeoutError)


# The longest interval between two polls of a followed frame (the interval doubles from follow_poll_s).
FOLLOW_MAX_POLL_S = 4.0


@dataclass(frozen=True)
class LoadOptions:
    seconds: float = 60.0
    warmup_s: float = 10.0
    max_warmup_s: float = 120.0  # the warm-up also waits (up to this) for every camera's first calibration
    drain_s: float = 60.0  # after the window, how long to wait for the workers to catch up
    keypoint_cameras: int = 50
    keypoint_fps: float = 6.0
    people: int = 20
    payload: str = "coco17"
    frames_per_camera: int = 120  # distinct simulated frames per camera, walked forwards and back
    seed_frames: int = 3  # posted per keypoint camera before the load, for a first calibration (0: cold start)
    seed_images: int = 6  # the same per image camera
    image_cameras: int = 3
    image_fps: float = 0.2
    dashboards: int = 5
    calibration_polls_per_s: float = 25.0
    distance_queries_per_s: float = 10.0
    follow_every: int = 20  # one keypoint frame in N is followed to `done` (every image frame is)
    follow_poll_s: float = 0.25  # a followed frame's first poll, and the longest wait for a new one to be seen
    metrics_every_s: float = 5.0
    webhook_cameras: int = 2
    workers: int = 1
    api_processes: int = 2  # `posemetry serve`'s split on 2 CPUs (the CLI passes its default for this machine)
    database_url: str | None = None
    url: str | None = None  # an already running deployment instead of a `posemetry serve` of our own
    admin_key: str | None = None
    model_dir: Path | None = None
    images_dir: Path | None = None
    profile_dir: Path | None = None
    seed: int = 0

    @property
    def offered_frames_per_s(self) -> float:
        return self.keypoint_cameras * self.keypoint_fps


@dataclass
class WebhookCounts:
    received: int = 0
    by_type: dict[str, int] = field(default_factory=dict)
    bad_signature: int = 0
    duplicates: int = 0
    alert_s: list[float] = field(default_factory=list)  # violation.detected: frame POST to delivery, in window


@dataclass
class LoadResult:
    options: LoadOptions
    target: str
    window_s: float
    warmup_s: float
    calibrated_at_start: int
    kinds: dict[str, KindStats]
    keypoints_done: Followed
    images_done: Followed
    backlog: list[BacklogSample]
    caught_up_after_s: float | None  # None: still behind when the drain ended
    queue_depths: list[tuple[float, dict[str, float]]]  # (t_s, {queue: queued jobs})
    jobs: dict[str, tuple[int, float]]  # queue -> (jobs finished in the window, their wall seconds)
    webhook_outcomes: dict[str, float]  # delivery attempts in the window by outcome (the service's counter)
    cpu_s: dict[str, float]
    load_before: tuple[float, float, float]
    load_after: tuple[float, float, float]
    webhooks: WebhookCounts | None
    profiles: dict[str, ProfileSummary] = field(default_factory=dict)
    profiler_cpu_s: float = 0.0
    client_loop_lag_s: list[float] = field(default_factory=list)  # the client's event loop: how late it woke
    worker_restarts: int = 0
    freshness: Freshness | None = None
    notes: list[str] = field(default_factory=list)


# --------------------------------------------------------------------------------------------------- target


@dataclass
class Target:
    """Where the load goes: host and port, keys, and (for a server of our own) its processes and database."""

    host: str
    port: int
    admin_key: str
    server: Server | None = None
    database_url: str | None = None
    token: str = ""


def _default_shared(*parts: str) -> Path:
    return Path(__file__).resolve().parents[1].parent.joinpath("shared", *parts)


def default_model_dir() -> Path:
    """POSEMETRY_MODEL_DIR if set, else the checkout's sibling `../shared/models` where it exists."""
    from service.settings import get_settings

    if os.environ.get("POSEMETRY_MODEL_DIR"):
        return Path(get_settings().model_dir).expanduser()
    shared = _default_shared("models")
    return shared if shared.is_dir() else Path(get_settings().model_dir).expanduser()


def default_images_dir() -> Path:
    return _default_shared("data", "oxford_town_centre", "frames")


def read_images(options: LoadOptions) -> list[bytes]:
    if options.image_cameras == 0:
        return []
    directory = options.images_dir or default_images_dir()
    files = sorted(directory.glob("*.jpg"))
    if not files:
        raise RuntimeError(f"no JPEG frames in {directory} (--images-dir, or --image-cameras 0)")
    return [path.read_bytes() for path in files]


def check_models(options: LoadOptions) -> Path:
    from service.pose.model_files import resolve_choice
    from service.settings import get_settings

    model_dir = options.model_dir or default_model_dir()
    resolve_choice(model_dir, get_settings().pose_model)  # ModelFilesError names every missing or bad file
    return model_dir


def target_for(options: LoadOptions, data_dir: Path, model_dir: Path | None) -> Target:
    """The deployment under load: the one at --url, or a `posemetry serve` to start in `data_dir`."""
    if options.url is not None:
        parts = urlsplit(options.url)
        if parts.scheme != "http" or parts.hostname is None:
            raise ValueError(f"--url must be http://HOST:PORT, got {options.url!r}")
        if not options.admin_key:
            raise ValueError("--url needs an admin key (--admin-key or POSEMETRY_ADMIN_KEY)")
        return Target(parts.hostname, parts.port or 80, options.admin_key, database_url=options.database_url)
    settings = {}
    if options.database_url:
        settings["database_url"] = options.database_url
    if model_dir is not None:
        settings["model_dir"] = str(model_dir)
    if options.webhook_cameras:
        settings["webhook_allowed_networks"] = LOOPBACK
    server = Server(data_dir, free_port(), options.workers, options.api_processes, settings)
    from service.settings import DEFAULT_DATABASE_FILE

    database_url = options.database_url or f"sqlite:///{data_dir / DEFAULT_DATABASE_FILE}"
    return Target("127.0.0.1", server.port, server.admin_key, server=server, database_url=database_url)
