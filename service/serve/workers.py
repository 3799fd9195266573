"""Several server processes on one port: a supervisor that accepts, workers that serve.

The supervisor owns the listening socket and deals the new connections to the workers in turn
(``service/serve/balancer.py``: the kernel's own spreading left one worker with twice the other's
connections, and its queue set the tail latency).

``Supervisor`` starts the workers, restarts one that dies after it started serving, stops all of
them on SIGINT or SIGTERM, and stops with an error when a worker fails during start-up (a broken
artifact folder fails the same way every time). The workers share one Prometheus multiprocess
directory, so a scrape of ``/metrics`` on any of them reports all of them (``service/api/metrics.py``).
A worker whose supervisor disappears (SIGKILL, OOM) sees its channel close and stops by itself
instead of serving on alone.
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

from uvicorn.server import STARTUP_FAILURE  # a worker's exit status when it stopped before serving

from service.api.metrics import MULTIPROC_ENV
from service.serve.balancer import ConnectionBalancer, HandedServer, channel_pair

log = logging.getLogger(__name__)

APP_FACTORY = "service.api.app:create_app"  # what uvicorn serves, with one worker or many
# uvicorn's httptools protocol answering parser errors with the JSON error body (its ``http``).
HTTP_PROTOCOL = "service.api.http_protocol:JsonErrorProtocol"
GRACEFUL_SECONDS = 10  # uvicorn's grace for requests in flight at a stop
BACKLOG = 2048  # uvicorn's default listen backlog
_POLL_SECONDS = 0.5  # how often the supervisor looks for dead workers and stop signals


def listening_socket(host: str, port: int, backlog: int = BACKLOG) -> socket.socket:
    """The supervisor's TCP socket, listening on ``host:port``; ``OSError`` when the port is taken."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, port))
        sock.listen(backlog)
    except OSError:
        sock.close()
        raise
    return sock


@dataclass(frozen=True)
class WorkerConfig:
    """What a worker process needs to serve (picklable: workers are spawned)."""

    log_level: str  # uvicorn's
    root_log_level: int  # the CLI's (INFO, or DEBUG with --verbose)
    graceful_seconds: int = GRACEFUL_SECONDS


def run_worker(config: WorkerConfig, channel: socket.socket) -> None:
    """The body of one worker process: uvicorn serving the connections ``channel`` brings."""
    import uvicorn

    from service.serve.logs import LOG_FORMAT, quiet_libraries

    logging.basicConfig(level=config.root_log_level, format=LOG_FORMAT)
    quiet_libraries()
    server = HandedServer(uvicorn.Config(APP_FACTORY, factory=True, http=HTTP_PROTOCOL,
                                         log_level=config.log_level,
                                         timeout_graceful_shutdown=config.graceful_seconds), channel)
    server.run()
    if not server.started:
        sys.exit(STARTUP_FAILURE)


class Supervisor:
    """Run ``workers`` server processes on ``host:port`` until SIGINT or SIGTERM."""

    _balancer: ConnectionBalancer  # made in ``run``, with the listening socket

    def __init__(self, host: str, port: int, workers: int, log_level: str = "info",
                 graceful_seconds: int = GRACEFUL_SECONDS, max_pending: int = 64):
        self.host, self.port, self.workers = host, port, workers
        self.max_pending = max_pending
        self.log_level, self.graceful_seconds = log_level, graceful_seconds
        self._context = multiprocessing.get_context("spawn")
        self._processes: list[SpawnProcess] = []
        self._stop = threading.Event()

    def run(self) -> int:
        """Serve until told to stop; the exit status (0, or 1 when a worker failed to start)."""
        # Listening before the workers start fails at once, with a clear error, on a taken port.
        listener = listening_socket(self.host, self.port)
        port = int(listener.getsockname()[1])
        self._balancer = ConnectionBalancer(listener, max_pending=self.max_pending)
        metrics_dir, own_dir = self._metrics_dir()
        config = WorkerConfig(self.log_level, logging.getLogger().getEffectiveLevel(), self.graceful_seconds)
        previous = {sig: signal.signal(sig, self._on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
        status = 0
        try:
            log.info("supervisor %d: %d workers on http://%s:%d (metrics in %s)", os.getpid(),
                     self.workers, self.host, port, metrics_dir)
            self._processes = [self._start(config, slot) for slot in range(self.workers)]
            while not self._stop.is_set():
                self._balancer.poll(_POLL_SECONDS)
                status = self._replace_dead(config)
                if status:
                    break
        finally:
            self._balancer.stop_accepting()
            listener.close()  # clients still in the backlog are refused, not left waiting
            self._stop_all()
            self._balancer.close()
            for sig, handler in previous.items():
                signal.signal(sig, handler)
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

    def _start(self, config: WorkerConfig, slot: int) -> SpawnProcess:
        ours, theirs = channel_pair()
        process = self._context.Process(target=run_worker, args=(config, theirs), name="complementme-worker")
        process.start()
        theirs.close()  # the worker holds its end now: its exit closes the channel
        self._balancer.add(slot, ours)
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
            self._processes[i] = self._start(config, i)
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
            elif process.exitcode not in (0, -signal.SIGTERM):  # uvicorn re-raises the SIGTERM it handled
                log.warning("supervisor: worker %d exited with status %s while stopping", process.pid,
                            process.exitcode)
