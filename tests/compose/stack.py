"""Driving docker-compose.yml as an operator does: the docker CLI, HTTP on the published port, psql and redis-cli in
their containers. Nothing here is mocked; every call reaches the real engine, the real containers and the real API.

Docker is required only where POSEMETRY_TESTS_REQUIRE_DOCKER=1 (set by .ci/run, which installs and starts it):
elsewhere a machine without a usable engine skips the Compose test, saying why.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from email.message import Message
from pathlib import Path
from typing import Any

import pytest

from tests.support.serving import REPO

REQUIRE_DOCKER_ENV = "POSEMETRY_TESTS_REQUIRE_DOCKER"
STANDINS = Path(__file__).resolve().parent / "standins" / "build.sh"
# `docker build --build-context` (BuildKit named contexts) needs Docker 23 or newer.
MIN_ENGINE_MAJOR = 23
DEADLINE_S = 180.0
IMAGE = "posemetry:latest"


def docker_problem() -> str | None:
    """Why Docker cannot run the Compose test here, or None when it can."""
    if shutil.which("docker") is None:
        return "no `docker` client on PATH"
    checks = {
        "the Docker daemon does not answer": ["docker", "info", "--format", "{{.ServerVersion}}"],
        "no Compose v2 plugin (`docker compose`)": ["docker", "compose", "version", "--short"],
        "no buildx plugin (`docker build --build-context` needs BuildKit)": ["docker", "buildx", "version"],
    }
    answers = {}
    for problem, command in checks.items():
        try:
            done = subprocess.run(command, capture_output=True, text=True, timeout=30, check=False)
        except subprocess.TimeoutExpired:
            return f"{problem} (timed out)"
        if done.returncode != 0:
            return f"{problem}: {(done.stderr or done.stdout).strip()[-300:]}"
        answers[problem] = done.stdout.strip()
    engine = answers["the Docker daemon does not answer"]
    major = re.match(r"\d+", engine)
    if major is None or int(major.group()) < MIN_ENGINE_MAJOR:
        return f"Docker engine {engine} is too old: `docker build --build-context` needs {MIN_ENGINE_MAJOR} or newer"
    return None


def require_docker() -> None:
    """Skip (or, where CI requires Docker, fail) when no usable engine runs here."""
    problem = docker_problem()
    if problem is None:
        return
    hint = "tests/compose/setup-docker.sh installs and starts one"
    if os.environ.get(REQUIRE_DOCKER_ENV) == "1":
        pytest.fail(f"Docker required ({REQUIRE_DOCKER_ENV}=1) but unusable: {problem} ({hint})")
    pytest.skip(f"Docker unusable here: {problem} ({hint})")


def run(command: list[str], *, env: dict[str, str] | None = None, timeout_s: float = 600) -> str:
    """Run a command to completion; its stdout, or an assertion error with its output."""
    done = subprocess.run(command, capture_output=True, text=True, env=env, timeout=timeout_s, check=False)
    assert done.returncode == 0, f"{' '.join(command)} exited with {done.returncode}:\n{done.stdout}{done.stderr}"
    return done.stdout


def ensure_base_images() -> str:
    """Images under the names the Dockerfile and the Compose file use (stand-ins where none can be pulled); returns
    the PostgreSQL image to run."""
    out = run([str(STANDINS)], timeout_s=900)
    lines = [line for line in out.splitlines() if line.startswith("POSEMETRY_POSTGRES_IMAGE=")]
    assert len(lines) == 1, out
    return lines[0].split("=", 1)[1]


def build_image(models: Path) -> None:
    """The documented offline build: the model files as the `models` stage, so nothing is downloaded or converted."""
    run(["docker", "build", "--build-context", f"models={models}", "-t", IMAGE, str(REPO)], timeout_s=900)


@dataclass
class Answer:
    status: int
    headers: Message
    body: Any


def http(base_url: str, method: str, path: str, body: object = None, *, key: str | None = None) -> Answer:
    """One request, as a client would send it: JSON for dicts, raw bytes as a JPEG."""
    headers = {}
    data = None
    if isinstance(body, bytes):
        data, headers["content-type"] = body, "image/jpeg"
    elif body is not None:
        data, headers["content-type"] = json.dumps(body).encode(), "application/json"
    if key is not None:
        headers["authorization"] = f"Bearer {key}"
    request = urllib.request.Request(base_url + path, data=data, method=method, headers=headers)
    try:
        with urllib.request.urlopen(request, timeout=30) as response:
            status, answer_headers, raw = response.status, response.headers, response.read()
    except urllib.error.HTTPError as error:
        status, answer_headers, raw = error.code, error.headers, error.read()
    content_type = answer_headers.get("content-type", "")
    return Answer(status, answer_headers, json.loads(raw) if raw and "json" in content_type else raw)


def wait_until(condition: Callable[[], bool], what: str, timeout_s: float = DEADLINE_S, every_s: float = 0.5) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")
        time.sleep(every_s)


@dataclass
class Stack:
    """One Compose project of the repository's docker-compose.yml, isolated from the caller's environment."""

    project: str
    postgres_image: str
    api_port: int

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.api_port}"

    def environment(self) -> dict[str, str]:
        """The test process's environment less POSEMETRY_* and COMPOSE_* (with no .env read either, see `command`):
        only what the test chooses reaches the Compose file."""
        env = {name: value for name, value in os.environ.items() if not name.startswith(("POSEMETRY_", "COMPOSE_"))}
        env["POSEMETRY_POSTGRES_IMAGE"] = self.postgres_image
        env["POSEMETRY_API_PORT"] = str(self.api_port)
        return env

    def command(self, *args: str) -> list[str]:
        return ["docker", "compose", "--project-directory", str(REPO), "--env-file", os.devnull] + [
            "-p",
            self.project,
            *args,
        ]

    def compose(self, *args: str, timeout_s: float = 300) -> str:
        return run(self.command(*args), env=self.environment(), timeout_s=timeout_s)

    def start(self, *args: str) -> subprocess.Popen[str]:
        """A Compose command left running (its stdout and stderr piped), for what must be in place before an act."""
        return subprocess.Popen(
            self.command(*args), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=self.environment()
        )

    def http(self, method: str, path: str, body: object = None, *, key: str | None = None) -> Answer:
        return http(self.base_url, method, path, body, key=key)

    def psql(self, query: str) -> str:
        return self.compose(
            "exec", "-T", "postgres", "psql", "-U", "posemetry", "-d", "posemetry", "-tAc", query
        ).strip()

    def redis(self, *args: str) -> str:
        out = self.compose("exec", "-T", "redis", "redis-cli", "--raw", *args).strip()
        assert not out.startswith(("ERR", "WRONGTYPE")), out  # redis-cli prints errors and exits 0
        return out

    def containers(self) -> list[dict[str, Any]]:
        """`docker compose ps -a` as records (Service, State, ExitCode, ID, ...)."""
        out = self.compose("ps", "-a", "--format", "json").strip()
        if out.startswith("["):
            return list(json.loads(out))
        return [json.loads(line) for line in out.splitlines() if line.strip()]

    def logs(self, tail: int = 40) -> str:
        """The last lines of every service's log, for a failure's report."""
        command = self.command("logs", "--no-color", "--tail", str(tail))
        done = subprocess.run(command, capture_output=True, text=True, env=self.environment(), timeout=60, check=False)
        return done.stdout + done.stderr

    def down(self) -> None:
        """Remove the project's containers, network and volumes, whatever state they are in."""
        command = self.command("down", "-v", "--remove-orphans", "--timeout", "10")
        subprocess.run(command, capture_output=True, env=self.environment(), timeout=300, check=False)


class Phases:
    """Wall time of each step of the scenario, printed as a table (the test asserts no timing)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.notes: list[str] = []

    def note(self, line: str) -> None:
        """A fact worth reading beside the timings (what was killed, how many posts were refused)."""
        self.notes.append(line)

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        started = time.monotonic()
        try:
            yield
        finally:
            self.seconds[name] = time.monotonic() - started

    def table(self) -> str:
        width = max((len(name) for name in self.seconds), default=0)
        lines = [f"  {name:<{width}}  {seconds:7.1f} s" for name, seconds in self.seconds.items()]
        total = sum(self.seconds.values())
        lines.append(f"  {'total':<{width}}  {total:7.1f} s")
        return "\n".join(["Compose test phases (wall time):", *lines, *(f"  - {note}" for note in self.notes)])
