"""Benchmark f: our service against an established serving framework on the same graphs (issue 20).

The framework peer (``bench/framework/``) serves the exported ONNX graphs, FAISS index and
catalog through BentoML's adaptive batching or LitServe's batching, as each documents, with
the numbers of our settings (``peer_config``) and one worker process per core, like our service
here (one ``complementme serve`` per core behind HAProxy, as the HTTP benchmark starts it). Each
peer, then our service, runs alone on loopback under the same wrk load (JSON body, every
concurrency level); before the load, each answers the benchmark query once and its top-k part
ids and translations are compared with ours. Ratios as in benchmark d: throughput ours / peer,
latency peer / ours (above 1 favours us).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bench.framework.pipeline import CONFIG_ENV, PeerConfig
from bench.framework.venv import FRAMEWORKS, ensure_venv, installed_versions
from bench.http_bench import DEFAULT_SERVER_ENV, check_answer, load_levels, our_service, write_bodies
from bench.machine import usable_cores
from bench.peer_bench import ratios
from bench.query import REPO, BenchQuery
from bench.server import Server, free_port, running_server
from bench.wrk import LoadSettings
from service.settings import Settings

log = logging.getLogger(__name__)

# BentoML's max_latency_ms is not how long its dispatcher waits for a batch (its regression of
# recent batch times decides that) but a deadline: a request it expects to miss it gets a 503.
# BentoML's default, 60 s: the documentation's example, 1 s, shed a third of the requests at
# c = 32 on a loaded 2-core host (smoke run), which would measure load shedding, not serving.
BENTOML_MAX_LATENCY_MS = 60_000.0
TRANSLATION_TOLERANCE = 1e-4  # canonical units; the same graphs on the same inputs, batched differently


@dataclass(frozen=True)
class FrameworkBenchConfig:
    """Settings of the framework comparison."""

    frameworks: tuple[str, ...] = ("bentoml", "litserve")
    concurrency: tuple[int, ...] = (1, 8, 32, 64)
    load: LoadSettings = field(default_factory=LoadSettings)
    workers: int = field(default_factory=usable_cores)
    server_env: tuple[tuple[str, str], ...] = tuple(DEFAULT_SERVER_ENV.items())

    def as_dict(self) -> dict[str, Any]:
        return {"frameworks": list(self.frameworks), "concurrency": list(self.concurrency),
                "load": self.load.as_dict(), "workers": self.workers,
                "server_env": dict(self.server_env), "body": "json"}


def peer_config(settings: Settings, framework: str, workers: int) -> PeerConfig:
    """The peer's numbers, taken from our settings so that both sides answer alike and batch alike.

    Batching: at most ``batch_max_size`` requests per batch on both sides; LitServe waits at most
    ``batch_max_wait_ms`` for a batch to fill, as our micro-batcher does, while BentoML's
    ``max_latency_ms`` bounds a request's whole time (see ``BENTOML_MAX_LATENCY_MS``).
    """
    s = settings
    wait = BENTOML_MAX_LATENCY_MS if framework == "bentoml" else s.batch_max_wait_ms
    return PeerConfig(
        artifacts=str(s.artifacts), seed=s.seed, neighbours_per_mode=s.neighbours_per_mode,
        complement_candidates=s.complement_candidates, complement_part_samples=s.complement_part_samples,
        complement_cover_distance=s.complement_cover_distance,
        complement_cover_share=s.complement_cover_share, suggest_order=s.suggest_order,
        share_min_mode_weight=s.share_min_mode_weight, share_order_head=s.share_order_head,
        share_spread_sigmas=s.share_spread_sigmas, scale_min=s.scale_min, scale_max=s.scale_max,
        rank_scale_weight=s.rank_scale_weight, rank_move_weight=s.rank_move_weight,
        infer_category=s.infer_category, category_min_confidence=s.category_min_confidence,
        faiss_blas_threshold=s.faiss_blas_threshold, max_k=s.max_k, default_k=s.default_k,
        min_points=s.min_points, max_points=s.max_points, max_batch_size=s.batch_max_size,
        max_latency_ms=wait, workers=workers)


@contextmanager
def framework_peer(framework: str, cfg: PeerConfig, cache: Path, start_timeout: float = 300.0
                   ) -> Iterator[Server]:
    """The framework peer on a free loopback port, ready when the block starts."""
    if framework not in FRAMEWORKS:
        raise ValueError(f"unknown framework {framework!r}; expected one of {', '.join(FRAMEWORKS)}")
    python = ensure_venv()
    port = free_port()
    if framework == "bentoml":
        cmd = [str(python.parent / "bentoml"), "serve", "bench.framework.bentoml_service:Suggest",
               "--host", "127.0.0.1", "--port", str(port)]
        ready = "/readyz"
    else:
        cmd = [str(python), "-m", "bench.framework.litserve_api", "--port", str(port)]
        ready = "/health"
    path = os.pathsep.join(p for p in (str(REPO), os.environ.get("PYTHONPATH", "")) if p)
    env = {CONFIG_ENV: cfg.to_json(), "PYTHONPATH": path,
           # One worker process per core, each single-threaded, as ours (settings blas_threads,
           # faiss_threads): the frameworks' request threads would otherwise each start an
           # OpenMP team (FAISS) and BLAS threads per core (a batch of one took 85 ms, not 8 ms,
           # in BentoML's worker without these).
           "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
           # BentoML asks before sending usage statistics; a bench sends none.
           "BENTOML_DO_NOT_TRACK": "True", "BENTOML_HOME": str(cache / "bentoml-home")}
    children: list[int] = []
    try:
        with running_server(cmd, port=port, ready_path=ready, log_path=cache / f"{framework}.log", env=env,
                            cwd=REPO, start_timeout=start_timeout) as server:
            try:
                yield server
            finally:
                children = descendants(server.process.pid)
    finally:
        # Both frameworks run worker processes under the one started here; on a loaded machine its
        # graceful stop can outlast running_server's patience (SIGKILL after 15 s), which would
        # leave workers behind to take CPU from the next server measured.
        _kill_leftovers(children, marker=str(python.parent.parent))


def descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (children, their children, ...), read from /proc."""
    parent: dict[int, int] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        parent[int(stat.parent.name)] = int(fields[1])
    found, frontier = [], [pid]
    while frontier:
        kids = [p for p, pp in parent.items() if pp in frontier]
        found += kids
        frontier = kids
    return found


def _kill_leftovers(pids: list[int], marker: str) -> None:
    """SIGKILL the processes of ``pids`` still alive whose command line holds ``marker``."""
    for pid in pids:
        try:
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().decode(errors="replace")
        except OSError:
            continue  # gone
        if marker in cmdline:
            log.warning("framework peer: killing leftover worker %d", pid)
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


def compare_answers(peer: dict[str, Any], ours: dict[str, Any], tolerance: float = TRANSLATION_TOLERANCE
                    ) -> dict[str, Any]:
    """Whether two /suggest answers hold the same parts in the same order, placed alike."""
    p, o = peer["suggestions"], ours["suggestions"]
    same_ids = [s["part_id"] for s in p] == [s["part_id"] for s in o]
    gap = max((abs(a - b) for sp, so in zip(p, o, strict=False)
               for a, b in zip(sp["translation"], so["translation"], strict=True)), default=0.0)
    return {"peer_ids": [s["part_id"] for s in p], "our_ids": [s["part_id"] for s in o],
            "same_ids": same_ids, "max_translation_gap": gap,
            "match": bool(same_ids and len(p) == len(o) and gap <= tolerance)}


def run_framework_bench(query: BenchQuery, cfg: FrameworkBenchConfig, cache: Path,
                        settings: Settings) -> dict[str, Any]:
    """Every framework peer, then our service, under the same load; answers compared, ratios."""
    bodies = write_bodies(query, cache, ("json",))
    body = bodies["json"].read_bytes()
    peers: dict[str, dict[str, Any]] = {}
    for framework in cfg.frameworks:
        with framework_peer(framework, peer_config(settings, framework, cfg.workers), cache) as peer:
            answer = check_answer(peer.url + "/suggest", body, timeout=cfg.load.timeout)
            levels = load_levels(peer.url + "/suggest", bodies, cfg.concurrency, cfg.load)
        peers[framework] = {"answer": answer, "levels": levels}
    with our_service(cache, dict(cfg.server_env), cfg.workers) as ours:
        our_answer = check_answer(ours.url + "/suggest", body, timeout=cfg.load.timeout)
        our_levels = load_levels(ours.url + "/suggest", bodies, cfg.concurrency, cfg.load,
                                 metrics_urls=ours.metrics_urls)
    versions = installed_versions(ensure_venv())
    return {
        "query": {"source": query.source, "points": len(query.points), "k": query.k},
        "ours": our_levels,
        "peers": {name: {"version": versions.get(name), "packages": versions,
                         "config": peer_config(settings, name, cfg.workers).__dict__,
                         "answers": compare_answers(p["answer"], our_answer),
                         "levels": p["levels"], "ratios": ratios(our_levels, p["levels"])}
                  for name, p in peers.items()},
    }
