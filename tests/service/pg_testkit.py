"""A real PostgreSQL server for the tests: initdb into a temporary folder, pg_ctl on a loopback port.

PostgreSQL refuses to run as root, so under root the server runs as the ``postgres`` user that
Debian's ``postgresql`` package creates (``runuser``); otherwise as the current user. Nothing is
installed here: when the server programs or that user are missing, ``find_postgres`` says why
and the tests skip with that reason.
"""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import shutil
import subprocess
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path

import psycopg
from catalog_testkit import free_port

PG_USER = "complementme"
PG_PASSWORD = "test-password-0123"
DEBIAN_PACKAGE = "postgresql"


def find_postgres() -> tuple[Path | None, str]:
    """The folder of initdb and pg_ctl, or None and the reason they cannot be used."""
    candidates = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"),
                        key=lambda p: int(Path(p).parts[4]) if Path(p).parts[4].isdigit() else 0)
    found = Path(candidates[-1]).parent if candidates else None
    if found is None and shutil.which("initdb"):
        found = Path(shutil.which("initdb") or "").parent
    if found is None or not (found / "pg_ctl").is_file():
        return None, (f"PostgreSQL's server programs (initdb, pg_ctl) are not installed: Debian package "
                      f"{DEBIAN_PACKAGE!r}")
    if os.geteuid() == 0:
        try:
            pwd.getpwnam("postgres")
        except KeyError:
            return None, ("running as root and there is no 'postgres' user to run PostgreSQL as (Debian's "
                          f"{DEBIAN_PACKAGE!r} package creates it)")
        if shutil.which("runuser") is None:
            return None, "running as root and runuser (util-linux) is missing"
    return found, ""


class PostgresCluster:
    """One PostgreSQL server of its own: a temporary data folder, a free loopback port."""

    def __init__(self, bindir: Path):
        self.bindir = bindir
        self.folder = Path(tempfile.mkdtemp(prefix="complementme-pg-"))
        self.data = self.folder / "data"
        self.log = self.folder / "postgres.log"
        self.port = free_port()
        self._as_postgres = os.geteuid() == 0

    def _run(self, *args: str) -> None:
        cmd = [str(self.bindir / args[0]), *args[1:]]
        if self._as_postgres:
            cmd = ["runuser", "-u", "postgres", "--", *cmd]
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
        if done.returncode != 0:
            log = self.log.read_text()[-3000:] if self.log.exists() else ""
            raise RuntimeError(f"{' '.join(cmd)} failed ({done.returncode}): {done.stderr[-3000:]}\n{log}")

    def init(self) -> PostgresCluster:
        pwfile = self.folder / "pwfile"
        pwfile.write_text(PG_PASSWORD + "\n")
        if self._as_postgres:
            entry = pwd.getpwnam("postgres")
            os.chown(self.folder, entry.pw_uid, entry.pw_gid)
            os.chown(pwfile, entry.pw_uid, entry.pw_gid)
        self._run("initdb", "-D", str(self.data), "-U", PG_USER, f"--pwfile={pwfile}", "--auth=scram-sha-256",
                  "-E", "UTF8", "--locale=C", "--no-sync")
        return self

    def start(self) -> PostgresCluster:
        options = (f"-p {self.port} -c listen_addresses=127.0.0.1 -c unix_socket_directories='' "
                   "-c max_connections=200")
        self._run("pg_ctl", "-D", str(self.data), "-l", str(self.log), "-w", "-t", "60", "-o", options,
                  "start")
        return self

    def stop(self) -> None:
        """A fast shutdown: open sessions are ended, their transactions rolled back."""
        self._run("pg_ctl", "-D", str(self.data), "-m", "fast", "-w", "-t", "60", "stop")

    def url(self, dbname: str = "postgres") -> str:
        return f"postgresql://{PG_USER}:{PG_PASSWORD}@127.0.0.1:{self.port}/{dbname}"

    def new_database(self) -> str:
        """A new empty database; its URL."""
        name = f"catalog_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(self.url(), autocommit=True) as conn:
            conn.execute(f"CREATE DATABASE {name}".encode())
        return self.url(name)

    def remove(self) -> None:
        with contextlib.suppress(RuntimeError):  # already stopped
            self.stop()
        shutil.rmtree(self.folder, ignore_errors=True)


def wait_until(check: Callable[[], bool], what: str, timeout: float = 120.0, every: float = 0.01) -> None:
    """Poll ``check`` until it holds (replicas apply changes in the background); fail after
    ``timeout`` seconds saying ``what`` did not happen."""
    deadline = time.monotonic() + timeout
    while not check():
        assert time.monotonic() < deadline, f"timed out waiting until {what}"
        time.sleep(every)
