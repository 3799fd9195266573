"""Benchmark b: HTTP load on loopback against ``complementme serve`` started as a subprocess.

For each body kind (JSON list of points, base64 float32) and each concurrency level, wrk keeps
that many connections busy for a fixed time after a warm-up: throughput, p50, p99 and errors.
The server runs with the service's defaults (one worker) plus the environment given in
``server_env`` (access logging off by default: it would be the bench measuring its log file).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

from bench.query import BODY_KINDS, BenchQuery
from bench.server import Server, complementme_command, free_port, running_server
from bench.wrk import LoadSettings, run_wrk

log = logging.getLogger(__name__)

DEFAULT_SERVER_ENV = {"COMPLEMENTME_LOG_LEVEL": "warning"}


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


def load_levels(url: str, bodies: dict[str, Path], concurrency: tuple[int, ...], load: LoadSettings
                ) -> list[dict[str, Any]]:
    """wrk at every (body kind, concurrency) pair against ``url``.

    After every wrk run one more request is sent and awaited: it is answered once the requests
    wrk abandoned have left the server's queue (the gate is first come, first served).
    """
    rows = []
    for kind, path in bodies.items():
        body = path.read_bytes()

        def drain(body: bytes = body) -> None:
            check_answer(url, body, timeout=load.timeout + 60)

        for c in concurrency:
            log.info("http: %s body, concurrency %d, %.0f s (+%.0f s warm-up)", kind, c, load.duration,
                     load.warmup)
            rows.append({"body": kind, **run_wrk(url, path, c, load, drain=drain)})
    return rows


def run_http_bench(query: BenchQuery, cfg: HttpBenchConfig, cache: Path) -> dict[str, Any]:
    """Start our service, check one answer, then run every load level."""
    bodies = write_bodies(query, cache, cfg.bodies)
    with our_service(cache, dict(cfg.server_env)) as server:
        answer = check_answer(server.url + "/suggest", bodies[cfg.bodies[0]].read_bytes())
        levels = load_levels(server.url + "/suggest", bodies, cfg.concurrency, cfg.load)
    return {
        "query": {"source": query.source, "points": len(query.points), "k": query.k},
        "top_part": answer["suggestions"][0]["part_id"] if answer["suggestions"] else None,
        "model_version": answer.get("model_version"),
        "levels": levels,
    }
