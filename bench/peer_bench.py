"""Benchmark d: our service against the peer baseline (``bench.peer.app``), in the same run.

The peer runs as such an app is started, one uvicorn process (torch itself uses every core for
its operators); ours as the HTTP benchmark starts it, one ``complementme serve`` per usable core
behind HAProxy. One after the other on loopback (never at the same time: on two cores they would
share the CPU), under the same wrk load with the JSON body (the peer knows no base64). Reported:
each side's throughput and latency, and ours as ratios to the peer's (throughput ours / peer;
latency peer / ours, so larger is better for us in both). Before the load, both answer the
benchmark query once: the peer's top part (it ranks by the mixture likelihood alone) should be
the most likely part of our answer (whose order also weighs the fit key and the complement
check): a sanity check that both serve the same model.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bench.http_bench import DEFAULT_SERVER_ENV, check_answer, load_levels, our_service, write_bodies
from bench.machine import usable_cores
from bench.query import REPO, BenchQuery
from bench.server import Server, free_port, running_server
from bench.wrk import LoadSettings

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PeerBenchConfig:
    """Settings of the peer comparison."""

    concurrency: tuple[int, ...] = (1, 32)
    load: LoadSettings = field(default_factory=LoadSettings)
    artifacts: Path = REPO / "exported"             # the model (graphs) and catalog both serve
    processes: int = field(default_factory=usable_cores)  # ours: server processes, behind HAProxy if several
    server_env: tuple[tuple[str, str], ...] = tuple(DEFAULT_SERVER_ENV.items())

    def as_dict(self) -> dict[str, Any]:
        return {"concurrency": list(self.concurrency), "load": self.load.as_dict(),
                "artifacts": str(self.artifacts), "processes": self.processes,
                "server_env": dict(self.server_env), "body": "json"}


@contextmanager
def peer_service(cache: Path, artifacts: Path, start_timeout: float = 180.0) -> Iterator[Server]:
    """The peer app under uvicorn (1 worker, no access log) on a free port, ready when the block starts."""
    port = free_port()
    cmd = [sys.executable, "-m", "uvicorn", "bench.peer.app:app", "--host", "127.0.0.1", "--port", str(port),
           "--workers", "1", "--log-level", "warning", "--no-access-log"]
    env = {"PEER_ARTIFACTS": str(artifacts)}
    with running_server(cmd, port=port, ready_path="/healthz", log_path=cache / "peer.log", env=env,
                        cwd=REPO, start_timeout=start_timeout) as server:
        yield server


def ratios(ours: list[dict[str, Any]], peer: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Ours relative to the peer at each concurrency both were measured at.

    ``throughput`` is ours / peer; ``p50`` and ``p99`` are peer / ours (latency speed-ups), so a
    value above 1 favours us in every column. A zero denominator gives None.
    """
    by_c = {row["connections"]: row for row in peer}
    out = []
    for row in ours:
        p = by_c.get(row["connections"])
        if p is None:
            continue
        out.append({
            "connections": row["connections"],
            "throughput": _div(row["throughput_rps"], p["throughput_rps"]),
            "p50": _div(p["p50_ms"], row["p50_ms"]),
            "p99": _div(p["p99_ms"], row["p99_ms"]),
        })
    return out


def _div(a: float | None, b: float | None) -> float | None:
    return None if a is None or not b else a / b


def run_peer_bench(query: BenchQuery, cfg: PeerBenchConfig, cache: Path) -> dict[str, Any]:
    """The peer, then our service, under the same load; the ratios and the top-part check."""
    bodies = write_bodies(query, cache, ("json",))
    body = bodies["json"].read_bytes()
    with peer_service(cache, cfg.artifacts) as peer:
        peer_answer = check_answer(peer.url + "/suggest", body, timeout=cfg.load.timeout)
        peer_levels = load_levels(peer.url + "/suggest", bodies, cfg.concurrency, cfg.load)
    with our_service(cache, dict(cfg.server_env), cfg.processes) as ours:
        our_answer = check_answer(ours.url + "/suggest", body, timeout=cfg.load.timeout)
        our_levels = load_levels(ours.url + "/suggest", bodies, cfg.concurrency, cfg.load,
                                 metrics_urls=ours.metrics_urls)
    peer_top = [s["part_id"] for s in peer_answer["suggestions"]]
    ours_sorted = our_answer["suggestions"]
    our_top = [s["part_id"] for s in ours_sorted]
    likeliest = max(ours_sorted, key=lambda s: s["score"])["part_id"] if ours_sorted else None
    return {
        "query": {"source": query.source, "points": len(query.points), "k": query.k},
        "sanity": {"peer_top": peer_top[:3], "our_top": our_top[:3], "our_most_likely": likeliest,
                   "same_top_part": bool(peer_top and likeliest == peer_top[0])},
        "peer": peer_levels,
        "ours": our_levels,
        "ratios": ratios(our_levels, peer_levels),
    }
