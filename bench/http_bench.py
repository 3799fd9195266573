"""Benchmark b: HTTP load on loopback against our service started as subprocesses.

For each body kind (JSON list of points, base64 float32) and each concurrency level, wrk keeps
that many connections busy for a fixed time after a warm-up: throughput, p50, p99 and errors.
The service runs as it is meant to run on a machine of its own: one ``complementme serve`` per
usable core (``processes``) behind HAProxy with the shipped configuration
(``bench.server.our_servers``, ``docker/haproxy/haproxy.cfg``), with the service's defaults plus
the environment given in ``server_env``: by default access logging off (it would be the bench
measuring its log file).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

from bench.machine import usable_cores
from bench.query import BODY_KINDS, BenchQuery
from bench.server import OurServers, our_servers
from bench.wrk import LoadSettings, run_wrk

log = logging.getLogger(__name__)

DEFAULT_SERVER_ENV = {"COMPLEMENTME_LOG_LEVEL": "warning"}


@dataclass(frozen=True)
class HttpBenchConfig:
    """Settings of the HTTP benchmark."""

    concurrency: tuple[int, ...] = (1, 8, 32, 64)
    bodies: tuple[str, ...] = BODY_KINDS
    load: LoadSettings = field(default_factory=LoadSettings)
    processes: int = field(default_factory=usable_cores)  # server processes, behind HAProxy if several
    server_env: tuple[tuple[str, str], ...] = tuple(DEFAULT_SERVER_ENV.items())

    def as_dict(self) -> dict[str, Any]:
        return {"concurrency": list(self.concurrency), "bodies": list(self.bodies),
                "load": self.load.as_dict(), "processes": self.processes, "server_env": dict(self.server_env)}


def write_bodies(query: BenchQuery, folder: Path, kinds: tuple[str, ...]) -> dict[str, Path]:
    """The request bodies as files for wrk's script, one per kind."""
    folder.mkdir(parents=True, exist_ok=True)
    out = {}
    for kind in kinds:
        path = folder / f"body-{kind}.json"
        path.write_bytes(query.body(kind))
        out[kind] = path
    return out


@contextmanager
def our_service(cache: Path, server_env: dict[str, str], processes: int = 1,
                start_timeout: float = 180.0) -> Iterator[OurServers]:
    """``processes`` ``complementme serve`` on free ports, behind HAProxy when there are several;
    ready (``/readyz``) when the block starts."""
    with our_servers(processes, cache, env=server_env, start_timeout=start_timeout) as served:
        yield served


def check_answer(url: str, body: bytes, timeout: float = 30.0) -> dict[str, Any]:
    """POST one body and return the JSON answer; ``RuntimeError`` unless the status is 200."""
    r = httpx.post(url, content=body, headers={"Content-Type": "application/json"}, timeout=timeout)
    if r.status_code != 200:
        raise RuntimeError(f"POST {url} answered {r.status_code}: {r.text[:500]}")
    return r.json()


BATCH_PREFIX = "complementme_batch"  # the service's micro-batching histograms in /metrics


def batch_counters(metrics_urls: Sequence[str]) -> dict[str, float]:
    """Sums and counts of the service's ``complementme_batch*`` histograms, summed over the server
    processes' ``/metrics`` (one that does not answer adds nothing)."""
    out: dict[str, float] = {}
    for url in metrics_urls:
        try:
            r = httpx.get(url, timeout=10.0)
        except httpx.HTTPError:
            continue
        if r.status_code == 200:
            for name, value in parse_batch_counters(r.text).items():
                out[name] = out.get(name, 0.0) + value
    return out


def parse_batch_counters(text: str) -> dict[str, float]:
    """``_sum`` and ``_count`` samples of ``complementme_batch*`` histograms in Prometheus text, summed
    over labels."""
    from prometheus_client.parser import text_string_to_metric_families

    out: dict[str, float] = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            if s.name.startswith(BATCH_PREFIX) and s.name.endswith(("_sum", "_count")):
                out[s.name] = out.get(s.name, 0.0) + float(s.value)
    return out


def batch_means(deltas: dict[str, float]) -> dict[str, float]:
    """Mean of each histogram over one run, from the differences of its ``_sum`` and ``_count``.

    ``complementme_batch_size`` gives queries per engine call; queue wait is reported in ms.
    """
    out: dict[str, float] = {}
    for name, total in deltas.items():
        if not name.endswith("_sum"):
            continue
        base = name[: -len("_sum")]
        count = deltas.get(base + "_count", 0.0)
        if count > 0:
            mean = total / count
            if base.endswith("_seconds"):
                base, mean = base[: -len("_seconds")] + "_ms", 1000 * mean
            out[base.removeprefix("complementme_")] = mean
    return out


def load_levels(url: str, bodies: dict[str, Path], concurrency: tuple[int, ...], load: LoadSettings,
                metrics_urls: Sequence[str] = ()) -> list[dict[str, Any]]:
    """wrk at every (body kind, concurrency) pair against ``url``.

    After every wrk run one more request is sent and awaited: it is answered once the requests
    wrk abandoned have left the server's queue (the gate is first come, first served). With
    ``metrics_urls`` (every server process's /metrics), the mean micro-batch size and queue wait
    of each measured run are recorded.
    """
    probe = (lambda: batch_counters(metrics_urls)) if metrics_urls else None
    rows = []
    for kind, path in bodies.items():
        body = path.read_bytes()

        def drain(body: bytes = body) -> None:
            check_answer(url, body, timeout=load.timeout + 60)

        for c in concurrency:
            log.info("http: %s body, concurrency %d, %.0f s (+%.0f s warm-up)", kind, c, load.duration,
                     load.warmup)
            row = run_wrk(url, path, c, load, drain=drain, probe=probe)
            if "counter_deltas" in row:
                row["server_means"] = batch_means(row.pop("counter_deltas"))
            rows.append({"body": kind, **row})
    return rows


def run_http_bench(query: BenchQuery, cfg: HttpBenchConfig, cache: Path) -> dict[str, Any]:
    """Start our service, check one answer, then run every load level."""
    bodies = write_bodies(query, cache, cfg.bodies)
    with our_service(cache, dict(cfg.server_env), cfg.processes) as server:
        answer = check_answer(server.url + "/suggest", bodies[cfg.bodies[0]].read_bytes())
        levels = load_levels(server.url + "/suggest", bodies, cfg.concurrency, cfg.load,
                             metrics_urls=server.metrics_urls)
    return {
        "query": {"source": query.source, "points": len(query.points), "k": query.k},
        "top_part": answer["suggestions"][0]["part_id"] if answer["suggestions"] else None,
        "model_version": answer.get("model_version"),
        "levels": levels,
    }
