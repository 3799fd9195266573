"""Soak under mixed hostile load (issue 16): goodput, /healthz p99 and RSS of a live server.

One worker on the shipped artifacts, loopback only, about a minute in all. Three phases of
``SECONDS`` each, every one with a /healthz probe every 50 ms:

1. ``/suggest`` at concurrency 32, closed loop (a 503 is retried at once);
2. the same at concurrency 128: shedding must be cheap, so goodput stays near (1) (the issue:
   at least 80%) and /healthz answers promptly (the issue: p99 under 50 ms);
3. (1) beside hostile clients: 20 slow bodies on /place and 20 on /suggest, 2 clients whose
   options fail in the ranking (mode_weights all zero), and one costly /suggest/batch after
   another (8 refined k = 20 queries). The slow and poisoning clients send from another
   loopback address (``HOSTILE``), as hostile clients on a network would: the server's error
   budget (``client_error_burst``) refuses the poisoning ones, not the normal clients.

The numbers are printed (``pytest -s``) and go in docs/performance.md, "Hostile load"; the test
asserts behaviour (answers, the error budget's refusals, RSS), not speed.
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import numpy as np
import orjson
import pytest
from catalog_testkit import LiveServer
from load_testkit import LoadResult, closed_loop, http_request, probe_elsewhere, slow_clients
from service_testkit import AssemblyQuery

from service.geometry.inputs import points_to_base64
from service.suggest.engine import SuggestionEngine

pytestmark = pytest.mark.slow

SECONDS = 8.0
HOSTILE = "127.0.0.2"


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError(f"no VmRSS in /proc/{pid}/status")


def _post(path: str, body: dict[str, Any]) -> bytes:
    return http_request("POST", path, orjson.dumps(body))


async def _with_health(port: int, load: Any) -> tuple[Any, list[float]]:
    health = http_request("GET", "/healthz")
    return tuple(await asyncio.gather(load, probe_elsewhere(port, health, every=0.05, seconds=SECONDS)))


def test_soak_under_mixed_hostile_load(artifacts: Path, tmp_path: Path, engine: SuggestionEngine,
                                       query: AssemblyQuery) -> None:
    server = LiveServer(artifacts, tmp_path / "data").start()
    assert server.proc is not None
    pid, port = server.proc.pid, server.port
    points = points_to_base64(query.points)
    suggest = _post("/suggest", {"points_base64": points, "k": 10})
    poison = _post("/suggest", {"points_base64": points, "k": 10,
                                "mode_weights": [0] * engine.artifacts.n_modes})
    heavy = _post("/suggest/batch", {"items": [{"points_base64": points, "k": 20,
                                                "refine_contact": True}] * 8})
    place = _post("/place", {"points_base64": points, "part_ids": [query.kept[0]]})
    rows: list[tuple[str, LoadResult, list[float], float]] = []
    try:
        asyncio.run(closed_loop(port, suggest, 8, 2.0))  # warm: caches, allocator
        rss_start = _rss_mb(pid)
        for name, concurrency in (("c=32", 32), ("c=128", 128)):
            result, health = asyncio.run(_with_health(port, closed_loop(port, suggest, concurrency, SECONDS)))
            rows.append((name, result, health, _rss_mb(pid)))

        async def hostile() -> tuple[LoadResult, LoadResult, LoadResult]:
            async with (slow_clients(port, place, 20, 0.5, source=HOSTILE),
                        slow_clients(port, suggest, 20, 0.5, source=HOSTILE)):
                return tuple(await asyncio.gather(  # type: ignore[return-value]
                    closed_loop(port, suggest, 32, SECONDS),
                    closed_loop(port, poison, 2, SECONDS, source=HOSTILE),
                    closed_loop(port, heavy, 1, SECONDS)))

        (normal, poisoned, costly), health = asyncio.run(_with_health(port, hostile()))
        rows.append(("c=32 + hostile", normal, health, _rss_mb(pid)))
    finally:
        server.stop()

    print(f"\nRSS after warm-up: {rss_start:.0f} MB")
    print("| Load | /suggest goodput (req/s) | p50 | p99 | 503s | /healthz p99 | RSS after |")
    for name, result, health, rss in rows:
        print(f"| {name} | {result.goodput:.1f} | {1000 * result.p(50):.0f} ms | "
              f"{1000 * result.p(99):.0f} ms | {result.statuses[503]} | "
              f"{1000 * np.percentile(health, 99):.1f} ms | {rss:.0f} MB |")
    poison_rate = sum(poisoned.statuses.values()) / poisoned.seconds
    print(f"hostile: poison {dict(poisoned.statuses)} ({poison_rate:.0f} answers a second), "
          f"heavy batches {dict(costly.statuses)}")

    (_, at32, _, _), (_, at128, health128, _), (_, mixed, health_mixed, rss_end) = rows
    for result in (at32, at128, mixed):
        assert set(result.statuses) <= {200, 503} and result.errors == 0, (result.statuses, result.errors)
    # The poisoning clients use up their error budget and are then refused (429) before parsing.
    assert set(poisoned.statuses) == {422, 429} and set(costly.statuses) <= {200, 503}, poisoned.statuses
    # Goodput and /healthz latency are measured and printed, not asserted (a busy host must not
    # fail the suite; docs/performance.md has the figures against the 80% and 50 ms).
    # What is asserted is behaviour: every request answered (200 or a 503 to retry), the hostile
    # phase's normal clients served, memory bounded.
    assert at128.statuses[200] > 0 and mixed.statuses[200] > 0 and health128 and health_mixed
    assert rss_end - rss_start < 150, f"RSS grew from {rss_start:.0f} to {rss_end:.0f} MB"
