"""Where the server's CPU goes under load: py-spy samples each API and worker process during the measured window
(`posemetry bench load --profile DIR`), and the collapsed stacks are summarised per role.

py-spy is an optional tool (`pip install py-spy`), not a dependency: it attaches from outside with ptrace, so the
processes under test run unmodified. It samples without pausing them (`--nonblocking`); its own CPU is reported
apart from the roles'. The raw files stay in DIR for flame graphs.

Only the thread holding the GIL is sampled (`--gil`). py-spy's default, every thread that is not idle, counts a
thread that has been woken but waits for a core as busy; on a loaded two-core machine that put a third of the
API's samples in `socket.recv`, `Condition.wait` and the event loop's `select`. The price: native code that
releases the GIL (SQLite executing a statement, onnxruntime) is not in the profile; the difference between the
process's CPU time and its GIL time (both reported) is that share.
"""

from __future__ import annotations

import re
import resource
import shutil
import subprocess
import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import psutil

SAMPLE_RATE_HZ = 50
_FRAME = re.compile(r"^(?P<function>.*) \((?P<file>[^()]*?)(?::\d+)?\)$")
# Packages whose frames are shown by module below the package, so the service's own code splits by area.
_OWN = ("service", "workers")


def py_spy() -> str | None:
    """The py-spy executable: on PATH, or beside this Python (a virtual environment's bin)."""
    beside = Path(sys.executable).with_name("py-spy")
    return str(beside) if beside.exists() else shutil.which("py-spy")


@dataclass
class Recording:
    role: str
    pid: int
    path: Path
    process: subprocess.Popen[bytes]


@dataclass
class Profiler:
    """One `py-spy record` per process, all started together for `seconds`."""

    directory: Path
    recordings: list[Recording] = field(default_factory=list)
    cpu_s: float = 0.0  # py-spy's own CPU, once finished
    _children_before_s: float = 0.0

    def start(self, roles: dict[str, list[psutil.Process]], seconds: float) -> None:
        executable = py_spy()
        if executable is None:
            raise RuntimeError("py-spy is not installed: `pip install py-spy` into this environment")
        self.directory.mkdir(parents=True, exist_ok=True)
        self._children_before_s = _children_cpu_s()
        for role, processes in roles.items():
            for process in processes:
                if "python" not in process.name():
                    continue  # redis-server
                path = self.directory / f"{role}-{process.pid}.txt"
                command = [executable, "record", "--pid", str(process.pid), "--duration", str(max(round(seconds), 1))]
                command += ["--rate", str(SAMPLE_RATE_HZ), "--format", "raw", "--output", str(path), "--nonblocking"]
                command.append("--gil")
                popen = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                self.recordings.append(Recording(role, process.pid, path, popen))

    def finish(self, timeout_s: float = 60.0) -> dict[str, ProfileSummary]:
        """Wait for the recordings and summarise them per role (roles with no readable file are left out)."""
        for recording in self.recordings:
            try:
                recording.process.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                recording.process.kill()
                recording.process.wait()
        # Only the py-spy processes are children this process has waited for since `start` (serve is reaped last).
        self.cpu_s = _children_cpu_s() - self._children_before_s
        summaries: dict[str, ProfileSummary] = {}
        for recording in self.recordings:
            if recording.path.exists():
                summaries.setdefault(recording.role, ProfileSummary()).add_file(recording.path)
        return summaries


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _area(file: str) -> str:
    """What a frame's file belongs to: a package (sqlalchemy, pydantic, ...), the service's module
    (service.frames.repository), or a standard-library module."""
    parts = [part for part in file.replace("\\", "/").split("/") if part]
    if "site-packages" in parts:
        parts = parts[parts.index("site-packages") + 1 :]
    for own in _OWN:
        if own in parts:
            module = parts[parts.index(own) :]
            return ".".join(module)[: -len(".py")] if module[-1].endswith(".py") else ".".join(module)
    if not parts:
        return "?"
    head = parts[0]
    return head[: -len(".py")] if head.endswith(".py") else head


@dataclass
class ProfileSummary:
    """Samples of one role: by the area of the innermost frame (self time) and by own function (inclusive)."""

    samples: int = 0
    self_by_area: Counter[str] = field(default_factory=Counter)
    inclusive_own: Counter[str] = field(default_factory=Counter)
    self_functions: Counter[str] = field(default_factory=Counter)

    def add_file(self, path: Path) -> None:
        for line in path.read_text(errors="replace").splitlines():
            stack, _, count_text = line.rpartition(" ")
            if not stack or not count_text.isdigit():
                continue
            count = int(count_text)
            frames = [_FRAME.match(frame) for frame in stack.split(";")]
            parsed = [(m["function"], m["file"]) for m in frames if m is not None]
            if not parsed:
                continue
            self.samples += count
            function, file = parsed[-1]
            self.self_by_area[_area(file)] += count
            self.self_functions[f"{function} ({_area(file)})"] += count
            seen = set()
            for function, file in parsed:
                area = _area(file)
                if area.startswith(_OWN):
                    name = f"{area}.{function}"
                    if name not in seen:
                        seen.add(name)
                        self.inclusive_own[name] += count

    def share(self, count: int) -> float:
        return 100.0 * count / self.samples if self.samples else 0.0
