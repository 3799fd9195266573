"""Benchmark g: ways to spread one port's connections over two server processes (issue 17).

The set-ups, each with ``processes`` (2) server processes serving the same app on the shipped
artifacts, on loopback:

* ``gunicorn``: gunicorn's arbiter with two uvicorn workers (the ``uvicorn-worker`` package)
  on its shared listening socket;
* ``uvicorn``: ``uvicorn --workers 2``, uvicorn's own supervisor, on its shared socket;
* ``haproxy``: Debian's HAProxy in front of two ``complementme serve`` processes, with the
  shipped configuration (``docker/haproxy/haproxy.cfg``: ``http`` mode, ``leastconn``, one
  thread), started by ``bench.server.our_servers`` as the other benchmarks start our service.

A fourth set-up, ``ours`` (``complementme serve --workers 2``: a supervisor that accepted every
connection and dealt it to its workers in turn), ran in the first full run, whose results are
committed (``bench/results/balancers.json``). It did not win by a clear margin against HAProxy, so
by issue 17's rule it was removed and HAProxy shipped; the report still renders that run, and
new runs compare every set-up with ``haproxy``.

Every process is configured the same way: the same ``COMPLEMENTME_*`` environment (one ONNX,
FAISS and BLAS thread each by the settings' defaults), the service's uvicorn HTTP protocol
(``service.serve.cli.HTTP_PROTOCOL``), uvloop, no access log, and each process's own /metrics.

The load is the HTTP benchmark's: wrk, one thread, ``connections`` (32) connections posting
the JSON body, a warm-up then a measured run. The set-ups run one at a time (on two cores they
would share the CPU), each started fresh and stopped after its run, in rounds; each round
starts at the next set-up, so that no set-up always runs first and the machine's drift (other
jobs, the time of day) lands on all of them alike. Besides wrk's figures every run records the
CPU time each process of the set-up used during the measured run (``/proc``): how evenly the
two server processes shared the work, and what the front (arbiter, supervisor, proxy) cost.
"""

from __future__ import annotations

import importlib.util
import logging
import os
import shutil
import signal
import statistics
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

from bench.http_bench import check_answer, write_bodies
from bench.query import REPO, BenchQuery
from bench.server import READY_PATH, free_port, missing_haproxy, our_servers, running_server
from bench.wrk import LoadSettings, run_wrk
from service.serve.cli import APP_FACTORY, GRACEFUL_SECONDS, HTTP_PROTOCOL

log = logging.getLogger(__name__)

SETUPS = ("gunicorn", "uvicorn", "haproxy")
REFERENCE = "haproxy"  # what the summary compares every set-up with: the shipped one
DEFAULT_SERVER_ENV = {"COMPLEMENTME_LOG_LEVEL": "warning"}
GUNICORN_WORKER = "bench.gunicorn_worker.JsonErrorUvicornWorker"  # gunicorn takes a dotted path
WORKER_TIMEOUT = 30  # seconds a supervisor waits on a silent worker before replacing it (uvicorn's)
_HZ = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


@dataclass(frozen=True)
class BalancerBenchConfig:
    """Settings of the balancer comparison."""

    setups: tuple[str, ...] = SETUPS
    rounds: int = 3                 # every set-up runs once per round
    connections: int = 32
    processes: int = 2              # server processes per set-up
    body: str = "json"
    load: LoadSettings = field(default_factory=lambda: LoadSettings(duration=20.0, warmup=5.0))
    server_env: tuple[tuple[str, str], ...] = tuple(DEFAULT_SERVER_ENV.items())
    haproxy_mode: str = "http"      # http: each request balanced; tcp: each connection
    haproxy_balance: str = "leastconn"
    haproxy_threads: int = 1        # as shipped: on two cores a second proxy thread takes CPU from servers
    start_timeout: float = 300.0

    def __post_init__(self) -> None:
        unknown = [s for s in self.setups if s not in SETUPS]
        if unknown or not self.setups:
            raise ValueError(f"set-ups must be among {', '.join(SETUPS)}, "
                             f"found {', '.join(self.setups) or 'none'}")
        if self.rounds < 1 or self.connections < 1 or self.processes < 1:
            raise ValueError(f"rounds, connections and processes must be at least 1, found {self.rounds}, "
                             f"{self.connections}, {self.processes}")
        if self.haproxy_mode not in ("http", "tcp"):
            raise ValueError(f"haproxy_mode must be http or tcp, found {self.haproxy_mode!r}")

    @property
    def log_level(self) -> str:
        return dict(self.server_env).get("COMPLEMENTME_LOG_LEVEL", "warning")

    def as_dict(self) -> dict[str, Any]:
        return {"setups": list(self.setups), "rounds": self.rounds, "connections": self.connections,
                "processes": self.processes, "body": self.body, "load": self.load.as_dict(),
                "server_env": dict(self.server_env),
                "haproxy": {"mode": self.haproxy_mode, "balance": self.haproxy_balance,
                            "threads": self.haproxy_threads}}


def round_order(setups: tuple[str, ...], round_index: int) -> list[str]:
    """The set-ups in the order round ``round_index`` runs them: rotated by one each round."""
    shift = round_index % len(setups)
    return list(setups[shift:] + setups[:shift])


# --- starting the set-ups -------------------------------------------------------------------


def uvicorn_command(port: int, workers: int, log_level: str) -> list[str]:
    """uvicorn's own command line serving the app as ``serve`` does, with its ``--workers``.

    uvicorn's supervisor kills and replaces a worker that does not answer its ping within
    ``--timeout-worker-healthcheck`` (5 s by default); on a busy machine a starved worker missed
    it and was replaced in the middle of a run, so it gets as long as gunicorn's worker timeout.
    """
    return [sys.executable, "-m", "uvicorn", APP_FACTORY, "--factory", "--host", "127.0.0.1",
            "--port", str(port), "--workers", str(workers), "--http", HTTP_PROTOCOL,
            "--log-level", log_level, "--no-access-log", "--timeout-graceful-shutdown", str(GRACEFUL_SECONDS),
            "--timeout-worker-healthcheck", str(WORKER_TIMEOUT)]


def gunicorn_command(port: int, workers: int, log_level: str, start_timeout: float) -> list[str]:
    """gunicorn with ``workers`` uvicorn workers (``bench.gunicorn_worker``) on the app factory.

    ``--timeout`` (after which the arbiter kills a silent worker) is the start-up allowance too:
    a uvicorn worker first tells the arbiter it is alive once the app's lifespan (loading the
    artifacts) has finished.
    """
    module, _, name = APP_FACTORY.partition(":")
    return [sys.executable, "-m", "gunicorn", f"{module}:{name}()", "--worker-class",
            GUNICORN_WORKER, "--workers", str(workers),
            "--bind", f"127.0.0.1:{port}", "--log-level", log_level,
            "--graceful-timeout", str(GRACEFUL_SECONDS), "--timeout", str(round(start_timeout))]


def missing_tools(setups: tuple[str, ...]) -> list[str]:
    """What the chosen set-ups need and this environment lacks, each with how to get it."""
    out = []
    if shutil.which("wrk") is None:
        out.append("wrk (Debian: apt-get install wrk)")
    if "gunicorn" in setups:
        for module, package in (("gunicorn", "gunicorn"), ("uvicorn_worker", "uvicorn-worker")):
            if importlib.util.find_spec(module) is None:
                out.append(f"{package} (pip install -c docker/constraints.txt -e '.[bench]')")
    if "haproxy" in setups and (haproxy := missing_haproxy()):
        out.append(haproxy)
    return out


def tool_versions(setups: tuple[str, ...]) -> dict[str, str | None]:
    """Versions of what serves besides our own code (uvicorn is in the machine's packages)."""
    out: dict[str, str | None] = {}
    if "gunicorn" in setups:
        for name in ("gunicorn", "uvicorn-worker"):
            try:
                out[name] = metadata.version(name)
            except metadata.PackageNotFoundError:
                out[name] = None
    if "haproxy" in setups:
        haproxy = shutil.which("haproxy")
        text = subprocess.run([haproxy, "-v"], capture_output=True, text=True, check=False).stdout \
            if haproxy else ""
        # "HAProxy version 2.6.12-1+deb12u4 2026/10/17 - https://haproxy.org/"
        words = text.split()
        out["haproxy"] = words[2] if len(words) > 2 and words[1] == "version" else None
    return out


@dataclass
class RunningSetup:
    """A started set-up: its URL and the processes whose trees hold its server processes."""

    url: str
    roots: list[int]


@contextmanager
def running_setup(name: str, cfg: BalancerBenchConfig, cache: Path) -> Iterator[RunningSetup]:
    """Start set-up ``name`` with fresh processes; ready (``/readyz`` through its port) in the block."""
    logs = cache / "logs"
    env = dict(cfg.server_env)
    if name == "haproxy":
        with our_servers(cfg.processes, logs, env=env, proxy=True, log_name="haproxy-backend",
                         start_timeout=cfg.start_timeout, mode=cfg.haproxy_mode, balance=cfg.haproxy_balance,
                         threads=cfg.haproxy_threads, timeout=cfg.load.timeout + 30) as served:
            yield RunningSetup(url=served.url, roots=served.roots)
        return
    port = free_port()
    stop_signal = signal.SIGINT  # uvicorn's graceful stop
    if name == "uvicorn":
        cmd = uvicorn_command(port, cfg.processes, cfg.log_level)
    elif name == "gunicorn":
        cmd = gunicorn_command(port, cfg.processes, cfg.log_level, cfg.start_timeout)
        stop_signal = signal.SIGTERM  # gunicorn's
    else:
        raise ValueError(f"unknown set-up {name!r}; expected one of {', '.join(SETUPS)}")
    with running_server(cmd, port=port, ready_path=READY_PATH, log_path=logs / f"{name}.log", env=env,
                        cwd=REPO, start_timeout=cfg.start_timeout, stop_signal=stop_signal) as server:
        yield RunningSetup(url=server.url, roots=[server.process.pid])


# --- CPU time per process (/proc) ---------------------------------------------------------------


def parse_stat(text: str) -> tuple[str, int, float]:
    """(command name, parent pid, user + system CPU seconds) from a ``/proc/<pid>/stat`` line.

    The name is in parentheses and may hold spaces or parentheses itself: the fields after it
    are split from the last ``)``.
    """
    open_, close = text.index("("), text.rindex(")")
    name, rest = text[open_ + 1:close], text[close + 2:].split()
    # rest[0] is field 3 (state): ppid is field 4, utime and stime fields 14 and 15.
    return name, int(rest[1]), (int(rest[11]) + int(rest[12])) / _HZ


def _stats() -> dict[int, tuple[str, int, float]]:
    out = {}
    for entry in os.scandir("/proc"):
        if not entry.name.isdigit():
            continue
        try:
            out[int(entry.name)] = parse_stat(Path(entry.path, "stat").read_text())
        except (OSError, ValueError, IndexError):
            continue  # gone meanwhile
    return out


def tree_cpu(roots: list[int]) -> dict[str, float]:
    """CPU seconds so far of every process in the trees under ``roots``, keyed ``"pid name"``."""
    stats = _stats()
    children: dict[int, list[int]] = {}
    for pid, (_, ppid, _) in stats.items():
        children.setdefault(ppid, []).append(pid)
    out, todo = {}, [r for r in roots if r in stats]
    while todo:
        pid = todo.pop()
        name, _, cpu = stats[pid]
        out[f"{pid} {name}"] = cpu
        todo += children.get(pid, [])
    return out


def cpu_split(before: dict[str, float], after: dict[str, float], processes: int, seconds: float
              ) -> dict[str, Any]:
    """The measured run's CPU per process: the ``processes`` busiest are the servers, the rest the front.

    ``before`` and ``after`` are ``tree_cpu`` snapshots around the run. ``busiest_share`` is the
    busiest server's part of the servers' CPU (0.5 with two is an even split); CPU figures are in
    cores (CPU seconds per second of the run). ``changed`` lists processes that started or ended
    during the run (a worker replaced by its supervisor): such a run's split is not comparable.
    """
    deltas = {k: v - before.get(k, 0.0) for k, v in after.items()}
    ranked = sorted(deltas.items(), key=lambda kv: -kv[1])
    servers, front = ranked[:processes], ranked[processes:]
    total = sum(v for _, v in servers)
    per = (lambda v: v / seconds) if seconds > 0 else (lambda v: 0.0)
    return {
        "servers_cores": [round(per(v), 3) for _, v in servers],
        "busiest_share": (servers[0][1] / total) if servers and total > 0 else None,
        "front_cores": round(per(sum(v for _, v in front)), 3),
        "processes": {k: round(v, 3) for k, v in ranked},
        "changed": sorted(set(before) ^ set(after)),
    }


# --- the runs and their summary ------------------------------------------------------------------


def run_setup(name: str, cfg: BalancerBenchConfig, body_file: Path, cache: Path) -> dict[str, Any]:
    """Start one set-up, check its answer, run the load (warm-up, measured run), stop it."""
    body = body_file.read_bytes()
    with running_setup(name, cfg, cache) as setup:
        url = setup.url + "/suggest"
        answer = check_answer(url, body, timeout=cfg.load.timeout)

        def drain() -> None:
            check_answer(url, body, timeout=cfg.load.timeout + 60)

        snapshots: list[dict[str, float]] = []

        def probe() -> dict[str, float]:
            snapshots.append(tree_cpu(setup.roots))
            return snapshots[-1]

        row = run_wrk(url, body_file, cfg.connections, cfg.load, drain=drain, probe=probe)
    row.pop("counter_deltas", None)  # from the same snapshots; cpu_split also sees who came and went
    top = answer["suggestions"][0]["part_id"] if answer["suggestions"] else None
    cpu = cpu_split(snapshots[0], snapshots[1], cfg.processes, row["seconds"])
    if cpu["changed"]:
        log.warning("balancers: %s: processes started or ended during the run: %s", name, cpu["changed"])
    return {"setup": name, **row, "top_part": top, "cpu": cpu}


def _med(values: list[float | None]) -> float | None:
    vals = [v for v in values if v is not None]
    return statistics.median(vals) if vals else None


def summarize(runs: list[dict[str, Any]], setups: tuple[str, ...], reference: str = REFERENCE
              ) -> list[dict[str, Any]]:
    """Per set-up: medians (and ranges) over its rounds, and its medians relative to ``reference``'s.

    ``vs_reference``: throughput as this / reference, p50 and p99 as reference / this, so above 1
    means this set-up did better than the reference (None without the reference in the runs).
    """
    rows = []
    for name in setups:
        mine = [r for r in runs if r["setup"] == name]
        if not mine:
            continue
        rps = [r["throughput_rps"] for r in mine]
        p99 = [r["p99_ms"] for r in mine if r["p99_ms"] is not None]
        rows.append({
            "setup": name, "runs": len(mine),
            "throughput_rps": _med(rps), "throughput_range": [min(rps), max(rps)],
            "p50_ms": _med([r["p50_ms"] for r in mine]), "p99_ms": _med(list(p99)),
            "p99_range": [min(p99), max(p99)] if p99 else None,
            "errors": sum(r["errors"] for r in mine),
            "busiest_share": _med([r["cpu"]["busiest_share"] for r in mine]),
            "front_cores": _med([r["cpu"]["front_cores"] for r in mine]),
        })
    ref = next((r for r in rows if r["setup"] == reference), None)
    for row in rows:
        row["reference"] = reference
        row["vs_reference"] = None if ref is None else {
            "throughput": _ratio(row["throughput_rps"], ref["throughput_rps"]),
            "p50": _ratio(ref["p50_ms"], row["p50_ms"]),
            "p99": _ratio(ref["p99_ms"], row["p99_ms"]),
        }
    return rows


def _ratio(a: float | None, b: float | None) -> float | None:
    return None if a is None or not b else a / b


def run_balancer_bench(query: BenchQuery, cfg: BalancerBenchConfig, cache: Path) -> dict[str, Any]:
    """Every set-up once per round, rotated; the runs, their summary and the tools' versions."""
    missing = missing_tools(cfg.setups)
    if missing:
        raise RuntimeError("the balancer benchmark needs: " + "; ".join(missing))
    body_file = write_bodies(query, cache, (cfg.body,))[cfg.body]
    runs = []
    for r in range(cfg.rounds):
        for position, name in enumerate(round_order(cfg.setups, r)):
            log.info("balancers: round %d/%d, %s", r + 1, cfg.rounds, name)
            runs.append({"round": r, "position": position, **run_setup(name, cfg, body_file, cache)})
    tops = {r["top_part"] for r in runs}
    return {
        "query": {"source": query.source, "points": len(query.points), "k": query.k},
        "versions": tool_versions(cfg.setups),
        "same_top_part": len(tops) == 1,
        "runs": runs,
        "summary": summarize(runs, cfg.setups),
    }
