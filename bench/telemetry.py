"""What the request telemetry middleware costs per request, in CPU time.

The ingest target (≥ 300 keypoint frames/s on 2 cores) leaves about 6 ms of CPU per frame for everything, so the
middleware must cost a small fraction of that. It is timed in isolation: the same minimal ASGI endpoint called
directly, with and without `RequestTelemetry` around it, alternating in rounds so load from other processes hits
both alike; the figure is the difference of the per-round minima of CPU time (time.process_time), which a noisy
shared machine inflates least. Three configurations: metrics only (access log below its level), metrics plus the
JSON access line (to /dev/null), and the same with prometheus-client's multiprocess mode (mmap-backed values, as
under `posemetry serve`), which runs in a child process because the mode is fixed at import.
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass

from starlette.routing import Route
from starlette.types import Message, Receive, Scope, Send

_ROUTE = Route("/v1/cameras/{camera_id}/keypoints", endpoint=lambda request: None, methods=["POST"])


async def _endpoint(scope: Scope, receive: Receive, send: Send) -> None:
    """A stand-in for the app: reads the body, answers 202, and marks the route as the router would."""
    scope["route"] = _ROUTE
    scope["path_params"] = {"camera_id": "cam-1"}
    await receive()
    await send({"type": "http.response.start", "status": 202, "headers": [(b"content-type", b"application/json")]})
    await send({"type": "http.response.body", "body": b"{}"})


def _scope() -> Scope:
    return {
        "type": "http",
        "method": "POST",
        "path": "/v1/cameras/cam-1/keypoints",
        "headers": [(b"content-type", b"application/json"), (b"x-request-id", b"bench-request-1")],
    }


async def _receive() -> Message:
    return {"type": "http.request", "body": b"{}", "more_body": False}


async def _send(_message: Message) -> None:
    return None


def _cpu_s_per_request(app: Callable, requests: int) -> float:
    async def run() -> None:
        for _ in range(requests):
            await app(_scope(), _receive, _send)

    started = time.process_time()
    asyncio.run(run())
    return (time.process_time() - started) / requests


@dataclass(frozen=True)
class TelemetryCost:
    """Extra CPU per request (µs) of the middleware, by configuration."""

    bare_us: float
    metrics_us: float
    metrics_and_log_us: float


def measure(requests: int, rounds: int) -> TelemetryCost:
    """Time the bare endpoint and the middleware in this process's metrics mode (see the module docstring)."""
    from service.observability.http import RequestTelemetry
    from service.observability.logs import configure_logging

    with open(os.devnull, "w") as null:
        configure_logging("json", "warning", stream=null)
        wrapped = RequestTelemetry(_endpoint, route_templates=lambda: [_ROUTE.path])
        bare, metrics, logged = [], [], []
        for _ in range(rounds):
            bare.append(_cpu_s_per_request(_endpoint, requests))
            logging.getLogger().setLevel(logging.WARNING)
            metrics.append(_cpu_s_per_request(wrapped, requests))
            logging.getLogger().setLevel(logging.INFO)
            logged.append(_cpu_s_per_request(wrapped, requests))
        logging.getLogger().handlers.clear()
    base = min(bare)
    return TelemetryCost(base * 1e6, (min(metrics) - base) * 1e6, (min(logged) - base) * 1e6)


def measure_multiprocess(requests: int, rounds: int) -> TelemetryCost:
    """`measure` in a child process with PROMETHEUS_MULTIPROC_DIR set (the mode `posemetry serve` runs in)."""
    with tempfile.TemporaryDirectory(prefix="posemetry-bench-metrics-") as directory:
        env = {**os.environ, "PROMETHEUS_MULTIPROC_DIR": directory}
        command = [sys.executable, "-m", "bench.telemetry", str(requests), str(rounds)]
        output = subprocess.run(command, env=env, check=True, capture_output=True, text=True).stdout
    return TelemetryCost(**json.loads(output))


def telemetry_lines(requests: int, rounds: int) -> list[str]:
    in_memory = measure(requests, rounds)
    shared = measure_multiprocess(requests, rounds)
    lines = [
        f"request telemetry middleware: CPU per request, min of {rounds} rounds of {requests} requests "
        f"(bare endpoint: {in_memory.bare_us:.1f} µs)",
        f"  {'metrics values':<34} {'metrics only':>13} {'metrics + JSON access line':>27}",
    ]
    for name, cost in (("in memory (one process)", in_memory), ("multiprocess files (serve)", shared)):
        lines.append(f"  {name:<34} {cost.metrics_us:10.1f} µs {cost.metrics_and_log_us:24.1f} µs")
    return lines


if __name__ == "__main__":
    cost = measure(int(sys.argv[1]), int(sys.argv[2]))
    print(json.dumps(cost.__dict__))
