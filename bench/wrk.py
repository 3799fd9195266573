"""Run wrk (a real load generator, closed loop: each connection keeps one request in flight).

wrk runs with one thread by default: on a 2-core machine every core wrk takes is a core the
server does not get, and one wrk thread drives thousands of requests per second.
"""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

LUA_SCRIPT = Path(__file__).resolve().parent / "post.lua"
MARKER = "BENCH_JSON "


@dataclass(frozen=True)
class LoadSettings:
    """How hard and how long one load level runs (every bound is a setting)."""

    duration: float = 10.0      # seconds measured per level
    warmup: float = 3.0         # seconds of load first, not measured (0: none)
    threads: int = 1            # wrk threads (at most the connection count)
    timeout: float = 30.0       # seconds after which wrk counts a request as timed out

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


def wrk_binary() -> str:
    path = shutil.which("wrk")
    if path is None:
        raise RuntimeError("wrk is not installed (Debian: apt-get install wrk); the HTTP benchmarks need it")
    return path


def wrk_command(url: str, body_file: Path, connections: int, duration: float, threads: int,
                timeout: float) -> list[str]:
    """The wrk command line for ``connections`` connections posting ``body_file`` to ``url``."""
    if connections < 1:
        raise ValueError(f"connections must be at least 1, found {connections}")
    return [wrk_binary(), "-t", str(max(1, min(threads, connections))), "-c", str(connections),
            "-d", f"{max(1, round(duration))}s", "--timeout", f"{max(1, round(timeout))}s", "--latency",
            "-s", str(LUA_SCRIPT), url, "--", str(body_file)]


def parse_wrk_output(stdout: str) -> dict[str, Any]:
    """The script's summary line as numbers: throughput (req/s), latency in ms, error counts.

    ``throughput_rps`` counts 2xx answers only (``answers_rps`` all answers); the latency
    percentiles are over every answer, so with errors they include the (fast) 503s. ``errors`` is
    every failed request: socket errors (connect, read, write), timeouts and non-2xx answers.
    Latencies are None when nothing was answered.
    """
    lines = [ln for ln in stdout.splitlines() if ln.startswith(MARKER)]
    if not lines:
        raise ValueError(f"wrk printed no {MARKER.strip()} line; its output was:\n{stdout[-2000:]}")
    raw = json.loads(lines[-1][len(MARKER):])
    seconds = raw["duration_us"] / 1e6
    done = raw["requests"] > 0  # with no answer at all, wrk's percentiles are zeros, not latencies
    lat = raw["latency_us"]

    def ms(key: str) -> float | None:
        return float(lat[key]) / 1000 if done else None

    socket_errors = raw["connect_errors"] + raw["read_errors"] + raw["write_errors"]
    return {
        "requests": raw["requests"],
        "seconds": seconds,
        # Throughput counts successful answers only: a fast 503 is not a served request.
        "throughput_rps": (raw["requests"] - raw["non2xx"]) / seconds if seconds > 0 else 0.0,
        "answers_rps": raw["requests"] / seconds if seconds > 0 else 0.0,
        "p50_ms": ms("p50"), "p90_ms": ms("p90"), "p99_ms": ms("p99"), "p999_ms": ms("p999"),
        "mean_ms": ms("mean"), "max_ms": ms("max"),
        "non2xx": raw["non2xx"],
        "statuses": {str(k): v for k, v in sorted(raw.get("statuses", {}).items())},
        "timeouts": raw["timeouts"], "socket_errors": socket_errors,
        "errors": socket_errors + raw["timeouts"] + raw["non2xx"],
        "bytes": raw["bytes"],
    }


def run_wrk(url: str, body_file: Path, connections: int, load: LoadSettings,
            drain: Callable[[], object] | None = None,
            probe: Callable[[], dict[str, float]] | None = None) -> dict[str, Any]:
    """One measured load level (after its warm-up); returns ``parse_wrk_output``'s summary.

    ``drain`` runs after each wrk run: wrk closes its connections with requests in flight, which
    the server still finishes (and which still hold its inference slots), so the next run would
    otherwise start against a busy server and see its queue full. ``probe`` reads server
    counters just before and just after the measured run; their differences are returned as
    ``counter_deltas``.
    """
    if load.warmup > 0:
        _run(wrk_command(url, body_file, connections, load.warmup, load.threads, load.timeout), load)
        if drain is not None:
            drain()
    before = probe() if probe is not None else {}
    out = _run(wrk_command(url, body_file, connections, load.duration, load.threads, load.timeout), load)
    after = probe() if probe is not None else {}
    if drain is not None:
        drain()
    res = parse_wrk_output(out)
    if probe is not None:
        res["counter_deltas"] = {k: v - before.get(k, 0.0) for k, v in after.items()}
    log.info("wrk c=%d: %.0f req/s, p50 %s ms, p99 %s ms, %d errors %s", connections, res["throughput_rps"],
             res["p50_ms"], res["p99_ms"], res["errors"], res["statuses"])
    return {"connections": connections, **res}


def _run(cmd: list[str], load: LoadSettings) -> str:
    limit = load.duration + load.warmup + load.timeout + 30
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=limit, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"wrk failed with status {proc.returncode}: {proc.stderr.strip() or proc.stdout}")
    return proc.stdout
