"""A real PostgreSQL server for the tests (Debian's ``postgresql``, installed with apt-get when missing and the tests
run as root): ``initdb`` in a temporary directory owned by an unprivileged user (``postgres`` when it exists, else
``nobody``; the server refuses to run as root), ``pg_ctl start`` on 127.0.0.1 at a free port with trust
authentication, stopped and removed at the end of the session. Each test gets a database of its own
(``PostgresServer.new_database``).

The fixtures (``postgres`` once per session, ``postgres_url`` per test) are registered in ``tests/conftest.py``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import os
import pwd
import shutil
import subprocess
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from services.common.zenoh_session import free_ports

DEBIAN_BIN = Path("/usr/lib/postgresql")
_databases = itertools.count()


def postgres_bindir() -> Path | None:
    """The newest Debian PostgreSQL's bin directory (with initdb and pg_ctl), or None."""
    found = sorted(
        DEBIAN_BIN.glob("*/bin/initdb"),
        key=lambda p: int(p.parent.parent.name) if p.parent.parent.name.isdigit() else 0,
    )
    return found[-1].parent if found else None


def install_postgres() -> Path:
    """Debian's postgresql, installed with apt-get when missing (as root); the test skipped only when that fails."""
    bindir = postgres_bindir()
    if bindir is not None:
        return bindir
    if os.geteuid() != 0 or shutil.which("apt-get") is None:
        pytest.skip("no PostgreSQL in /usr/lib/postgresql and not root with apt-get to install it")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    done: subprocess.CompletedProcess[str] | None = None
    for command in (
        ["apt-get", "install", "-y", "-q", "postgresql"],
        ["apt-get", "update"],
        ["apt-get", "install", "-y", "-q", "postgresql"],
    ):
        done = subprocess.run(command, capture_output=True, text=True, timeout=900, env=env)
        if done.returncode == 0 and postgres_bindir() is not None:
            break
    bindir = postgres_bindir()
    if bindir is None:
        pytest.skip(f"apt-get install -y postgresql failed: {done.stderr.strip()[-300:] if done else ''}")
    return bindir


def _server_user() -> str | None:
    """The unprivileged user the server runs as when the tests run as root; None when they do not."""
    if os.geteuid() != 0:
        return None
    for name in ("postgres", "nobody"):
        try:
            pwd.getpwnam(name)
        except KeyError:
            continue
        return name
    pytest.skip("running as root and no unprivileged user (postgres, nobody) to run PostgreSQL as")


@dataclasses.dataclass
class PostgresServer:
    """A running server: its bin directory, data directory, port and the user it runs as."""

    bindir: Path
    root: Path
    port: int
    user: str | None

    def run(self, *command: str, timeout: float = 60.0) -> subprocess.CompletedProcess[str]:
        """A PostgreSQL program of ``bindir`` run as the server's user; CalledProcessError with its output."""
        argv = [str(self.bindir / command[0]), *command[1:]]
        if self.user is not None:
            argv = ["runuser", "-u", self.user, "--", *argv]
        done = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, cwd=self.root)
        if done.returncode != 0:
            raise subprocess.CalledProcessError(done.returncode, argv, done.stdout, done.stderr)
        return done

    @property
    def data(self) -> Path:
        return self.root / "data"

    def url(self, database: str = "postgres") -> str:
        return f"postgresql://postgres@127.0.0.1:{self.port}/{database}"

    def new_database(self) -> str:
        """The URL of a new, empty database."""
        import psycopg

        name = f"magnet_test_{os.getpid()}_{next(_databases)}"
        with psycopg.connect(self.url(), autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def start(self) -> None:
        options = f"-h 127.0.0.1 -p {self.port} -k {self.root} -F -c fsync=off -c full_page_writes=off"
        self.run("pg_ctl", "-D", str(self.data), "-l", str(self.root / "server.log"), "-o", options, "-w", "start")

    def stop(self) -> None:
        self.run("pg_ctl", "-D", str(self.data), "-m", "immediate", "-w", "stop")


def start_postgres() -> Iterator[PostgresServer]:
    """initdb, start, yield the server; stop it and remove its directory at the end."""
    bindir = install_postgres()
    user = _server_user()
    root = Path(tempfile.mkdtemp(prefix="magnet-pg-"))
    root.chmod(0o755)
    if user is not None:
        entry = pwd.getpwnam(user)
        os.chown(root, entry.pw_uid, entry.pw_gid)
    server = PostgresServer(bindir, root, free_ports(1)[0], user)
    try:
        server.run("initdb", "-D", str(server.data), "-U", "postgres", "-A", "trust", "-E", "UTF8", "--no-sync")
        server.start()
        yield server
    finally:
        with contextlib.suppress(subprocess.CalledProcessError, subprocess.TimeoutExpired):
            server.stop()
        shutil.rmtree(root, ignore_errors=True)
