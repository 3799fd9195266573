"""The growing catalog of one server process: additions, deletions and the snapshot it serves.

``CatalogWriter.open`` runs at start when ``COMPLEMENTME_DATA_DIR`` is set:

1. open the store (SQLite WAL) and check the folder (``CatalogStore.check_folder``): a database
   that lost commits the other files prove (a deleted WAL, an older database put back) refuses
   to start, naming the files; files of adds that never committed move to ``quarantine/``;
2. re-embed added parts computed by another model version (their geometry is kept, so a new
   model never loses them);
3. load every live part (a part whose geometry file is missing or damaged, or whose id now
   clashes with a shipped part, is left out and listed in the status);
4. reconcile the index file with the database: it must reflect the database's last change and
   hold the same parts and vectors; otherwise it is rebuilt from the database rows;
5. publish the snapshot (shipped + added parts, ``CatalogSnapshot``) to serve.

Writes: ``add`` stores a prepared part in one SQLite transaction, then brings the served
snapshot up to the database's latest change before returning, so the next request sees the
part. Snapshot rebuilds are serialised and coalesced: a writer whose change was already
included by another writer's rebuild returns at once. Changes made by other processes on the
same folder are picked up by a polling thread (``COMPLEMENTME_CATALOG_POLL_SECONDS``).

With ``COMPLEMENTME_CATALOG_BACKEND=postgres`` the store is the shared database
(``service.catalog_store.pg_store``) and there is no folder to check: the start re-embeds, loads every live
part from the database and publishes the snapshot, then a ``ChangeFollower``
(``service.catalog_store.follow``) applies every other replica's changes as they commit. While the database
cannot be reached, writes raise ``UnavailableError`` (503 with Retry-After, nothing stored)
and the last snapshot keeps being served.
"""

from __future__ import annotations

import dataclasses
import logging
import re
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from service.catalog_store.follow import ChangeFollower
from service.catalog_store.part_prep import embed_geometry
from service.catalog_store.pg_store import KeyTakenError, PgCatalogStore
from service.catalog_store.snapshot import (
    AddedPart,
    CatalogBuilder,
    combined_index,
    read_index_file,
    write_index_file,
)
from service.catalog_store.store import (
    ADDED_SHAPE_PREFIX,
    CatalogStore,
    NewPart,
    PartGeometry,
    StoredPart,
    StoreError,
    StoreUnavailableError,
)
from service.errors import ConflictError, InputError, NotFoundError, StorageFullError, UnavailableError
from service.geometry.mesh import resample_points
from service.settings import Settings
from service.suggest.engine import SuggestionEngine
from service.suggest.snapshot import CatalogSnapshot

log = logging.getLogger(__name__)

# Ids and names a client may choose: shape ids become part of part ids and URLs.
SHAPE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$")
CATEGORY = re.compile(r"^[A-Za-z0-9][A-Za-z0-9 ._-]{0,63}$")
# The Idempotency-Key header of an add: 1-200 visible ASCII characters (a UUID fits).
IDEMPOTENCY_KEY = re.compile(r"^[\x21-\x7e]{1,200}$")


def added_record(p: StoredPart) -> dict[str, Any]:
    """The catalog record of an added part (the fields of ``CATALOG_FIELDS`` plus name, origin)."""
    return {"part_id": p.part_id, "shape_id": p.shape_id, "category": p.category, "style": p.style,
            "label": p.label, "translation": p.translation, "bbox_min": p.bbox_min, "bbox_max": p.bbox_max,
            "area": p.area, "split": "added", "duplicate_of": None, "name": p.name, "origin": "added"}


class CatalogWriter:
    """Owns a data folder for one process and publishes the catalog snapshot to serve.

    ``engine`` is the process's long-lived engine: its networks embed added parts, its shipped
    snapshot is the base every published snapshot extends.
    """

    def __init__(self, store: CatalogStore | PgCatalogStore, engine: SuggestionEngine, settings: Settings,
                 publish: Callable[[CatalogSnapshot], None]):
        self.store = store
        self.engine = engine
        self.settings = settings
        self._publish = publish
        self.builder = CatalogBuilder(engine.catalog)
        self.parts: dict[int, AddedPart] = {}          # by parts.id, in order of addition
        self.seq = 0                                    # the last change the snapshot includes
        self.index_seq = -1                             # the change the index file reflects
        self.index_rebuilt = False
        self.reembedded = 0
        self.skipped: dict[int, dict[str, str]] = {}   # parts.id -> {"part_id", "reason"}
        self.snapshot = engine.shipped                  # the one published last
        self._sync_lock = threading.Lock()
        self._stop = threading.Event()
        self._poller: threading.Thread | None = None
        self.follower: ChangeFollower | None = None     # the postgres backend's

    # ------------------------------------------------------------------ start
    @classmethod
    def open(cls, settings: Settings, engine: SuggestionEngine,
             publish: Callable[[CatalogSnapshot], None]) -> CatalogWriter:
        """Open the data folder, reconcile it and publish the first snapshot (see module doc)."""
        if settings.catalog_backend == "postgres":
            return cls._open_postgres(settings, engine, publish)
        assert settings.data_dir is not None, "CatalogWriter.open needs settings.data_dir"
        store = CatalogStore(settings.data_dir)
        writer = cls(store, engine, settings, publish)
        try:
            store.check_folder()
            writer._reembed_stale()
            writer._load_all()
            writer._reconcile_index()
        except BaseException:
            store.close()
            raise
        log.info("catalog additions from %s: %d part(s) at change %d%s", settings.data_dir,
                 len(writer.parts), writer.seq, f", {len(writer.skipped)} left out" if writer.skipped else "")
        if settings.catalog_poll_seconds > 0:
            writer._poller = threading.Thread(target=writer._poll, name="catalog-poll", daemon=True)
            writer._poller.start()
        return writer

    @classmethod
    def _open_postgres(cls, settings: Settings, engine: SuggestionEngine,
                       publish: Callable[[CatalogSnapshot], None]) -> CatalogWriter:
        """Connect to the shared database, load its parts, publish, then follow its changes."""
        assert settings.database_url is not None, "the postgres backend needs settings.database_url"
        store = PgCatalogStore(settings.database_url.get_secret_value(), engine.model_version,
                               pool_size=settings.database_pool_size, timeout=settings.database_timeout,
                               idle_seconds=settings.request_timeout,
                               migrate_schema=settings.database_migrate)
        writer = cls(store, engine, settings, publish)
        try:
            writer._reembed_stale()
            writer._load_all()
        except BaseException:
            store.close()
            raise
        log.info("catalog additions from %s: %d part(s) at change %d%s", store.location, len(writer.parts),
                 writer.seq, f", {len(writer.skipped)} left out" if writer.skipped else "")
        follower = ChangeFollower(store.connect_listener, store.last_seq, writer.sync, lambda: writer.seq,
                                  settings.catalog_poll_seconds)
        follower.heard(writer.seq)
        writer.follower = follower
        follower.start()
        return writer

    def close(self) -> None:
        self._stop.set()
        if self._poller is not None:
            self._poller.join(timeout=10)
        if self.follower is not None:
            self.follower.stop()
        self.store.close()

    @property
    def model_version(self) -> str:
        return self.engine.model_version

    def _reembed_stale(self) -> None:
        stale = [p for p in self.store.parts() if p.model_version != self.model_version]
        if not stale:
            return
        log.info("re-embedding %d added part(s) computed by other model versions", len(stale))
        updates = []
        for p in stale:
            try:
                g = self.store.read_geometry(p)
            except StoreError as exc:
                log.error("cannot re-embed: %s", exc)
                continue
            e, f = embed_geometry(self.engine.networks, g.vertices, g.faces, self.engine.artifacts.n_points,
                                  self.settings.seed, self.engine.artifacts.placement_points)
            updates.append((p.id, e, f))
        if updates:
            self.store.update_embeddings(updates, self.model_version)
        self.reembedded = len(updates)

    def _load_all(self) -> None:
        with self._sync_lock:
            with self.store.reading():  # the change number and the rows of one moment
                self.seq = self.store.last_seq()
                rows = self.store.parts()
            self.parts = {}
            self._admit(rows)
            self.builder.set_parts(list(self.parts.values()))
            self._publish_snapshot()

    def _reconcile_index(self) -> None:
        """Keep the index file if it matches the database exactly; rebuild it otherwise."""
        assert self.store.index_path is not None, "only the data folder has an index file"
        found = read_index_file(self.store.index_path)
        ids = np.array(list(self.parts), dtype=np.int64)
        emb = self._added_embeddings()
        ok = (found is not None and found.seq == self.seq and found.model_version == self.model_version
              and np.array_equal(found.row_ids, ids) and found.embeddings.shape == emb.shape
              and np.array_equal(found.embeddings, emb))
        if ok:
            self.index_seq = self.seq
            return
        why = "missing or unreadable" if found is None else (
            f"reflects change {found.seq} with {len(found.row_ids)} part(s), the database is at change "
            f"{self.seq} with {len(ids)}")
        level = logging.INFO if found is None and not self.parts else logging.WARNING  # a new folder
        log.log(level, "%s: index file %s; rebuilding it from the database", self.store.index_path, why)
        self.index_rebuilt = True
        self._write_index()

    # ------------------------------------------------------------------ writes
    def add(self, part: NewPart, shape_id: str | None,
            may_commit: Callable[[], bool] | None = None) -> StoredPart:
        """Store a prepared part and serve it; returns its row (with its new ``part_id``).

        ``may_commit`` is asked just before the commit (``CatalogStore.add``): False stores nothing.

        Raises:
            InputError: bad category or shape id; ConflictError: a shipped shape id;
            StorageFullError: the data folder holds ``max_added_parts`` parts;
            CommitRefusedError: ``may_commit`` said no.
        """
        self._check_names(part.category, shape_id)
        with self._reachable():
            self._check_room()
            stored = self.store.add(part, shape_id, may_commit)
        self._serve_own(stored.added_seq)
        return stored

    def add_once(self, prepare: Callable[[], NewPart], shape_id: str | None, key: str, request_sha256: str,
                 may_commit: Callable[[], bool] | None = None) -> tuple[StoredPart, bool]:
        """``add`` under an idempotency key: the first request with ``key`` adds the part that
        ``prepare`` makes; a retry of it (same ``request_sha256``) gets that part back without
        adding anything. Returns the part and whether it was added before (a replay).

        Raises:
            InputError: ``idempotency_key_reused`` (the key came with another request), or
            ``idempotency_unsupported`` (the SQLite backend); as ``add`` otherwise.
        """
        store = self.store
        if not isinstance(store, PgCatalogStore):
            raise InputError("idempotency_unsupported", "the Idempotency-Key header needs the postgres "
                             "catalog backend (COMPLEMENTME_CATALOG_BACKEND); send the add without it")
        if not IDEMPOTENCY_KEY.match(key):
            raise InputError("invalid_idempotency_key", "Idempotency-Key must be 1-200 visible ASCII "
                             "characters (a UUID, for example)")
        with self._reachable():
            found = store.find_key(key)
        if found is None:
            part = prepare()
            self._check_names(part.category, shape_id)
            with self._reachable():
                self._check_room()
                try:
                    stored = store.add(part, shape_id, may_commit, idempotency_key=key,
                                       request_sha256=request_sha256)
                    self._serve_own(stored.added_seq)
                    return stored, False
                except KeyTakenError as exc:  # the same key's other request committed first
                    found = (exc.stored, exc.request_sha256)
        stored, sha = found
        if sha != request_sha256:
            raise InputError("idempotency_key_reused", f"Idempotency-Key {key!r} was used for another "
                             f"request (it added part {stored.part_id!r}); use a new key for each new part")
        self._serve_own(stored.added_seq)
        return stored, True

    def _check_room(self) -> None:
        if self.store.counts()[0] >= self.settings.max_added_parts:
            raise StorageFullError("catalog_full", f"the catalog holds {self.settings.max_added_parts} "
                                   "added parts, the most COMPLEMENTME_MAX_ADDED_PARTS allows")

    def database_up(self) -> bool:
        """Whether the shared database answered this replica's last round trips: the follower's
        own connection (it reconnects every second while the database is away) and the store's
        last operation. The one answer to "is the database reachable" for writes, /readyz and
        /metrics. Always True for the SQLite backend."""
        f = self.follower
        return f is None or (f.up and getattr(self.store, "available", True))

    @contextmanager
    def _reachable(self) -> Iterator[None]:
        """An unreachable database as 503 ``database_unavailable`` with Retry-After.

        While the follower knows the database is away the write is refused at once: trying it
        would hold the client for the pool's whole timeout (COMPLEMENTME_DATABASE_TIMEOUT, 5 s)
        only to fail the same way. The follower's reconnection marks it back up."""
        try:
            if self.follower is not None and self.follower.lost:
                raise StoreUnavailableError(f"known to be unreachable since the follower lost it: "
                                            f"{self.follower.last_error}")
            yield
        except StoreUnavailableError as exc:
            raise UnavailableError("database_unavailable", f"the catalog database cannot be reached "
                                   f"({exc}); nothing was stored or deleted: retry later",
                                   self.settings.database_retry_after) from None

    def _serve_own(self, seq: int) -> None:
        """After a commit: serve change ``seq`` before answering. The change is stored whatever
        happens here, so a database gone just after the commit is logged, not answered: the
        follower applies the change when the database is back."""
        try:
            self.catch_up(seq)
        except StoreUnavailableError as exc:
            log.warning("change %d is committed but not yet served here: %s", seq, exc)

    def delete(self, part_id: str) -> None:
        """Remove an added part from the catalog; shipped parts cannot be deleted (409)."""
        if part_id in self.engine.catalog.index_of:
            raise ConflictError("shipped_part", f"part {part_id!r} ships with the model's artifacts and "
                                "cannot be deleted; leave it out per request with exclude_parts")
        with self._reachable():
            seq = self.store.delete(part_id)
        if seq is None:
            raise NotFoundError("unknown_part", f"part {part_id!r} is not in the catalog")
        self._serve_own(seq)

    def _check_names(self, category: str, shape_id: str | None) -> None:
        if not CATEGORY.match(category):
            raise InputError("invalid_category", f"category {category!r} must be 1-64 letters, digits, "
                             "spaces, '.', '_' or '-', starting with a letter or digit")
        if shape_id is None:
            return
        if not SHAPE_ID.match(shape_id) or shape_id.startswith(ADDED_SHAPE_PREFIX):
            raise InputError("invalid_shape_id", f"shape_id {shape_id!r} must be 1-100 letters, digits, '.', "
                             f"'_' or '-', starting with a letter or digit (and not '{ADDED_SHAPE_PREFIX}', "
                             "kept for parts sent without one)")
        if shape_id in self.engine.catalog.shape_ids:
            raise ConflictError("shipped_shape", f"shape {shape_id!r} belongs to the shipped catalog; add "
                                "parts of new shapes only")

    # ------------------------------------------------------------------ snapshots
    def catch_up(self, seq: int) -> None:
        """Return once the served snapshot includes change ``seq`` (rebuilding it if needed)."""
        with self._sync_lock:
            if self.seq < seq:
                self._sync_locked()

    def sync(self) -> bool:
        """Bring the snapshot up to the database's latest change; True if it changed."""
        with self._sync_lock:
            return self._sync_locked()

    def _sync_locked(self) -> bool:
        with self.store.reading():
            changes = self.store.changes_since(self.seq)
            if not changes:
                return False
            last = changes[-1].seq
            full = any(c.kind != "add" for c in changes)
            if full:
                rows = [p for p in self.store.parts() if p.added_seq <= last]
            else:
                rows = self.store.parts([c.part for c in changes
                                         if c.part is not None and c.part not in self.parts])
        # Every read of the database first: one that fails (the database went away) must leave
        # the replica as it was, at its old change, to apply these changes again later.
        cached = {pid: part.geometry for pid, part in self.parts.items()} if full else {}
        loaded = self._read_geometries(rows, cached)
        self.seq = last
        if full:
            self.parts, self.skipped = {}, {}
            self._admit(rows, cached, loaded)
            self.builder.set_parts(list(self.parts.values()))
        else:
            self.builder.append(self._admit(rows, loaded=loaded))
        self._publish_snapshot()
        if self.store.index_path is not None:
            self._write_index()
        if self.follower is not None:
            self.follower.heard(last)
        return True

    def _read_geometries(self, rows: list[StoredPart], cached: dict[int, PartGeometry]
                         ) -> dict[int, PartGeometry | StoreError]:
        wanted = [p for p in rows if p.id not in cached]
        return self.store.read_geometries(wanted) if wanted else {}

    def _admit(self, rows: list[StoredPart], cached: dict[int, PartGeometry] | None = None,
               loaded: dict[int, PartGeometry | StoreError] | None = None) -> list[AddedPart]:
        """Add rows to ``self.parts``, in order, with their geometry from ``cached``, ``loaded`` or
        (rows in neither) the store; rows that cannot be served are listed in ``self.skipped``."""
        D = self.engine.catalog.embeddings.shape[1]
        Fp = self.engine.catalog.part_features.shape[1]
        S = self.builder.n_points
        admitted = []
        loaded = loaded if loaded is not None else self._read_geometries(rows, cached or {})
        for p in rows:
            reason = None
            # A part a replica of another model added to the shared database (a rolling update)
            # is embedded here from its mesh, with the seeded samples the start would use; the
            # next start stores the vectors (_reembed_stale). Storing them now would make every
            # such add a re-embedding change, and every replica reload its catalog for it.
            restamp = p.model_version != self.model_version and isinstance(self.store, PgCatalogStore)
            if p.part_id in self.engine.catalog.index_of:
                reason = "its id is also the id of a shipped part"
            elif not restamp and (p.embedding.shape != (D,) or p.part_feature.shape != (Fp,)):
                reason = (f"embedding/feature sizes {p.embedding.shape}/{p.part_feature.shape} do not fit "
                          f"the model ({D}, {Fp})")
            elif not restamp and p.model_version != self.model_version:
                reason = f"embedded by model {p.model_version}, not re-embedded"
            if reason is None and cached is not None and p.id in cached:
                g = cached[p.id]
            elif reason is None:
                got = loaded[p.id]
                if isinstance(got, StoreError):
                    reason = str(got)
                else:
                    g = got
            if reason is not None:
                log.error("added part %s is left out of the catalog: %s", p.part_id, reason)
                self.skipped[p.id] = {"part_id": p.part_id, "reason": reason}
                continue
            if restamp:
                e, f = embed_geometry(self.engine.networks, g.vertices, g.faces,
                                      self.engine.artifacts.n_points, self.settings.seed,
                                      self.engine.artifacts.placement_points)
                p = dataclasses.replace(p, embedding=e, part_feature=f, model_version=self.model_version)
            if len(g.points) != S:  # preview size of another artifact version
                g = dataclasses.replace(g, points=resample_points(g.points, S, self.settings.seed))
            part = AddedPart(p.id, added_record(p), p.embedding, p.part_feature, g)
            self.parts[p.id] = part
            admitted.append(part)
        return admitted

    def _publish_snapshot(self) -> None:
        """The next snapshot (the engine, its networks and caches, stay as they are)."""
        catalog = self.builder.catalog()
        index = combined_index(self.engine.index, catalog, len(self.engine.catalog))
        snapshot = self.engine.snapshot(catalog, index)
        self.snapshot = snapshot
        self._publish(snapshot)

    def _added_embeddings(self) -> np.ndarray:
        D = self.engine.catalog.embeddings.shape[1]
        if not self.parts:
            return np.zeros((0, D), np.float32)
        return np.stack([p.embedding for p in self.parts.values()]).astype(np.float32)

    def _write_index(self) -> None:
        assert self.store.index_path is not None, "only the data folder has an index file"
        write_index_file(self.store.index_path, self.seq, self.model_version, list(self.parts),
                         self._added_embeddings(), self.engine.index.metric_type)
        self.index_seq = self.seq

    def _poll(self) -> None:
        while not self._stop.wait(self.settings.catalog_poll_seconds):
            try:
                if self.store.last_seq() > self.seq:
                    self.sync()
            except Exception:  # keep polling: a failed refresh must not stop later ones
                log.exception("refreshing the catalog from %s failed", self.store.location)

    # ------------------------------------------------------------------ status
    def status(self) -> dict[str, Any]:
        deleted: int | None
        last: int | None
        try:
            if not self.database_up():
                raise StoreUnavailableError("known to be unreachable")  # answer at once, not after a timeout
            deleted, last = self.store.counts()[1], self.store.last_seq()
        except StoreUnavailableError:  # the database is down: what this replica knows
            deleted, last = None, self.follower.database_seq if self.follower is not None else None
        return {
            "writable": True, "backend": self.store.backend, "shipped_parts": len(self.engine.catalog),
            "added_parts": len(self.parts), "deleted_parts": deleted, "parts": len(self.snapshot.catalog),
            "sequence": self.seq, "database_sequence": last,
            "index_sequence": self.index_seq if self.store.index_path is not None else None,
            "index_rebuilt_at_start": self.index_rebuilt, "reembedded_at_start": self.reembedded,
            "left_out": list(self.skipped.values()), "replication": self.replication(),
        }

    def replication(self) -> dict[str, Any] | None:
        """Where this replica is in the shared database's changes (None for the SQLite backend)."""
        f = self.follower
        if f is None:
            return None
        up = self.database_up()
        return {"database": "up" if up else "unreachable", "applied_change": self.seq,
                "database_change": f.database_seq, "lag_changes": f.lag_changes,
                "lag_seconds": round(f.lag_seconds, 3), "last_error": None if up else f.last_error}

