"""Benchmark b: HTTP load on loopback against ``complementme serve`` started as a subprocess.

For each body kind (JSON list of points, base64 float32) and each concurrency level, wrk keeps
that many connections busy for a fixed time after a warm-up: throughput, p50, p99 and errors.
The server runs with the service's defaults plus the environment given in ``server_env``: by
default one worker process per usable core (how the service is meant to be run on a machine of
its own; ``service/serve/workers.py``) and access logging off (it would be the bench measuring its log
file).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

from bench.machine import usable_cores
from bench.query import BODY_KINDS, BenchQuery
from bench.server import Server, complementme_command, free_port, running_server
from bench.wrk import LoadSettings, run_wrk

log = logging.getLogger(__name__)

DEFAULT_SERVER_ENV = {"COMPLEMENTME_LOG_LEVEL": "warning", "COMPLEMENTME_WORKERS": str(usable_cores())}


@dataclass(frozen=True)
class HttpBenchConfig:
    """Settings of the HTTP benchmark."""

    concurrency: tuple[int, ...] = (1, 8, 32, 64)
    bodies: tuple[str, ...] = BODY_KINDS
    load: LoadSettings = field(default_factory=LoadSettings)
    server_env: tuple[tuple[str, str], ...] = tuple(DEFAULT_SERVER_ENV.items())

    def as_dict(self) -> dict[str, Any]:
        return {"concurrency": list(self.concurrency), "bodies": list(self.bodies),
                "load": self.load.as_dict(), "server_env": dict(self.server_env)}


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
def our_service(cache: Path, server_env: dict[str, str], start_timeout: float = 180.0) -> Iterator[Server]:
    """``complementme serve`` on a free port, ready (``/readyz``) when the block starts."""
    port = free_port()
    cmd = [*complementme_command(), "serve", "--host", "127.0.0.1", "--port", str(port)]
    with running_server(cmd, port=port, ready_path="/readyz", log_path=cache / "serve.log",
                        env=server_env, start_timeout=start_timeout) as server:
        yield server


def check_answer(url: str, body: bytes, timeout: float = 30.0) -> dict[str, Any]:
    """POST one body and return the JSON answer; ``RuntimeError`` unless the status is 200."""
    r = httpx.post(url, content=body, headers={"Content-Type": "application/json"}, timeout=timeout)
    if r.status_code != 200:
        raise RuntimeError(f"POST {url} answered {r.status_code}: {r.text[:500]}")
    return r.json()


BATCH_PREFIX = "complementme_batch"  # the service's micro-batching histograms in /metrics


def batch_counters(metrics_url: str) -> dict[str, float]:
    """Sums and counts of the service's ``complementme_batch*`` histograms ({} without /metrics)."""
    try:
        r = httpx.get(metrics_url, timeout=10.0)
    except httpx.HTTPError:
        return {}
    return parse_batch_counters(r.text) if r.status_code == 200 else {}


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
                metrics_url: str | None = None) -> list[dict[str, Any]]:
    """wrk at every (body kind, concurrency) pair against ``url``.

    After every wrk run one more request is sent and awaited: it is answered once the requests
    wrk abandoned have left the server's queue (the gate is first come, first served). With
    ``metrics_url``, the mean micro-batch size and queue wait of each measured run are recorded.
    """
    probe = (lambda: batch_counters(metrics_url)) if metrics_url else None
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
    with our_service(cache, dict(cfg.server_env)) as server:
        answer = check_answer(server.url + "/suggest", bodies[cfg.bodies[0]].read_bytes())
        levels = load_levels(server.url + "/suggest", bodies, cfg.concurrency, cfg.load,
                             metrics_url=server.url + "/metrics")
    return {
        "query": {"source": query.source, "points": len(query.points), "k": query.k},
        "top_part": answer["suggestions"][0]["part_id"] if answer["suggestions"] else None,
        "model_version": answer.get("model_version"),
        "levels": levels,
    }
