"""A throwaway PostgreSQL server: Debian's binaries, a fresh cluster in a temporary directory.

What the tests (tests/conftest.py) and the failover benchmark run the shared storage on; not for production.

The server listens on 127.0.0.1 (a free port) and on a Unix socket in its directory, with trust
authentication for the one user ``agv`` and fsync off (a test's data need not survive a power cut). PostgreSQL
refuses to run as root: as root, every command runs as the ``postgres`` system user (the one Debian's package
creates) through ``runuser``, and the directory belongs to that user.

Missing binaries are an error, not a reason to skip: `.ci/install-system-deps` installs the package, and a suite
that silently skipped the PostgreSQL tests would claim what it did not check.
"""

from __future__ import annotations

import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import uuid
from pathlib import Path

import psycopg

USER = "agv"
#: where Debian's postgresql package puts the server's binaries (the newest major version is used)
BIN_GLOB = "/usr/lib/postgresql/*/bin"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def find_bin_dir() -> Path:
    """The directory of initdb, pg_ctl and postgres: AGV_FE_TEST_PG_BIN, else the newest Debian install."""
    configured = os.environ.get("AGV_FE_TEST_PG_BIN")
    candidates = [Path(configured)] if configured else sorted(Path("/").glob(BIN_GLOB.lstrip("/")), reverse=True)
    for directory in candidates:
        if (directory / "initdb").is_file() and (directory / "pg_ctl").is_file():
            return directory
    raise RuntimeError(
        f"PostgreSQL's server binaries (initdb, pg_ctl) are not in {configured or BIN_GLOB}: install Debian's "
        "postgresql package (.ci/install-system-deps does) or set AGV_FE_TEST_PG_BIN to their directory"
    )


class PostgresServer:
    """One PostgreSQL cluster in a temporary directory; :meth:`database` gives each test a fresh database."""

    def __init__(self) -> None:
        self.bin_dir = find_bin_dir()
        self.root = Path(tempfile.mkdtemp(prefix="agv-fe-pg-"))
        self.data = self.root / "data"
        self.socket_dir = self.root / "socket"
        self.log_path = self.root / "server.log"
        self.port = free_port()
        self._as_user: list[str] = []
        if os.geteuid() == 0:
            owner = pwd.getpwnam("postgres")  # KeyError: Debian's package creates this user
            self._as_user = ["runuser", "-u", "postgres", "--"]
            self.socket_dir.mkdir()
            for path in (self.root, self.socket_dir):
                os.chown(path, owner.pw_uid, owner.pw_gid)
        else:
            self.socket_dir.mkdir()

    def _run(self, *command: str) -> None:
        done = subprocess.run(
            [*self._as_user, str(self.bin_dir / command[0]), *command[1:]],
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        if done.returncode != 0:
            log = self.log_path.read_text() if self.log_path.exists() else ""
            raise RuntimeError(f"{command[0]} failed ({done.returncode}): {done.stdout}{done.stderr}\n{log}")

    def init(self) -> PostgresServer:
        self._run("initdb", "-D", str(self.data), "-U", USER, "-A", "trust", "-E", "UTF8", "--no-sync")
        return self.start()

    def start(self) -> PostgresServer:
        options = f"-h 127.0.0.1 -p {self.port} -k {self.socket_dir} -F -c max_connections=300"
        self._run("pg_ctl", "-D", str(self.data), "-l", str(self.log_path), "-o", options, "-w", "-t", "120", "start")
        return self

    def stop(self, mode: str = "fast") -> None:
        """Stop the server (``immediate``: as if it crashed); its data stays for :meth:`start`."""
        self._run("pg_ctl", "-D", str(self.data), "-m", mode, "-w", "-t", "120", "stop")

    def close(self) -> None:
        if (self.data / "postmaster.pid").exists():
            self.stop("immediate")
        shutil.rmtree(self.root, ignore_errors=True)

    def url(self, database: str = "postgres") -> str:
        return f"postgresql://{USER}@127.0.0.1:{self.port}/{database}"

    def database(self) -> str:
        """A new, empty database; its URL."""
        name = f"t_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(self.url(), autocommit=True) as admin:
            admin.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)
