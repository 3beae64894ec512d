"""Prometheus metrics: every family posemetry exports, and how the values of many processes reach one scrape.

Two kinds of values:

- Recorded as things happen (HTTP requests, frames ingested, jobs, pose inference, webhook deliveries): the
  metric objects below, written by whichever process does the work.
- Read at scrape time (queue depths from Redis, calibration state per camera from the database, in
  service.observability.collectors): state that already lives in a shared store, read by the API process that
  answers the scrape, with one round trip each. Recording those as gauges in every process would show stale,
  per-process copies of one global truth.

**Processes.** `posemetry serve` runs several API processes and several workers on one host, and Prometheus
scrapes one of the API processes, which must answer for all of them. That is prometheus-client's multiprocess
mode: with `PROMETHEUS_MULTIPROC_DIR` set before the library is imported, every process writes its values to
memory-mapped files in that directory, and /metrics merges the files of all processes (counters and histograms
summed, including those of processes that have exited, so totals never go backwards; in-progress gauges summed
over live processes only). `serve` and `api --processes N` own the directory: they clear it when they start and
mark dead processes (service.observability.multiprocess). The cost is a write into a shared page per update,
no locks between processes and no network.

Workers on other machines (Docker Compose, one container per worker) share no directory. There a worker serves
its own metrics on a port (`posemetry worker --metrics-port`, setting `worker_metrics_port`) and Prometheus
scrapes each worker as its own target; the API still exports the shared queue and camera state. Pushing to a
Pushgateway was rejected: it keeps the last value of workers that are gone and is meant for batch jobs.

A forking worker (`--fork`) runs each job in a fresh child process. With one set of files per pid that would
leave a set per job, so a worker's job processes (never more than one at a time) share one extra set named
after the worker (`<pid>-horse`), through prometheus-client's `process_identifier` hook.

**Cardinality.** Labels take bounded values only: route templates, never raw paths; status classes; queue
names; job outcomes; sources; pose model names. Per-camera values exist only in the scrape-time gauges, which
vanish with the camera.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from typing import Literal

from prometheus_client import (
    REGISTRY,
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    disable_created_metrics,
    start_http_server,
    values,
)
from prometheus_client.multiprocess import MultiProcessCollector
from prometheus_client.registry import Collector

from service.observability.multiprocess import HORSE_SUFFIX, multiprocess_dir

_fork_parent: int | None = None


def _process_identifier() -> str:
    """This process's file name part: its pid, or `<worker pid>-horse` in a forking worker's job process."""
    pid = os.getpid()
    if _fork_parent is not None and pid != _fork_parent:
        return f"{_fork_parent}{HORSE_SUFFIX}"
    return str(pid)


def share_files_with_forked_jobs() -> None:
    """Called by a forking worker before it forks: its job processes then write to one shared set of files."""
    global _fork_parent
    _fork_parent = os.getpid()


if multiprocess_dir() is not None:
    values.ValueClass = values.MultiProcessValue(_process_identifier)
# `_created` series double the series count for a start time Prometheus does not use (multiprocess mode has none).
disable_created_metrics()

# --------------------------------------------------------------------------------------------------- HTTP

HTTP_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0)
HTTP_REQUEST_DURATION = Histogram(
    "posemetry_http_request_duration_seconds",
    "Time from a request's arrival to its last response byte, by route template, method and status class.",
    ["method", "route", "status_class"],
    buckets=HTTP_BUCKETS_S,
)
HTTP_REQUESTS_IN_PROGRESS = Gauge(
    "posemetry_http_requests_in_progress",
    "Requests being served now, over all API processes.",
    multiprocess_mode="livesum",
)

# --------------------------------------------------------------------------------------------------- frames

FRAME_SOURCES = ("keypoints", "image")
FRAMES_INGESTED = Counter(
    "posemetry_frames_ingested",
    "Frames stored by the API (retries of a stored frame not counted), by source: posted keypoints or an image.",
    ["source"],
)

# --------------------------------------------------------------------------------------------------- jobs

JOB_BUCKETS_S = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0)
JOB_DURATION = Histogram(
    "posemetry_job_duration_seconds",
    "Wall time of each job as its worker ran it, by queue (the job kind) and outcome: succeeded, failed (raised, "
    "timed out or its process died), retried (failed, queued again) or stopped.",
    ["queue", "outcome"],
    buckets=JOB_BUCKETS_S,
)
JOB_FAILURES = Counter(
    "posemetry_job_failures",
    "Job runs that failed (raised, timed out or lost their process), retried ones included, by queue.",
    ["queue"],
)
JOBS_IN_PROGRESS = Gauge(
    "posemetry_jobs_in_progress",
    "Jobs being run now, over all live workers, by queue.",
    ["queue"],
    multiprocess_mode="livesum",
)

# --------------------------------------------------------------------------------------------------- pose

POSE_BUCKETS_S = (0.025, 0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0)
POSE_INFERENCE = Histogram(
    "posemetry_pose_inference_seconds",
    "Pose inference time per image frame (person detector and pose model on every person), by pose model.",
    ["model"],
    buckets=POSE_BUCKETS_S,
)

# --------------------------------------------------------------------------------------------------- webhooks

WebhookOutcome = Literal["delivered", "retrying", "failed", "blocked"]
WEBHOOK_OUTCOMES: tuple[WebhookOutcome, ...] = ("delivered", "retrying", "failed", "blocked")
WEBHOOK_DELIVERIES = Counter(
    "posemetry_webhook_deliveries",
    "Webhook delivery attempts by outcome: delivered (2xx), retrying (failed, another attempt is scheduled), "
    "failed (gave up after the last attempt) or blocked (the URL broke the outbound policy).",
    ["outcome"],
)

# Label values known in advance start at zero, so a dashboard shows 0 rather than no data.
for _source in FRAME_SOURCES:
    FRAMES_INGESTED.labels(source=_source)
for _outcome in WEBHOOK_OUTCOMES:
    WEBHOOK_DELIVERIES.labels(outcome=_outcome)


def record_webhook_delivery(outcome: WebhookOutcome) -> None:
    """Count one webhook delivery attempt; the webhook job calls this once per attempt.

    `outcome` must be one of WEBHOOK_OUTCOMES: an open set of label values would make the family unbounded.
    """
    if outcome not in WEBHOOK_OUTCOMES:
        raise ValueError(f"webhook outcome must be one of {', '.join(WEBHOOK_OUTCOMES)}, got {outcome!r}")
    WEBHOOK_DELIVERIES.labels(outcome=outcome).inc()


# --------------------------------------------------------------------------------------------------- exposition


def exposition_registry(collectors: Iterable[Collector] = ()) -> CollectorRegistry:
    """What a scrape returns: every process's recorded values, plus `collectors` read at scrape time.

    In multiprocess mode the values come from the shared directory (this process's included); otherwise from
    this process's default registry, which also carries the Python process and GC metrics.
    """
    registry = CollectorRegistry(auto_describe=False)
    path = multiprocess_dir()
    if path is not None:
        MultiProcessCollector(registry, path=str(path))
    else:
        registry.register(REGISTRY)  # a registry is a collector of everything registered in it
    for collector in collectors:
        registry.register(collector)
    return registry


def start_metrics_server(port: int, host: str) -> None:
    """Serve this process's metrics on http://host:port/ in a daemon thread (a worker on its own machine)."""
    start_http_server(port, addr=host, registry=exposition_registry())
