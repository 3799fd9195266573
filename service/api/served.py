"""What this process serves: one object, made in the lifespan, that every route reaches through
a typed dependency (``service.api.deps.ServedDep``).

``Served`` owns:

* the long-lived ``SuggestionEngine`` (networks, the settings it reads, its caches), made once;
* the current ``CatalogSnapshot`` (catalog, index, search): the shipped catalog at first, then
  each snapshot the catalog writer publishes. Publishing is one reference swap, so a request
  reads the snapshot it started with from start to end, and readers never wait for writers;
* the micro-batcher (``service.api.batching``), whose worker runs the queued suggestion queries
  through the engine on the snapshot current when their batch runs;
* the catalog writer (``service.catalog_store.writer``), opened here when a data folder or the
  postgres backend is configured; None for a read-only server.

Each method is one call a route makes. A route that reads catalog rows in more than one call
(``/assemble``: the start part's row, the assembly, the rendering) takes ``snapshot`` once and
passes it on, so that a write published meanwhile cannot shift its rows.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from service.api.batching import BatchStats, MicroBatcher, Ticket
from service.api.metrics import Metrics
from service.artifacts.catalog import Catalog
from service.catalog_store.writer import CatalogWriter
from service.errors import ServiceError
from service.geometry.frames import Frame, UpAxis
from service.modeling.assembly import AssembleOptions, Assembler, AssembleResult, Start
from service.settings import Settings
from service.suggest.engine import PlaceResult, SuggestionEngine, SuggestOptions, SuggestResult
from service.suggest.frame_fit import FrameFit, fit_frame
from service.suggest.snapshot import CatalogSnapshot

# One suggestion query: its points (caller's frame) and options.
SuggestQuery = tuple[np.ndarray, SuggestOptions]
# The micro-batcher of suggestion queries: (points, options) in, SuggestResult out.
SuggestBatcher = MicroBatcher[SuggestQuery, SuggestResult]


class Served:
    """The engine, the catalog snapshot it serves, the batcher and the catalog writer of one process."""

    def __init__(self, engine: SuggestionEngine, settings: Settings, metrics: Metrics):
        self.engine = engine
        self.settings = settings
        self.metrics = metrics
        self._snapshot = engine.shipped
        self.writer: CatalogWriter | None = None
        metrics.set_model(engine.model_version, len(engine.catalog))
        self.batcher: SuggestBatcher = MicroBatcher(
            self.run_batch, max_size=settings.batch_max_size, max_wait=settings.batch_max_wait_ms / 1000,
            max_cost=settings.batch_max_cost_ms, cost=self.query_cost,
            workers=settings.batch_workers, name="suggest-batcher",
            stats=BatchStats(wait=metrics.queue_wait.observe, ran=metrics.observe_batch))
        metrics.watch(metrics.queued, lambda: self.batcher.queued)

    # ---------------------------------------------------------------- the snapshot
    @property
    def snapshot(self) -> CatalogSnapshot:
        """The catalog snapshot served now."""
        return self._snapshot

    @property
    def catalog(self) -> Catalog:
        """The catalog served now (shipped + added parts)."""
        return self._snapshot.catalog

    @property
    def model_version(self) -> str:
        return self.engine.model_version

    def publish(self, snapshot: CatalogSnapshot) -> None:
        """Serve ``snapshot`` from the next request (or batch) on."""
        self._snapshot = snapshot
        self.metrics.set_model(self.engine.model_version, len(snapshot.catalog))

    def open_catalog(self) -> None:
        """Open the catalog additions (``COMPLEMENTME_DATA_DIR`` or the postgres backend), if
        configured; their snapshot is served from here on. Raises ``StoreError`` to refuse to start."""
        if not self.settings.catalog_enabled:
            return
        self.writer = CatalogWriter.open(self.settings, self.engine, self.publish)
        if self.writer.follower is not None:
            self.metrics.watch_replication(self.writer.replication)

    def close(self, timeout: float) -> None:
        """Answer the queued queries (later ones get 503 shutting_down), then close the writer and
        the engine's thread."""
        self.batcher.close(timeout)
        if self.writer is not None:
            self.writer.close()
            self.writer = None
        self.engine.close()

    # ---------------------------------------------------------------- what the batcher runs
    def run_batch(self, items: list[SuggestQuery], deadlines: Sequence[float | None]
                  ) -> list[SuggestResult | ServiceError]:
        """One batch of queries through the engine, on the snapshot served now."""
        return self.engine.suggest_batch(items, deadlines, snapshot=self._snapshot)

    def query_cost(self, query: SuggestQuery) -> float:
        """A query's estimated CPU milliseconds (the batcher's ``max_cost`` counts them)."""
        return self.engine.query_cost(len(query[0]), query[1])

    # ---------------------------------------------------------------- what the routes call
    def check(self, n_points: int, options: SuggestOptions) -> None:
        """Refuse a query before it joins a batch: bad options, or over the request budget."""
        self.engine.check_budget(self.engine.check_query(n_points, options))

    async def suggest(self, points: np.ndarray, options: SuggestOptions, ticket: Ticket | None = None,
                      deadline: float | None = None) -> SuggestResult:
        """One query through the batcher; its ``ServiceError`` is raised."""
        return await self.batcher.submit((points, options), ticket, deadline)

    async def suggest_many(self, queries: list[SuggestQuery], ticket: Ticket | None = None,
                           deadline: float | None = None) -> list[SuggestResult | ServiceError]:
        """One request's queries in the same batch; one answer or error each."""
        return await self.batcher.submit_many(queries, ticket, deadline)

    def place(self, points: np.ndarray, part_ids: list[str], frame: Frame | None, refine_contact: bool,
              fit_scale: bool | None) -> PlaceResult:
        return self.engine.place(points, part_ids, frame, refine_contact=refine_contact, fit_scale=fit_scale,
                                 snapshot=self._snapshot)

    def fit_frame(self, points: np.ndarray, options: SuggestOptions, up_axes: Sequence[UpAxis],
                  snapshot: CatalogSnapshot) -> FrameFit:
        """The complete object's frame estimated from a partial, in one engine batch (not the
        batcher's), on ``snapshot`` (the one the request read at its start)."""
        return fit_frame(self.engine, self.settings, points, options, up_axes, snapshot=snapshot)

    def assemble(self, start: Start, options: AssembleOptions, snapshot: CatalogSnapshot) -> AssembleResult:
        """Grow a shape from ``start`` (rows of ``snapshot``, the one the request read at its start)."""
        return Assembler(self.engine, self.settings, snapshot).assemble(start, options)
