"""What the load benchmark records while it runs: per request kind (latencies, statuses, how late requests left),
frames followed to `done`, the workers' backlog over time, and CPU time per process role.

Plain data and cheap recording (an append per request); percentiles are computed once, at the end.
"""

from __future__ import annotations

import math
import os
import resource
from collections import Counter
from dataclasses import dataclass, field

import numpy as np
import psutil

CLIENT = "load client"
OTHER = "other processes"


def percentile_ms(values_s: list[float], q: float) -> float:
    return float(np.percentile(values_s, q) * 1000.0) if values_s else math.nan


@dataclass
class KindStats:
    """One request kind (POST keypoints, GET calibration, ...) inside the measured window."""

    expected: int  # the status that counts as success
    latencies_s: list[float] = field(default_factory=list)  # send to last response byte
    send_lag_s: list[float] = field(default_factory=list)  # schedule to send (the client's own queueing)
    statuses: Counter[int] = field(default_factory=Counter)
    failures: Counter[str] = field(default_factory=Counter)  # no response: timeouts, refused, reset
    skipped: int = 0  # never sent: the client was too far behind its schedule (see LoadRun._every)

    def record(self, lag_s: float, latency_s: float, status: int) -> None:
        self.send_lag_s.append(lag_s)
        self.latencies_s.append(latency_s)
        self.statuses[status] += 1

    def record_failure(self, lag_s: float, latency_s: float, reason: str) -> None:
        self.send_lag_s.append(lag_s)
        self.latencies_s.append(latency_s)
        self.failures[reason] += 1

    @property
    def sent(self) -> int:
        return len(self.latencies_s)

    @property
    def ok(self) -> int:
        return self.statuses[self.expected]

    @property
    def errors(self) -> int:
        return self.sent - self.ok + self.skipped

    def error_summary(self) -> str:
        parts = [f"{status} x{n}" for status, n in sorted(self.statuses.items()) if status != self.expected]
        parts += [f"{reason} x{n}" for reason, n in sorted(self.failures.items())]
        parts += [f"skipped x{self.skipped}"] if self.skipped else []
        return ", ".join(parts) or "0"

    def end_to_end_s(self) -> list[float]:
        """Schedule to response: what the camera (or dashboard) waited, its own backlog included."""
        return [lag + latency for lag, latency in zip(self.send_lag_s, self.latencies_s, strict=True)]


@dataclass
class BacklogSample:
    """Frames the workers have not answered yet, read from the database at `t_s` (seconds from window start)."""

    t_s: float
    pending: int  # keypoints stored (or people found), waiting to be measured
    detecting: int  # images waiting for (or in) pose inference
    oldest_age_s: float  # age of the oldest frame still pending or detecting (0 when none)


@dataclass
class Followed:
    """Frames followed from POST to `done` (one keypoint frame in N, every image frame)."""

    done_s: list[float] = field(default_factory=list)  # client send time to the server's processed_at
    unfinished: int = 0  # still not done when the benchmark gave up waiting
    failed: int = 0  # ended `failed`


@dataclass
class CpuSnapshot:
    """Cumulative CPU seconds (user + system) per process, and the whole machine's busy time."""

    by_pid: dict[int, tuple[str, float]]
    client_s: float
    machine_busy_s: float

    @classmethod
    def take(cls, roles: dict[str, list[psutil.Process]]) -> CpuSnapshot:
        by_pid: dict[int, tuple[str, float]] = {}
        for role, processes in roles.items():
            for process in processes:
                try:
                    times = process.cpu_times()
                except psutil.Error:
                    continue
                by_pid[process.pid] = (role, times.user + times.system)
        usage = resource.getrusage(resource.RUSAGE_SELF)
        machine = psutil.cpu_times()
        busy = machine.user + machine.nice + machine.system + machine.irq + machine.softirq + machine.steal
        return cls(by_pid, usage.ru_utime + usage.ru_stime, busy)


def cpu_split(start: CpuSnapshot, end: CpuSnapshot) -> dict[str, float]:
    """CPU seconds per role between two snapshots, plus this process (the load client) and every other process on
    the machine (other benchmarks, other users: the noise in the wall-clock figures). A process that started in
    between counts whole; one that ended in between is lost (the benchmark says when workers restarted)."""
    split: Counter[str] = Counter()
    for pid, (role, seconds) in end.by_pid.items():
        before = start.by_pid.get(pid)
        split[role] += seconds - (before[1] if before is not None and before[0] == role else 0.0)
    split[CLIENT] = end.client_s - start.client_s
    ours = sum(split.values())
    split[OTHER] = max(end.machine_busy_s - start.machine_busy_s - ours, 0.0)
    return dict(split)


def load_average() -> tuple[float, float, float]:
    return os.getloadavg()
