"""``complementme serve --workers 2``: one port, connections dealt to the workers, one /metrics view,
supervision.

Each test runs the real CLI on the real artifacts in a process of its own.
"""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from catalog_testkit import free_port
from prometheus_client.parser import text_string_to_metric_families
from service_testkit import AssemblyQuery

REPO = Path(__file__).resolve().parents[2]
SERVING = "serving connections handed over"  # a worker's log line once it takes connections


class Served:
    """``complementme serve --workers N`` on a free port, its log in a file."""

    def __init__(self, artifacts: Path, tmp: Path, workers: int = 2, **env: str):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log = tmp / f"serve-{self.port}.log"
        full_env = {k: v for k, v in os.environ.items()
                    if not k.startswith("COMPLEMENTME_") and k != "PROMETHEUS_MULTIPROC_DIR"}
        full_env.update({"COMPLEMENTME_ARTIFACTS": str(artifacts), "COMPLEMENTME_VERIFY_CHECKSUMS": "false",
                         "COMPLEMENTME_LOG_LEVEL": "info", "PYTHONPATH": str(REPO), **env})
        with open(self.log, "ab") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "training", "serve", "--host", "127.0.0.1", "--port", str(self.port),
                 "--workers", str(workers)], env=full_env, cwd=REPO, stdout=out, stderr=subprocess.STDOUT)

    def wait_ready(self, workers: int = 2, started: int | None = None, timeout: float = 180) -> Served:
        """Until ``workers`` worker processes run, ``started`` workers in all (default: ``workers``)
        have said they serve, and the port answers ``/readyz`` (it does once one worker serves)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            assert self.proc.poll() is None, f"the supervisor exited: {self.log.read_text()[-3000:]}"
            serving = self.log.read_text().count(SERVING)
            if len(self.workers()) == workers and serving >= (started or workers) and _ready(self.url):
                return self
            time.sleep(0.2)
        raise AssertionError(f"not ready: {self.log.read_text()[-3000:]}")

    def workers(self) -> list[int]:
        """Pids of the supervisor's worker processes (not multiprocessing's resource tracker)."""
        return [pid for pid in _children(self.proc.pid) if "spawn_main" in _cmdline(pid)]

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def _children(pid: int) -> list[int]:
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    except OSError:
        return []
    return [int(p) for p in text.split()]


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def _alive(pid: int) -> bool:
    """Running and not a zombie."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _ready(url: str) -> bool:
    try:
        return httpx.get(url + "/readyz", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


def _healthz_count(url: str) -> float:
    """``GET /healthz`` answers counted in one scrape of ``/metrics``."""
    text = httpx.get(url + "/metrics", timeout=10).text
    total = 0.0
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            if s.name == "complementme_http_requests_total" and s.labels.get("route") == "/healthz":
                total += s.value
    return total


def _established_on(port: int, pids: list[int]) -> dict[int, int]:
    """Established TCP connections on local ``port`` held by each of ``pids`` (from /proc)."""
    inodes: set[str] = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with open(table) as rows:
            next(rows)
            for row in rows:
                fields = row.split()
                if int(fields[1].rsplit(":", 1)[1], 16) == port and fields[3] == "01":
                    inodes.add(fields[9])
    held = {}
    for pid in pids:
        links = [os.readlink(f) for f in Path(f"/proc/{pid}/fd").iterdir() if f.is_symlink()]
        held[pid] = sum(1 for link in links if link.startswith("socket:[") and link[8:-1] in inodes)
    return held


def _wait_until(check, timeout: float, what: str) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if check():
            return
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.fixture(scope="module")
def served(artifacts: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Served, Path]]:
    tmp = tmp_path_factory.mktemp("workers")
    metrics_dir = tmp / "prometheus"
    server = Served(artifacts, tmp, PROMETHEUS_MULTIPROC_DIR=str(metrics_dir)).wait_ready()
    try:
        yield server, metrics_dir
    finally:
        server.stop()


def test_connections_spread_over_the_workers_and_metrics_sum_them(served: tuple[Served, Path],
                                                                  query: AssemblyQuery) -> None:
    server, metrics_dir = served
    before = _healthz_count(server.url)
    for _ in range(40):  # a new connection each time: the supervisor deals them out
        assert httpx.get(server.url + "/healthz", timeout=10).status_code == 200
    # Every scrape, whichever worker answers it, counts all 40.
    for _ in range(5):
        assert _healthz_count(server.url) == before + 40
    pids = {int(m.group(1)) for f in metrics_dir.iterdir() if (m := re.match(r"counter_(\d+)\.db", f.name))}
    assert set(server.workers()) <= pids and len(pids) >= 2, "both workers must have served"
    body = {"points": query.points.tolist(), "k": 5}
    answers = [httpx.post(server.url + "/suggest", json=body, timeout=30) for _ in range(6)]
    assert all(a.status_code == 200 for a in answers)
    # Every worker serves the same model, so the ranking does not depend on which one answered.
    assert len({tuple(s["part_id"] for s in a.json()["suggestions"]) for a in answers}) == 1


def test_keep_alive_connections_are_split_evenly(served: tuple[Served, Path]) -> None:
    server, _ = served
    clients = [httpx.Client(base_url=server.url, timeout=10) for _ in range(8)]
    try:
        for client in clients:  # each client keeps its one connection open
            assert client.get("/healthz").status_code == 200
        held = _established_on(server.port, server.workers())
        assert sorted(held.values()) == [4, 4], held
    finally:
        for client in clients:
            client.close()


def test_a_stopped_worker_gets_no_pile_of_connections(artifacts: Path, tmp_path: Path) -> None:
    server = Served(artifacts, tmp_path, COMPLEMENTME_WORKER_MAX_PENDING="2").wait_ready()
    stuck, other = server.workers()
    clients: list[socket.socket] = []
    try:
        os.kill(stuck, signal.SIGSTOP)  # its event loop takes nothing while stopped
        for _ in range(8):
            clients.append(socket.create_connection(("127.0.0.1", server.port), timeout=10))
        # The stopped worker is handed at most 2 (they wait in its channel); the rest go to the other.
        _wait_until(lambda: _established_on(server.port, [other])[other] == 6, 30,
                    "6 connections on the other worker")
        assert _established_on(server.port, [stuck])[stuck] == 0
        os.kill(stuck, signal.SIGCONT)
        _wait_until(lambda: _established_on(server.port, [stuck])[stuck] == 2, 30, "the stopped worker's 2")
    finally:
        os.kill(stuck, signal.SIGCONT)
        for c in clients:
            c.close()
        server.stop()


def test_a_killed_worker_is_replaced_and_its_counts_kept(served: tuple[Served, Path]) -> None:
    server, _ = served
    before = _healthz_count(server.url)
    victim = server.workers()[0]
    os.kill(victim, signal.SIGKILL)
    _wait_until(lambda: victim not in server.workers() and len(server.workers()) == 2, 30,
                "a replacement worker")
    server.wait_ready()
    # The port keeps answering (the other worker serves while the new one loads) ...
    for _ in range(10):
        assert httpx.get(server.url + "/healthz", timeout=10).status_code == 200
    # ... and the dead worker's requests stay counted.
    assert _healthz_count(server.url) >= before + 10


def test_workers_stop_when_the_supervisor_is_killed(artifacts: Path, tmp_path: Path) -> None:
    server = Served(artifacts, tmp_path).wait_ready()
    workers = server.workers()
    server.proc.send_signal(signal.SIGKILL)
    server.proc.wait(timeout=10)
    _wait_until(lambda: not any(_alive(pid) for pid in workers), 60, "orphaned workers to stop")


def test_sigterm_stops_every_process_and_removes_the_metrics_folder(artifacts: Path, tmp_path: Path) -> None:
    server = Served(artifacts, tmp_path).wait_ready()
    workers = server.workers()
    folder = re.search(r"metrics in (\S+)\)", server.log.read_text())
    assert folder, server.log.read_text()[-2000:]
    assert Path(folder.group(1)).is_dir()
    server.proc.send_signal(signal.SIGTERM)
    assert server.proc.wait(timeout=60) == 0
    assert not any(_alive(pid) for pid in workers)
    assert not Path(folder.group(1)).exists()
    # Each worker stopped cleanly: uvicorn's graceful shutdown ran to the app's own shutdown.
    log = server.log.read_text()
    assert "Traceback" not in log and "while stopping" not in log, log[-3000:]
    assert log.count("Application shutdown complete") == 2, log[-3000:]


def test_a_worker_that_cannot_start_stops_the_supervisor(tmp_path: Path) -> None:
    empty = tmp_path / "no-artifacts"
    empty.mkdir()
    server = Served(empty, tmp_path)
    try:
        status = server.proc.wait(timeout=120)
    finally:
        server.stop()
    assert status == 1, server.log.read_text()[-2000:]
    assert "failed to start" in server.log.read_text()


def test_a_port_held_by_another_program_is_a_clear_error(artifacts: Path, tmp_path: Path) -> None:
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        env = {k: v for k, v in os.environ.items() if not k.startswith("COMPLEMENTME_")}
        result = subprocess.run(
            [sys.executable, "-m", "training", "serve", "--host", "127.0.0.1", "--port", str(port),
             "--workers", "2", "--artifacts", str(artifacts)],
            env={**env, "PYTHONPATH": str(REPO)}, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 1
    assert f"cannot listen on 127.0.0.1:{port}" in result.stderr
