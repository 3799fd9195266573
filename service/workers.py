"""Several server processes on one port, each with its own listening socket (``SO_REUSEPORT``).

uvicorn's own ``--workers`` shares one listening socket among its processes. Under keep-alive
load the process that wakes first accepts a whole burst of connections and keeps them: with two
workers and 32 connections one process ran at 100 % of a core and the other idled (217 req/s,
against 200 with one worker). With a socket per process the kernel spreads new connections over
the listening processes by a hash of their addresses (the same two workers: 394 req/s).

``Supervisor`` starts the workers, restarts one that dies after it started serving, stops all of
them on SIGINT or SIGTERM, and stops with an error when a worker fails during start-up (a broken
artifact folder fails the same way every time). The workers share one Prometheus multiprocess
directory, so a scrape of ``/metrics`` on any of them reports all of them (``service/metrics.py``).
A worker whose supervisor disappears (SIGKILL, OOM) stops by itself instead of serving on alone.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import shutil
import signal
import socket
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from multiprocessing.context import SpawnProcess
from pathlib import Path
from types import FrameType

from service.metrics import MULTIPROC_ENV

log = logging.getLogger(__name__)

APP_FACTORY = "service.api.app:create_app"  # what uvicorn serves, with one worker or many
GRACEFUL_SECONDS = 10  # uvicorn's grace for requests in flight at a stop
STARTUP_FAILURE = 3  # a worker's exit status when it stopped before serving
_PARENT_POLL_SECONDS = 1.0


def listening_socket(host: str, port: int) -> socket.socket:
    """A TCP socket bound to ``host:port`` with ``SO_REUSEPORT``, so that every worker can bind it.

    Raises ``OSError`` when another program holds the port without ``SO_REUSEPORT``.
    """
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        sock.bind((host, port))
    except OSError:
        sock.close()
        raise
    return sock


@dataclass(frozen=True)
class WorkerConfig:
    """What a worker process needs to serve (picklable: workers are spawned)."""

    host: str
    port: int
    log_level: str  # uvicorn's
    root_log_level: int  # the CLI's (INFO, or DEBUG with --verbose)
    graceful_seconds: int = GRACEFUL_SECONDS


def run_worker(config: WorkerConfig, parent_pid: int) -> None:
    """The body of one worker process: its own socket on the shared port, then uvicorn."""
    import uvicorn

    from service.cli import LOG_FORMAT, quiet_libraries

    logging.basicConfig(level=config.root_log_level, format=LOG_FORMAT)
    quiet_libraries()
    _stop_when_orphaned(parent_pid)
    sock = listening_socket(config.host, config.port)
    server = uvicorn.Server(uvicorn.Config(APP_FACTORY, factory=True, log_level=config.log_level,
                                           timeout_graceful_shutdown=config.graceful_seconds))
    server.run(sockets=[sock])
    if not server.started:
        sys.exit(STARTUP_FAILURE)


def _stop_when_orphaned(parent_pid: int) -> None:
    """SIGTERM this process (uvicorn's graceful stop) once its supervisor is gone."""

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(_PARENT_POLL_SECONDS)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


class Supervisor:
    """Run ``workers`` server processes on ``host:port`` until SIGINT or SIGTERM."""

    def __init__(self, host: str, port: int, workers: int, log_level: str = "info",
                 graceful_seconds: int = GRACEFUL_SECONDS):
        self.host, self.port, self.workers = host, port, workers
        self.log_level, self.graceful_seconds = log_level, graceful_seconds
        self._context = multiprocessing.get_context("spawn")
        self._processes: list[SpawnProcess] = []
        self._stop = threading.Event()

    def run(self) -> int:
        """Serve until told to stop; the exit status (0, or 1 when a worker failed to start)."""
        # Binding here first resolves port 0 and fails at once, with a clear error, on a taken port.
        reserved = listening_socket(self.host, self.port)
        port = int(reserved.getsockname()[1])
        metrics_dir, own_dir = self._metrics_dir()
        config = WorkerConfig(self.host, port, self.log_level, logging.getLogger().getEffectiveLevel(),
                              self.graceful_seconds)
        previous = {sig: signal.signal(sig, self._on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
        status = 0
        try:
            log.info("supervisor %d: %d workers on http://%s:%d (metrics in %s)", os.getpid(),
                     self.workers, self.host, port, metrics_dir)
            self._processes = [self._start(config) for _ in range(self.workers)]
            while not self._stop.wait(0.5):
                status = self._replace_dead(config)
                if status:
                    break
        finally:
            self._stop_all()
            for sig, handler in previous.items():
                signal.signal(sig, handler)
            reserved.close()
            if own_dir:
                shutil.rmtree(metrics_dir, ignore_errors=True)
        return status

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        log.info("supervisor: %s, stopping the workers", signal.Signals(signum).name)
        self._stop.set()

    def _metrics_dir(self) -> tuple[Path, bool]:
        """The workers' Prometheus multiprocess directory: ``PROMETHEUS_MULTIPROC_DIR`` if set
        (then it is the operator's to clean), else a fresh temporary one removed at the end."""
        given = os.environ.get(MULTIPROC_ENV)
        if given:
            Path(given).mkdir(parents=True, exist_ok=True)
            return Path(given), False
        path = Path(tempfile.mkdtemp(prefix="complementme-metrics-"))
        os.environ[MULTIPROC_ENV] = str(path)  # inherited by the spawned workers
        return path, True

    def _start(self, config: WorkerConfig) -> SpawnProcess:
        process = self._context.Process(target=run_worker, args=(config, os.getpid()),
                                        name="complementme-worker")
        process.start()
        log.info("supervisor: started worker %d", process.pid)
        return process

    def _replace_dead(self, config: WorkerConfig) -> int:
        """Restart workers that exited; 1 (stop serving) when one failed during its start-up."""
        from prometheus_client import multiprocess

        for i, process in enumerate(self._processes):
            if process.is_alive() or self._stop.is_set():
                continue
            process.join()
            multiprocess.mark_process_dead(process.pid)
            if process.exitcode == STARTUP_FAILURE:
                log.error("supervisor: worker %d failed to start (see its log above); stopping", process.pid)
                return 1
            log.warning("supervisor: worker %d exited with status %s; starting another", process.pid,
                        process.exitcode)
            self._processes[i] = self._start(config)
        return 0

    def _stop_all(self) -> None:
        """SIGTERM every worker (uvicorn's graceful stop), SIGKILL those still running after the grace."""
        for process in self._processes:
            if process.is_alive() and process.pid is not None:
                os.kill(process.pid, signal.SIGTERM)
        deadline = time.monotonic() + self.graceful_seconds + 5
        for process in self._processes:
            process.join(timeout=max(0.0, deadline - time.monotonic()))
            if process.is_alive():
                log.warning("supervisor: worker %d did not stop in time; killing it", process.pid)
                process.kill()
                process.join()
