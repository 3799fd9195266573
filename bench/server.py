"""Start HTTP servers as subprocesses on free loopback ports and wait until they are ready.

Used for ``complementme serve`` (our service), the peer baseline's uvicorn and the balancer
benchmark's set-ups. ``our_servers`` starts our service as it is meant to run on a machine of its
own: one ``complementme serve`` per core, each on a port of its own, behind HAProxy with the
shipped configuration (``docker/haproxy/haproxy.cfg``, of which only the ``bind`` address and the
``server`` lines are replaced). A server's output goes to a log file, never to a pipe: a pipe
nobody reads fills up under load and stalls the server, which would show up as latency.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path

import httpx

from bench.query import REPO

log = logging.getLogger(__name__)

HAPROXY_CONFIG = REPO / "docker" / "haproxy" / "haproxy.cfg"
READY_PATH = "/readyz"  # 200 once a server process has loaded and warmed up (HAProxy checks it too)


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that is free on ``host`` now (the OS picks it)."""
    return free_ports(1, host)[0]


def free_ports(n: int, host: str = "127.0.0.1") -> list[int]:
    """``n`` distinct TCP ports free on ``host`` now: all bound at once while the OS picks them.

    Why: ports picked one after the other may repeat (each socket is closed before the next
    bind), and two servers told the same port look ready together (the second one's readiness
    check is answered by the first, then it fails to bind): a CI run saw two "servers" behind
    HAProxy that were one.
    """
    with ExitStack() as stack:
        sockets = [stack.enter_context(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) for _ in range(n)]
        for s in sockets:
            s.bind((host, 0))
        return [int(s.getsockname()[1]) for s in sockets]


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


# --- our service: one process, or one per core behind HAProxy ----------------------------------


def haproxy_config(port: int, backends: Sequence[int], *, mode: str | None = None, balance: str | None = None,
                   threads: int | None = None, timeout: float | None = None,
                   shipped: Path = HAPROXY_CONFIG) -> str:
    """The shipped HAProxy configuration on ``127.0.0.1:port`` in front of ``backends`` (loopback
    ports): its ``bind`` line and ``server`` lines replaced, the rest as shipped.

    ``mode``, ``balance``, ``threads`` (``nbthread``) and ``timeout`` (client and server, seconds)
    replace the shipped values when given. ``ValueError`` if the file no longer has exactly one
    of each line this replaces.
    """
    replace = {"bind": f"bind 127.0.0.1:{port}"}
    if mode is not None:
        replace["mode"] = f"mode {mode}"
    if balance is not None:
        replace["balance"] = f"balance {balance}"
    if threads is not None:
        replace["nbthread"] = f"nbthread {threads}"
    if timeout is not None:
        seconds = f"{max(1, round(timeout))}s"
        replace["timeout client"] = f"timeout client {seconds}"
        replace["timeout server"] = f"timeout server {seconds}"
    found = dict.fromkeys(replace, 0)
    out: list[str] = []
    servers_at = None
    for line in shipped.read_text().splitlines():
        words = line.split("#", 1)[0].split()
        indent = line[: len(line) - len(line.lstrip())]
        if words[:1] == ["server"]:
            servers_at = len(out) if servers_at is None else servers_at
            continue
        key = next((k for k in replace if words[: len(k.split())] == k.split()), None)
        if key is not None:
            found[key] += 1
            line = indent + replace[key]
        out.append(line)
    wrong = [k for k, n in found.items() if n != 1]
    if wrong or servers_at is None:
        raise ValueError(f"{shipped}: expected one line of each of {', '.join(wrong or ['server'])} "
                         f"to replace, and server lines; found otherwise")
    indent = "    "
    servers = [f"{indent}server s{i + 1} 127.0.0.1:{p}" for i, p in enumerate(backends)]
    out[servers_at:servers_at] = servers
    return "\n".join(out) + "\n"


@dataclass
class OurServers:
    """Our service as started by ``our_servers``."""

    url: str             # where clients connect: HAProxy's port, or the one server's
    backends: list[str]  # each server process's own URL (each reports its own /metrics)
    roots: list[int]     # pids of the processes started (servers, proxy), for /proc accounting

    @property
    def metrics_urls(self) -> list[str]:
        return [b + "/metrics" for b in self.backends]


def missing_haproxy() -> str | None:
    """How to get HAProxy when it is not on the path (None when it is)."""
    return None if shutil.which("haproxy") else "haproxy (Debian: apt-get install haproxy)"


@contextmanager
def our_servers(processes: int, log_dir: Path, *, env: dict[str, str] | None = None,
                proxy: bool | None = None, log_name: str = "serve", start_timeout: float = 180.0,
                mode: str | None = None, balance: str | None = None, threads: int | None = None,
                timeout: float | None = None) -> Iterator[OurServers]:
    """``processes`` ``complementme serve`` on free loopback ports, and (``proxy``; by default when
    there are several) HAProxy in front of them with the shipped configuration.

    Ready when the block starts: every server answers ``/readyz``, and so does the proxy (its
    health checks have found a server up). Logs go to ``log_dir``: ``<log_name>.log`` for a lone
    server, ``<log_name>-<i>.log`` and ``haproxy.log`` behind the proxy; HAProxy's configuration is
    written there too. ``mode`` to ``timeout`` are passed to ``haproxy_config``.
    """
    if processes < 1:
        raise ValueError(f"processes must be at least 1, found {processes}")
    proxy = processes > 1 if proxy is None else proxy
    if proxy and (missing := missing_haproxy()):
        raise RuntimeError(f"{processes} server processes run behind HAProxy, which is missing: {missing}")
    with ExitStack() as stack:
        *ports, front = free_ports(processes + 1)
        servers = []
        for i, port in enumerate(ports):
            cmd = [*complementme_command(), "serve", "--host", "127.0.0.1", "--port", str(port)]
            name = f"{log_name}-{i}.log" if proxy else f"{log_name}.log"
            servers.append(stack.enter_context(running_server(
                cmd, port=port, ready_path=READY_PATH, log_path=log_dir / name, env=env, cwd=REPO,
                start_timeout=start_timeout)))
        backends = [s.url for s in servers]
        roots = [s.process.pid for s in servers]
        if not proxy:
            yield OurServers(url=backends[0], backends=backends, roots=roots)
            return
        conf = log_dir / "haproxy.cfg"
        conf.write_text(haproxy_config(front, ports, mode=mode, balance=balance, threads=threads,
                                       timeout=timeout))
        haproxy = stack.enter_context(running_server(
            [shutil.which("haproxy") or "haproxy", "-f", str(conf), "-db"], port=front, ready_path=READY_PATH,
            log_path=log_dir / "haproxy.log", start_timeout=start_timeout))
        yield OurServers(url=haproxy.url, backends=backends, roots=[*roots, haproxy.process.pid])
