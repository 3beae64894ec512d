"""Metrics read at scrape time from the shared stores: queue depths from Redis, calibration state per camera
from the database (see service.observability.metrics for why these are not recorded gauges).

Each source costs one round trip per scrape (one Redis pipeline, one SQL query) and never fails the scrape: an
unreachable store drops its families and sets `posemetry_metrics_source_up{source}` to 0, which is what an
alert should watch.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from typing import TYPE_CHECKING

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session, sessionmaker

from service import __version__
from service.dispatch import DispatchUnavailableError
from service.observability.overview import camera_overview

if TYPE_CHECKING:
    from service.observability.queue_depths import QueueDepths

log = logging.getLogger(__name__)


def _gauge(name: str, documentation: str, labels: Sequence[str]) -> GaugeMetricFamily:
    return GaugeMetricFamily(name, documentation, labels=list(labels))


class SharedStateCollector:
    """The scrape-time families: build info, cameras from the database, and queue depths when a queue is given."""

    def __init__(self, read_sessions: sessionmaker[Session], queues: QueueDepths | None = None) -> None:
        self.read_sessions = read_sessions
        self.queues = queues

    def collect(self) -> Iterator[Metric]:
        info = _gauge("posemetry_build_info", "Always 1; the running posemetry version.", ["version"])
        info.add_metric([__version__], 1.0)
        yield info
        up = _gauge(
            "posemetry_metrics_source_up",
            "Whether this scrape could read the source (database, redis); 0: its families are missing.",
            ["source"],
        )
        try:
            yield from self._cameras()
            up.add_metric(["database"], 1.0)
        except SQLAlchemyError as exc:
            log.warning("metrics: cannot read the cameras: %s", exc)
            up.add_metric(["database"], 0.0)
        if self.queues is not None:
            try:
                yield self._queue_jobs(self.queues.read())
                up.add_metric(["redis"], 1.0)
            except DispatchUnavailableError as exc:
                log.warning("metrics: cannot read the queue depths: %s", exc)
                up.add_metric(["redis"], 0.0)
        yield up

    def _cameras(self) -> list[Metric]:
        with self.read_sessions() as session:
            cameras = camera_overview(session)
        calibrated = _gauge(
            "posemetry_camera_calibrated",
            "1 when the camera has a current calibration (distances are reported).",
            ["camera"],
        )
        evidence = _gauge(
            "posemetry_camera_usable_evidence",
            "Usable people stored for the camera (both shoulders and ankles seen): what calibrations solve on.",
            ["camera"],
        )
        version = _gauge(
            "posemetry_camera_calibration_version", "The current calibration's version (0: none).", ["camera"]
        )
        solved_at = _gauge(
            "posemetry_camera_calibration_timestamp_seconds",
            "When the current calibration was solved (Unix time); absent for an uncalibrated camera.",
            ["camera"],
        )
        epoch = _gauge(
            "posemetry_camera_calibration_epoch",
            "The camera's calibration epoch: 1 for a new camera, +1 at every detected move, reset or image resize.",
            ["camera"],
        )
        moves = CounterMetricFamily(
            "posemetry_camera_moves",
            "Moves of the camera (re-aimed, bumped, zoomed) that the movement test found; each opened a new epoch.",
            labels=["camera"],
        )
        for camera in cameras:
            epoch.add_metric([camera.camera_id], float(camera.epoch))
            moves.add_metric([camera.camera_id], float(camera.moves))
            calibrated.add_metric([camera.camera_id], 0.0 if camera.calibration_version is None else 1.0)
            evidence.add_metric([camera.camera_id], float(camera.usable_evidence))
            version.add_metric([camera.camera_id], float(camera.calibration_version or 0))
            if camera.calibrated_at is not None:
                solved_at.add_metric([camera.camera_id], camera.calibrated_at.timestamp())
        return [calibrated, evidence, version, solved_at, epoch, moves]

    @staticmethod
    def _queue_jobs(depths: dict[tuple[str, str], int]) -> Metric:
        family = _gauge(
            "posemetry_queue_jobs",
            "Jobs per queue and state (queued, started, failed, scheduled), from Redis.",
            ["queue", "state"],
        )
        for (queue, state), count in depths.items():
            family.add_metric([queue, state], float(count))
        return family
