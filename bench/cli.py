"""``python -m bench``: one command per benchmark, ``all`` to run them in order, ``report`` to render.

Each command writes ``<results-dir>/<name>.json`` (machine, settings, results); ``report`` turns
every result file present into the generated section of docs/performance.md. ``--quick`` shrinks
every count and duration for development (its numbers are not for publishing).
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import typer

from bench.query import EXAMPLE, REPO, BenchQuery
from bench.results import CACHE_DIR, RESULTS_DIR

log = logging.getLogger("bench")

app = typer.Typer(help="Performance benchmarks of the suggestion service (issue 6).", no_args_is_help=True,
                  add_completion=False)

DOC = REPO / "docs" / "performance.md"

ResultsOpt = typer.Option(RESULTS_DIR, "--results-dir", help="Where the JSON results go.")
QuickOpt = typer.Option(False, "--quick", help="Tiny counts and durations, for development only.")
QueryOpt = typer.Option(EXAMPLE, "--query", help="JSON file with the query's points.")
CacheOpt = typer.Option(CACHE_DIR, "--cache-dir", help="Built indexes, request bodies and server logs.")
# The load options of every wrk-driven command (http, peer, framework; balancers keeps its own
# defaults for duration and warm-up).
DurationOpt = typer.Option(None, min=1, help="Measured seconds per level (default 10).")
WarmupSecondsOpt = typer.Option(None, min=0, help="Warm-up seconds per level (default 3).")
WrkThreadsOpt = typer.Option(1, min=1, help="wrk threads.")
WrkTimeoutOpt = typer.Option(30.0, min=1, help="Seconds before wrk counts a request as timed out.")
ServerEnvOpt = typer.Option(None, help="KEY=VALUE for our server processes (repeatable).")
ProcessesOpt = typer.Option(None, "--processes", min=1, help=(
    "Processes of our server, behind HAProxy (docker/haproxy/haproxy.cfg) when more than one "
    "(default: the usable cores)."))


@app.callback()
def main(verbose: bool = typer.Option(False, "--verbose", "-v", help="Log debug messages.")) -> None:
    logging.basicConfig(level=logging.DEBUG if verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    for name in ("faiss.loader", "httpx", "httpcore"):
        logging.getLogger(name).setLevel(logging.WARNING)


def _ints(text: str, name: str) -> tuple[int, ...]:
    try:
        values = tuple(int(x.replace("_", "")) for x in text.split(",") if x.strip())
    except ValueError:
        raise typer.BadParameter(f"{name} must be comma-separated integers, found {text!r}") from None
    if not values or min(values) < 1:
        raise typer.BadParameter(f"{name} must list positive integers, found {text!r}")
    return values


def _env_pairs(items: list[str] | None) -> tuple[tuple[str, str], ...]:
    from bench.http_bench import DEFAULT_SERVER_ENV

    env = dict(DEFAULT_SERVER_ENV)
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise typer.BadParameter(f"--server-env takes KEY=VALUE, found {item!r}")
        env[key] = value
    return tuple(env.items())


def _query(path: Path) -> BenchQuery:
    from bench.query import load_query

    return load_query(path, n_points=1000, k=10)


def _save(results_dir: Path, name: str, config: dict[str, Any], run: Callable[[], dict[str, Any]]) -> None:
    """Describe the machine (its load average before the run), run the bench, save both."""
    from bench.machine import describe_machine
    from bench.results import save_result
    from service.settings import get_settings

    machine = describe_machine(get_settings().artifacts)
    path = save_result(results_dir, name, machine, config, run())
    log.info("wrote %s", path)


def _load(quick: bool, load_seconds: float | None, warmup_seconds: float | None, wrk_threads: int,
          timeout: float) -> Any:
    from bench.wrk import LoadSettings

    return LoadSettings(duration=load_seconds or (2.0 if quick else 10.0),
                        warmup=warmup_seconds if warmup_seconds is not None else (1.0 if quick else 3.0),
                        threads=wrk_threads, timeout=timeout)


def do_engine(results_dir: Path, query: Path, quick: bool, reps: int | None, warmup: int | None) -> None:
    from bench.engine_bench import EngineBenchConfig, config_dict, load_engine, run_engine_bench
    from service.settings import get_settings

    cfg = EngineBenchConfig(reps=reps or (30 if quick else 1000),
                            warmup=warmup if warmup is not None else (5 if quick else 50))
    settings = get_settings()
    engine = load_engine(settings)
    _save(results_dir, "engine", config_dict(cfg),
          lambda: run_engine_bench(engine, settings, _query(query), cfg))


def _processes(processes: int | None) -> int:
    from bench.machine import usable_cores

    return processes or usable_cores()


def do_http(results_dir: Path, query: Path, quick: bool, cache: Path, concurrency: str, load: Any,
            server_env: list[str] | None, processes: int | None = None) -> None:
    from bench.http_bench import HttpBenchConfig, run_http_bench

    cfg = HttpBenchConfig(concurrency=_ints(concurrency, "--concurrency"), load=load,
                          processes=_processes(processes), server_env=_env_pairs(server_env))
    _save(results_dir, "http", cfg.as_dict(), lambda: run_http_bench(_query(query), cfg, cache))


def do_catalog(results_dir: Path, query: Path, quick: bool, cache: Path, sizes: str | None, noise: float,
               index_kind: str, flat_max: int | None, search_reps: int | None, engine_reps: int | None,
               recall_queries: int | None, mmap_min: int | None = None) -> None:
    from bench.catalog_bench import CatalogBenchConfig, run_catalog_bench
    from bench.engine_bench import load_engine
    from service.settings import get_settings

    cfg = CatalogBenchConfig(
        sizes=_ints(sizes or ("10000" if quick else "10000,100000,1000000"), "--sizes"), noise=noise,
        index_kind=index_kind, flat_max=flat_max, search_reps=search_reps or (30 if quick else 300),
        engine_reps=engine_reps or (20 if quick else 300),
        recall_queries=recall_queries if recall_queries is not None else (15 if quick else 63),
        warmup=3 if quick else 20, worker_reps=20 if quick else 300)
    if mmap_min is not None:
        cfg = dataclasses.replace(cfg, mmap_min=mmap_min)
    settings = get_settings()
    engine = load_engine(settings)
    _save(results_dir, "catalog", cfg.as_dict(),
          lambda: run_catalog_bench(engine, settings, _query(query), cfg, cache))


def do_peer(results_dir: Path, query: Path, cache: Path, concurrency: str, load: Any,
            server_env: list[str] | None, processes: int | None = None) -> None:
    from bench.peer_bench import PeerBenchConfig, run_peer_bench
    from service.settings import get_settings

    cfg = PeerBenchConfig(concurrency=_ints(concurrency, "--concurrency"), load=load,
                          artifacts=get_settings().artifacts, processes=_processes(processes),
                          server_env=_env_pairs(server_env))
    _save(results_dir, "peer", cfg.as_dict(), lambda: run_peer_bench(_query(query), cfg, cache))


def do_framework(results_dir: Path, query: Path, cache: Path, frameworks: str, concurrency: str, load: Any,
                 server_env: list[str] | None) -> None:
    from bench.framework.venv import FRAMEWORKS
    from bench.framework_bench import FrameworkBenchConfig, run_framework_bench
    from service.settings import get_settings

    names = tuple(n.strip() for n in frameworks.split(",") if n.strip())
    unknown = [n for n in names if n not in FRAMEWORKS]
    if not names or unknown:
        raise typer.BadParameter(f"--frameworks takes a comma-separated list of {', '.join(FRAMEWORKS)}, "
                                 f"found {frameworks!r}")
    cfg = FrameworkBenchConfig(frameworks=names, concurrency=_ints(concurrency, "--concurrency"), load=load,
                               server_env=_env_pairs(server_env))
    _save(results_dir, "framework", cfg.as_dict(),
          lambda: run_framework_bench(_query(query), cfg, cache, get_settings()))


def do_interactive(results_dir: Path, query: Path, quick: bool, cache: Path, requests: int | None,
                   warmup: int | None, target_faces: int, server_env: list[str] | None,
                   processes: int | None = None) -> None:
    from bench.interactive_bench import InteractiveBenchConfig, run_interactive_bench

    cfg = InteractiveBenchConfig(requests=requests or (3 if quick else 20),
                                 warmup=warmup if warmup is not None else (1 if quick else 2),
                                 parse_reps=2 if quick else 5, target_faces=target_faces,
                                 processes=_processes(processes), server_env=_env_pairs(server_env))
    _save(results_dir, "interactive", cfg.as_dict(), lambda: run_interactive_bench(_query(query), cfg, cache))


def do_balancers(results_dir: Path, query: Path, quick: bool, cache: Path, setups: str, rounds: int | None,
                 connections: int, load: Any, haproxy_mode: str, haproxy_balance: str,
                 server_env: list[str] | None) -> None:
    from bench.balancer_bench import DEFAULT_SERVER_ENV, BalancerBenchConfig, run_balancer_bench

    env = {**DEFAULT_SERVER_ENV, **dict(_env_pairs(server_env))}
    try:
        cfg = BalancerBenchConfig(setups=tuple(s.strip() for s in setups.split(",") if s.strip()),
                                  rounds=rounds or (1 if quick else 3), connections=connections, load=load,
                                  server_env=tuple(env.items()), haproxy_mode=haproxy_mode,
                                  haproxy_balance=haproxy_balance)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None
    _save(results_dir, "balancers", cfg.as_dict(), lambda: run_balancer_bench(_query(query), cfg, cache))


def do_report(results_dir: Path, doc: Path) -> None:
    from bench.report import render_results, write_report
    from bench.results import load_results

    write_report(doc, render_results(load_results(results_dir)))
    log.info("rendered %s from %s", doc, results_dir)


@app.command()
def engine(
    results_dir: Path = ResultsOpt, query: Path = QueryOpt, quick: bool = QuickOpt,
    reps: int | None = typer.Option(None, min=1, help="Timed requests per variant (default 1000)."),
    warmup: int | None = typer.Option(None, min=0, help="Untimed requests first (default 50)."),
) -> None:
    """a. Engine latency per stage for one request, in process (no HTTP)."""
    do_engine(results_dir, query, quick, reps, warmup)


@app.command()
def http(
    results_dir: Path = ResultsOpt, query: Path = QueryOpt, quick: bool = QuickOpt,
    cache_dir: Path = CacheOpt,
    concurrency: str = typer.Option("1,8,32,64", help="Concurrency levels (wrk connections)."),
    duration: float | None = DurationOpt, warmup_seconds: float | None = WarmupSecondsOpt,
    wrk_threads: int = WrkThreadsOpt, timeout: float = WrkTimeoutOpt,
    server_env: list[str] | None = ServerEnvOpt,
    processes: int | None = ProcessesOpt,
) -> None:
    """b. HTTP load with wrk against `complementme serve` per core behind HAProxy (JSON, base64 bodies)."""
    do_http(results_dir, query, quick, cache_dir, concurrency,
            _load(quick, duration, warmup_seconds, wrk_threads, timeout), server_env, processes)


@app.command()
def catalog(
    results_dir: Path = ResultsOpt, query: Path = QueryOpt, quick: bool = QuickOpt,
    cache_dir: Path = CacheOpt,
    sizes: str | None = typer.Option(None, help="Catalog sizes (default 10000,100000,1000000)."),
    noise: float = typer.Option(0.05, min=0, help="Replica noise, fraction of each dimension's std."),
    index_kind: str = typer.Option("auto", help="build_index kind: auto, flat, ivf, hnsw, ivf_sq8, "
                                      "ivf_pq, ivf_pqfs, hnsw_sq8."),
    flat_max: int | None = typer.Option(None, min=1, help="build_index flat_max (default: its own)."),
    search_reps: int | None = typer.Option(None, min=1, help="Timed searches per size (default 300)."),
    engine_reps: int | None = typer.Option(None, min=1, help="Timed /suggest per size (default 300)."),
    recall_queries: int | None = typer.Option(None, min=0, help="Held-out queries for recall (default 63)."),
    mmap_min: int | None = typer.Option(None, min=1, help="Sizes from this many parts are memory-mapped "
                                        "from .npy files and measured in a worker process "
                                        "(default 2000000)."),
) -> None:
    """c. Catalog scaling: index build, search latency, recall@64 and engine latency per size
    (add 10000000 to --sizes for ten million parts: about 8 GB under --cache-dir)."""
    do_catalog(results_dir, query, quick, cache_dir, sizes, noise, index_kind, flat_max, search_reps,
               engine_reps, recall_queries, mmap_min)


@app.command()
def peer(
    results_dir: Path = ResultsOpt, query: Path = QueryOpt, quick: bool = QuickOpt,
    cache_dir: Path = CacheOpt,
    concurrency: str = typer.Option("1,32", help="Concurrency levels."),
    duration: float | None = DurationOpt, warmup_seconds: float | None = WarmupSecondsOpt,
    wrk_threads: int = WrkThreadsOpt, timeout: float = WrkTimeoutOpt,
    server_env: list[str] | None = ServerEnvOpt,
    processes: int | None = ProcessesOpt,
) -> None:
    """d. The peer baseline (torch eager, plain FastAPI) against our service, same load, same run."""
    load = _load(quick, duration, warmup_seconds, wrk_threads, timeout)
    do_peer(results_dir, query, cache_dir, concurrency, load, server_env, processes)


@app.command()
def framework(
    results_dir: Path = ResultsOpt, query: Path = QueryOpt, quick: bool = QuickOpt,
    cache_dir: Path = CacheOpt,
    frameworks: str = typer.Option("bentoml,litserve", help="Framework peers to run, in order."),
    concurrency: str = typer.Option("1,8,32,64", help="Concurrency levels."),
    duration: float | None = DurationOpt, warmup_seconds: float | None = WarmupSecondsOpt,
    wrk_threads: int = WrkThreadsOpt, timeout: float = WrkTimeoutOpt,
    server_env: list[str] | None = ServerEnvOpt,
) -> None:
    """f. Framework peers (BentoML, LitServe; same graphs and index) against our service, same run."""
    load = _load(quick, duration, warmup_seconds, wrk_threads, timeout)
    do_framework(results_dir, query, cache_dir, frameworks, concurrency, load, server_env)


@app.command(name="framework-venv")
def framework_venv() -> None:
    """Create the framework peers' venv (bench/.venv-peer) if it is missing or out of date."""
    from bench.framework.venv import ensure_venv, installed_versions

    python = ensure_venv()
    log.info("framework peer venv ready: %s %s", python, installed_versions(python))


@app.command()
def interactive(
    results_dir: Path = ResultsOpt, query: Path = QueryOpt, quick: bool = QuickOpt,
    cache_dir: Path = CacheOpt,
    requests: int | None = typer.Option(None, min=1, help="Timed requests per path (default 20)."),
    warmup: int | None = typer.Option(None, min=0, help="Untimed requests per path first (default 2)."),
    target_faces: int = typer.Option(100_000, min=1, help="Triangles of the uploaded query mesh."),
    server_env: list[str] | None = ServerEnvOpt,
    processes: int | None = ProcessesOpt,
) -> None:
    """e. Interactive paths at concurrency 1: mesh upload (GLB, OBJ), /place, contact, /assemble."""
    do_interactive(results_dir, query, quick, cache_dir, requests, warmup, target_faces, server_env,
                   processes)


@app.command()
def balancers(
    results_dir: Path = ResultsOpt, query: Path = QueryOpt, quick: bool = QuickOpt,
    cache_dir: Path = CacheOpt,
    setups: str = typer.Option("gunicorn,uvicorn,haproxy", help="Set-ups to compare, in the first "
                               "round's order."),
    rounds: int | None = typer.Option(None, min=1, help="Runs of every set-up, interleaved (default 3)."),
    connections: int = typer.Option(32, min=1, help="wrk connections."),
    duration: float | None = typer.Option(None, min=1, help="Measured seconds per run (default 20)."),
    warmup_seconds: float | None = typer.Option(None, min=0, help="Warm-up seconds per run (default 5)."),
    wrk_threads: int = WrkThreadsOpt, timeout: float = WrkTimeoutOpt,
    haproxy_mode: str = typer.Option("http", help="HAProxy's mode: http (balances requests) or tcp "
                                     "(balances connections)."),
    haproxy_balance: str = typer.Option("leastconn", help="HAProxy's balance algorithm."),
    server_env: list[str] | None = typer.Option(None, help="KEY=VALUE for every server (repeatable)."),
) -> None:
    """g. Two server processes behind one port three ways, c = 32, interleaved rounds (issue 17)."""
    if warmup_seconds is None and not quick:
        warmup_seconds = 5.0
    load = _load(quick, duration or (None if quick else 20.0), warmup_seconds, wrk_threads, timeout)
    do_balancers(results_dir, query, quick, cache_dir, setups, rounds, connections, load, haproxy_mode,
                 haproxy_balance, server_env)


@app.command()
def report(results_dir: Path = ResultsOpt,
           doc: Path = typer.Option(DOC, help="Markdown file with the generated section's markers.")) -> None:
    """Render the results into docs/performance.md (between its markers)."""
    do_report(results_dir, doc)


@app.command(name="all")
def run_all(
    results_dir: Path = ResultsOpt, query: Path = QueryOpt, quick: bool = QuickOpt,
    cache_dir: Path = CacheOpt,
    doc: Path = typer.Option(DOC, help="Markdown file the report is rendered into."),
    duration: float | None = typer.Option(None, min=1, help="Measured seconds per load level (default 10)."),
    sizes: str | None = typer.Option(None, help="Catalog sizes (default 10000,100000,1000000)."),
) -> None:
    """engine, http, catalog, peer, interactive and framework with their defaults, then the report."""
    load = _load(quick, duration, None, 1, 30.0)
    do_engine(results_dir, query, quick, None, None)
    do_http(results_dir, query, quick, cache_dir, "1,8,32,64", load, None)
    do_catalog(results_dir, query, quick, cache_dir, sizes, 0.05, "auto", None, None, None, None)
    do_peer(results_dir, query, cache_dir, "1,32", load, None)
    do_interactive(results_dir, query, quick, cache_dir, None, None, 100_000, None)
    do_framework(results_dir, query, cache_dir, "bentoml,litserve", "1,8,32,64", load, None)
    do_report(results_dir, doc)
