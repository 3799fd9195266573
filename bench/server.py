"""Start an HTTP server as a subprocess on a free loopback port and wait until it is ready.

Used for ``complementme serve`` (our service) and for the peer baseline's uvicorn. The server's
output goes to a log file, never to a pipe: a pipe nobody reads fills up under load and stalls
the server, which would show up as latency.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx

log = logging.getLogger(__name__)


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free on ``host`` now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def complementme_command() -> list[str]:
    """How to run the ``complementme`` CLI of this environment (its script, else ``-m training``)."""
    script = Path(sys.executable).parent / "complementme"
    return [str(script)] if script.is_file() else [sys.executable, "-m", "training"]


@dataclass
class Server:
    """A running server: its base URL, process and log file."""

    url: str
    process: subprocess.Popen[bytes]
    log_path: Path


@contextmanager
def running_server(command: Sequence[str], *, port: int, ready_path: str, log_path: Path,
                   env: dict[str, str] | None = None, cwd: Path | None = None,
                   start_timeout: float = 180.0, stop_signal: int = signal.SIGINT) -> Iterator[Server]:
    """Run ``command`` (which must listen on ``port``) until the block ends.

    Waits until ``GET ready_path`` answers 200; raises ``RuntimeError`` with the log's tail if
    the process exits first or ``start_timeout`` seconds pass. On exit the server gets
    ``stop_signal`` (SIGINT: uvicorn's graceful stop; gunicorn's is SIGTERM), then SIGKILL after 15 s.
    """
    log_path.parent.mkdir(parents=True, exist_ok=True)
    url = f"http://127.0.0.1:{port}"
    full_env = {**os.environ, **(env or {})}
    with open(log_path, "wb") as out:
        proc = subprocess.Popen(list(command), stdout=out, stderr=subprocess.STDOUT, env=full_env,
                                cwd=str(cwd) if cwd else None)
        try:
            _wait_ready(proc, url + ready_path, log_path, start_timeout, stop_signal)
            log.info("server ready at %s (pid %d, log %s)", url, proc.pid, log_path)
            yield Server(url=url, process=proc, log_path=log_path)
        finally:
            _stop(proc, stop_signal)


def _wait_ready(proc: subprocess.Popen[bytes], url: str, log_path: Path, timeout: float,
                stop_signal: int) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"server exited with status {proc.returncode} before it was ready; "
                               f"log {log_path}:\n{log_tail(log_path)}")
        try:
            if httpx.get(url, timeout=2.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.25)
    _stop(proc, stop_signal)
    raise RuntimeError(f"server not ready at {url} after {timeout:.0f} s; log {log_path}:\n"
                       f"{log_tail(log_path)}")


def _stop(proc: subprocess.Popen[bytes], stop_signal: int = signal.SIGINT) -> None:
    if proc.poll() is not None:
        return
    proc.send_signal(stop_signal)
    try:
        proc.wait(timeout=15)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=15)


def log_tail(path: Path, lines: int = 30) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"
