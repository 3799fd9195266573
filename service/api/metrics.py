"""Prometheus metrics of the server, in a registry of its own.

A registry per app (not prometheus-client's global one) lets tests build many apps in one
process. Each server process reports its own: where several run behind a proxy (one per core,
docs/deploy.md), Prometheus scrapes each of them, and sums over them are taken in the queries.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from prometheus_client import (
    CollectorRegistry,
    Counter,
    Gauge,
    Histogram,
    ProcessCollector,
    disable_created_metrics,
    generate_latest,
)
from prometheus_client.exposition import CONTENT_TYPE_LATEST

from service.errors import ServiceError

# Request latencies run from sub-millisecond probes to multi-second batches and mesh uploads.
_LATENCY_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0)
_STAGE_BUCKETS = (0.0001, 0.0002, 0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.5, 1.0)
_SIZE_BUCKETS = (1, 2, 4, 8, 16, 32, 64, 128, 256, 512, 1024)

CONTENT_TYPE = CONTENT_TYPE_LATEST

# The *_created series double the output for no use on a scrape target like this one.
disable_created_metrics()


class Metrics:
    """The service's counters, histograms and gauges."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self._model_version: str | None = None
        r = self.registry
        # process_resident_memory_bytes and friends: memory that uploads leave behind shows here.
        ProcessCollector(registry=r)
        self.requests = Counter("complementme_http_requests", "HTTP requests by method, route and status.",
                                ["method", "route", "status"], registry=r)
        self.latency = Histogram("complementme_http_request_duration_seconds",
                                 "HTTP request latency by method, route and status.",
                                 ["method", "route", "status"], buckets=_LATENCY_BUCKETS, registry=r)
        self.inference = Histogram("complementme_inference_duration_seconds",
                                   "ONNX Runtime time per engine call, by graph.", ["graph"],
                                   buckets=_STAGE_BUCKETS, registry=r)
        self.search = Histogram("complementme_search_duration_seconds",
                                "Nearest-part search time per engine call (numpy brute force or FAISS).",
                                buckets=_STAGE_BUCKETS, registry=r)
        self.scoring = Histogram("complementme_scoring_duration_seconds",
                                 "Mixture re-scoring and ranking time per engine call.",
                                 buckets=_STAGE_BUCKETS, registry=r)
        self.batch_size = Histogram("complementme_batch_size", "Queries per engine call (micro-batches "
                                    "of concurrent requests, /suggest/batch requests, single /place calls).",
                                    buckets=_SIZE_BUCKETS, registry=r)
        self.queue_wait = Histogram("complementme_batch_queue_wait_seconds",
                                    "Seconds a request's queries waited in the micro-batcher's queue.",
                                    buckets=_STAGE_BUCKETS, registry=r)
        self.queued = Gauge("complementme_batch_queued_queries",
                            "Queries waiting in the micro-batcher's queue now.", registry=r)
        self.candidates = Histogram("complementme_candidates", "Catalog parts re-scored per query.",
                                    buckets=_SIZE_BUCKETS, registry=r)
        self.catalog_parts = Gauge("complementme_catalog_parts", "Parts in the loaded catalog.", registry=r)
        self.model_info = Gauge("complementme_model_info", "The loaded model version (value 1).",
                                ["model_version"], registry=r)
        # The overload gate's (service/api/overload.py).
        self.rejections = Counter("complementme_overload_rejections", "Requests refused by the overload "
                                  "gate or cut at their deadline, by reason.", ["reason"], registry=r)
        self.inflight_requests = Gauge("complementme_inflight_requests", "Gated requests running now.",
                                       registry=r)
        self.queued_requests = Gauge("complementme_queued_requests", "Gated requests waiting for a slot.",
                                     registry=r)
        self.receiving_bytes = Gauge("complementme_receiving_body_bytes", "Bytes reserved by request "
                                     "bodies being received now (COMPLEMENTME_MAX_RECEIVING_BYTES).",
                                     registry=r)

    def watch_replication(self, replication: Callable[[], dict[str, Any] | None]) -> None:
        """Gauges of a postgres-backed replica's place in the database's changes (registered only
        then: a SQLite server has no such place)."""
        r = self.registry
        gauges = {
            "applied_change": Gauge("complementme_catalog_applied_change", "The last catalog database "
                                    "change this replica's served catalog includes.", registry=r),
            "database_change": Gauge("complementme_catalog_database_change", "The latest catalog database "
                                     "change this replica knows of.", registry=r),
            "lag_changes": Gauge("complementme_catalog_lag_changes", "Catalog database changes known but not "
                                 "yet applied.", registry=r),
            "lag_seconds": Gauge("complementme_catalog_lag_seconds", "How long this replica has known of a "
                                 "change it has not applied (0: up to date).", registry=r),
            "database": Gauge("complementme_catalog_database_up", "1 while the catalog database is "
                              "reachable, 0 while it is not.", registry=r),
        }

        def reader(key: str) -> Callable[[], float]:
            def read() -> float:
                state = replication() or {}
                value = state.get(key, 0)
                return float(value == "up") if key == "database" else float(value or 0)
            return read

        for key, gauge in gauges.items():
            self.watch(gauge, reader(key))

    def watch(self, gauge: Gauge, read: Callable[[], float]) -> None:
        """Report ``read()`` as the gauge's value at each scrape."""
        gauge.set_function(read)

    def observe_request(self, method: str, route: str, status: int, seconds: float) -> None:
        labels = (method, route, str(status))
        self.requests.labels(*labels).inc()
        self.latency.labels(*labels).observe(seconds)

    def observe_engine(self, timings: dict[str, float], batch_size: int, candidates: list[int]) -> None:
        """Record one engine call's stage timings (seconds) and sizes."""
        for graph in ("g", "h_query", "h_head"):
            if graph in timings:
                self.inference.labels(graph).observe(timings[graph])
        if "search" in timings:
            self.search.observe(timings["search"])
        if "score" in timings:
            self.scoring.observe(timings["score"])
        self.batch_size.observe(batch_size)
        for c in candidates:
            self.candidates.observe(c)

    def observe_batch(self, answers: Sequence[Any], size: int) -> None:
        """Record one micro-batch: its size, and the stages of its engine call (when a query ran)."""
        done = [a for a in answers if not isinstance(a, ServiceError)]
        if done:
            self.observe_engine(done[0].timings, size, [a.candidates for a in done])
        else:
            self.batch_size.observe(size)

    def set_model(self, model_version: str, parts: int) -> None:
        self.catalog_parts.set(parts)
        if self._model_version not in (None, model_version):
            self.model_info.remove(self._model_version)
        self.model_info.labels(model_version).set(1)
        self._model_version = model_version

    def render(self) -> bytes:
        """The text exposition of this process's metrics."""
        return generate_latest(self.registry)
