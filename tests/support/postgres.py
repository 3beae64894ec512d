"""A throwaway PostgreSQL cluster for tests, from the distribution's server binaries (Debian: `postgresql`).

initdb refuses to run as root, and CI runs as root: there the cluster is created and run as the `postgres`
system user (which the Debian package creates), in a directory under /tmp handed to that user. As anyone else
it runs as the current user. The server listens only on a Unix socket inside that directory (no TCP, so no
port clashes with anything else on the machine; the port number only names the socket file) and runs with
fsync off: the data are disposable and the tests are faster for it.
"""

from __future__ import annotations

import contextlib
import os
import pwd
import re
import shutil
import socket
import subprocess
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import psycopg
import pytest
from psycopg import sql

SUPERUSER = "postgres"
START_TIMEOUT_S = 60
# Users a root process may hand the cluster to, in order of preference.
UNPRIVILEGED_USERS = ("postgres", "nobody")


class PostgresUnavailableError(RuntimeError):
    """No PostgreSQL server binaries on this machine (install Debian's `postgresql` package)."""


def find_bin_dir() -> Path:
    """The newest /usr/lib/postgresql/<version>/bin holding initdb, else wherever initdb is on PATH."""
    candidates = []
    for initdb in Path("/usr/lib/postgresql").glob("*/bin/initdb"):
        version = re.match(r"\d+", initdb.parents[1].name)
        candidates.append((int(version.group()) if version else 0, initdb.parent))
    if candidates:
        return max(candidates)[1]
    on_path = shutil.which("initdb")
    if on_path and (Path(on_path).resolve().parent / "pg_ctl").exists():
        return Path(on_path).resolve().parent
    raise PostgresUnavailableError("no initdb found under /usr/lib/postgresql/*/bin or on PATH")


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@dataclass(frozen=True)
class _RunAs:
    uid: int
    gid: int

    @classmethod
    def choose(cls) -> _RunAs | None:
        """None: run as ourselves; otherwise the unprivileged user root must hand the cluster to."""
        if os.geteuid() != 0:
            return None
        for name in UNPRIVILEGED_USERS:
            with contextlib.suppress(KeyError):
                entry = pwd.getpwnam(name)
                return cls(entry.pw_uid, entry.pw_gid)
        raise PostgresUnavailableError(f"running as root and none of the users {UNPRIVILEGED_USERS} exists")

    def subprocess_kwargs(self) -> dict[str, Any]:
        return {"user": self.uid, "group": self.gid, "extra_groups": []}


class PostgresCluster:
    """initdb + pg_ctl start in a fresh temporary directory; stop() shuts it down and deletes everything."""

    def __init__(self) -> None:
        self.bin_dir = find_bin_dir()
        self.run_as = _RunAs.choose()
        # Directly under /tmp, not pytest's tmp_path: that one is private to root (0700), which the postgres user
        # could not enter, and its long path would overflow the ~107-byte limit on Unix socket paths.
        self.root = Path(tempfile.mkdtemp(prefix="posemetry-pg-"))
        self.data_dir = self.root / "data"
        self.socket_dir = self.root
        self.log_file = self.root / "server.log"
        self.port = _free_port()
        self._started = False
        if self.run_as is not None:
            os.chown(self.root, self.run_as.uid, self.run_as.gid)

    def _run(self, *args: str) -> subprocess.CompletedProcess[str]:
        kwargs = self.run_as.subprocess_kwargs() if self.run_as is not None else {}
        env = {**os.environ, "LC_ALL": "C", "LANG": "C"}
        result = subprocess.run(
            [str(self.bin_dir / args[0]), *args[1:]],
            cwd=self.root,
            env=env,
            capture_output=True,
            text=True,
            timeout=START_TIMEOUT_S + 30,
            check=False,
            **kwargs,
        )
        if result.returncode != 0:
            log = self.log_file.read_text() if self.log_file.exists() else ""
            raise RuntimeError(f"{' '.join(args)} failed ({result.returncode}):\n{result.stdout}{result.stderr}{log}")
        return result

    def start(self) -> PostgresCluster:
        self._run(
            "initdb", "-D", str(self.data_dir), "-U", SUPERUSER, "-A", "trust", "-E", "UTF8", "--locale=C",
            "--no-sync", "--no-instructions",
        )  # fmt: skip
        self.start_server()
        return self

    def start_server(self) -> None:
        """Start the server on the existing cluster (after `start`, or again after `stop_server`)."""
        options = (
            f"-p {self.port} -k {self.socket_dir} -c listen_addresses='' -c fsync=off -c synchronous_commit=off "
            "-c full_page_writes=off -c max_connections=100"
        )
        self._run(
            "pg_ctl", "start", "-D", str(self.data_dir), "-l", str(self.log_file), "-w", "-t", str(START_TIMEOUT_S),
            "-o", options,
        )  # fmt: skip
        self._started = True

    def stop_server(self, mode: str = "fast") -> None:
        """Stop the server and keep the cluster (a database outage): `fast` ends every session first, as a
        restart of the database would; `immediate` is a crash."""
        self._run("pg_ctl", "stop", "-D", str(self.data_dir), "-m", mode, "-w")
        self._started = False

    def stop(self) -> None:
        try:
            if self._started:
                self.stop_server("immediate")
        finally:
            shutil.rmtree(self.root, ignore_errors=True)

    def url(self, database: str) -> str:
        """SQLAlchemy URL of a database in this cluster, over the Unix socket."""
        return f"postgresql+psycopg://{SUPERUSER}@/{database}?host={self.socket_dir}&port={self.port}"

    @contextlib.contextmanager
    def admin(self) -> Iterator[psycopg.Connection[Any]]:
        """An autocommit superuser connection to the maintenance database (CREATE/DROP DATABASE need one)."""
        with psycopg.connect(
            host=str(self.socket_dir), port=self.port, user=SUPERUSER, dbname="postgres", autocommit=True
        ) as connection:
            yield connection

    def create_database(self, name: str, template: str | None = None) -> str:
        query = sql.SQL("CREATE DATABASE {}").format(sql.Identifier(name))
        if template is not None:
            query = sql.SQL("CREATE DATABASE {} TEMPLATE {}").format(sql.Identifier(name), sql.Identifier(template))
        with self.admin() as connection:
            connection.execute(query)
        return self.url(name)

    def drop_database(self, name: str) -> None:
        with self.admin() as connection:
            connection.execute(sql.SQL("DROP DATABASE IF EXISTS {} WITH (FORCE)").format(sql.Identifier(name)))


REQUIRE_POSTGRES_ENV = "POSEMETRY_TESTS_REQUIRE_POSTGRES"


def cluster_or_skip() -> PostgresCluster:
    """A new (not yet started) cluster; the test skips when PostgreSQL is not installed, or fails where CI requires
    it (REQUIRE_POSTGRES_ENV=1, set by .ci/run), so a missing package cannot pass silently."""
    try:
        return PostgresCluster()
    except PostgresUnavailableError as exc:
        if os.environ.get(REQUIRE_POSTGRES_ENV) == "1":
            pytest.fail(f"PostgreSQL required ({REQUIRE_POSTGRES_ENV}=1): {exc}")
        pytest.skip(f"PostgreSQL not installed: {exc}")
