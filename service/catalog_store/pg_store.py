"""The catalog additions' store on PostgreSQL: one database shared by every replica.

The same methods as ``service.catalog_store.store.CatalogStore`` (the SQLite data folder), so the catalog
writer and its snapshots do not care which one they use. The database is the source of truth;
every replica's catalog snapshot and index are a cache of it (``service.catalog_store.writer``), kept up
to date by ``service.catalog_store.follow``.

Tables (``MIGRATIONS``; ``complementme catalog migrate`` applies them)::

    schema_migrations  the migrations applied: version, description, applied_at
    changes            seq (1, 2, 3, ... in commit order), kind (add | delete | reembed), part, at
    parts              one row per added part: id (sequence ``part_ids``: replicas never collide),
                       part_id, shape_id, category, name, style, label, translation, bbox_min,
                       bbox_max (double precision[3]), area, n_vertices, n_faces, mesh_sha256,
                       added_seq, deleted_seq (NULL while live), created_at, and the
                       idempotency_key (unique) and request_sha256 of the request that added it
    part_embeddings    (part, model_version) -> embedding, part_feature (little-endian float32
                       bytea): one per model version, so replicas of two model versions share the
                       catalog during a rolling update
    part_meshes        part -> data (the centred mesh and preview points in the data folder's
                       npz format, ``service.catalog_store.store.encode_geometry``), bytea stored uncompressed

**One order of changes.** Every write transaction starts with ``LOCK TABLE changes IN EXCLUSIVE
MODE``, which blocks other writers (of every replica) and no reader, and takes the next change
number as ``MAX(seq) + 1`` under it. Change numbers are therefore committed in their own order:
a replica that has applied change n and asks for ``seq > n`` can never later meet a change
below n (with a plain sequence, numbers are taken in one order and committed in another, and a
follower would skip the slow one). The lock also makes the shape counter behind part ids
race-free. A write notifies channel ``complementme_catalog`` with its change number;
PostgreSQL delivers notifications at commit, and only then.

Errors: a database that cannot be reached (refused connection, timeout, lost connection, the
write lock not granted within ``database_timeout``) raises ``StoreUnavailableError``; nothing
was committed unless the connection broke during the commit itself, which the idempotency key
of an add resolves (the retried add answers the stored part).
"""

from __future__ import annotations

import hashlib
import logging
import math
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from typing import Any

import numpy as np
import psycopg
from psycopg.conninfo import conninfo_to_dict, make_conninfo
from psycopg_pool import ConnectionPool, PoolTimeout

from service.artifacts.layout import format_part_id
from service.catalog_store.store import (
    Change,
    CommitRefusedError,
    NewPart,
    PartGeometry,
    StoredPart,
    StoreError,
    StoreUnavailableError,
    added_shape_id,
    decode_geometry,
    encode_geometry,
    vec6,
)

log = logging.getLogger(__name__)

CHANNEL = "complementme_catalog"
# pg_advisory_xact_lock key that serialises migrations of replicas starting together ("CmMg").
MIGRATION_LOCK = 0x436D4D67
# Meshes fetched per query when a replica loads or catches up.
MESH_BATCH = 128


@dataclass(frozen=True)
class Migration:
    version: int
    description: str
    sql: str


MIGRATIONS: tuple[Migration, ...] = (
    Migration(1, "added parts, their meshes and embeddings per model version, the change log", """
CREATE SEQUENCE part_ids;
CREATE TABLE changes (
    seq bigint PRIMARY KEY,
    kind text NOT NULL CHECK (kind IN ('add', 'delete', 'reembed')),
    part bigint,
    at timestamptz NOT NULL
);
CREATE TABLE parts (
    id bigint PRIMARY KEY,
    part_id text NOT NULL UNIQUE,
    shape_id text NOT NULL,
    category text NOT NULL,
    name text,
    style text,
    label text,
    translation double precision[] NOT NULL CHECK (cardinality(translation) = 3),
    bbox_min double precision[] NOT NULL CHECK (cardinality(bbox_min) = 3),
    bbox_max double precision[] NOT NULL CHECK (cardinality(bbox_max) = 3),
    area double precision NOT NULL,
    n_vertices integer NOT NULL,
    n_faces integer NOT NULL,
    mesh_sha256 text NOT NULL,
    added_seq bigint NOT NULL REFERENCES changes (seq),
    deleted_seq bigint REFERENCES changes (seq),
    created_at timestamptz NOT NULL,
    idempotency_key text UNIQUE,
    request_sha256 text
);
CREATE INDEX parts_shape ON parts (shape_id);
CREATE TABLE part_embeddings (
    part bigint NOT NULL REFERENCES parts (id),
    model_version text NOT NULL,
    embedding bytea NOT NULL,
    part_feature bytea NOT NULL,
    computed_at timestamptz NOT NULL,
    PRIMARY KEY (part, model_version)
);
CREATE TABLE part_meshes (
    part bigint PRIMARY KEY REFERENCES parts (id),
    data bytea NOT NULL
);
-- Out of line, never compressed: pglz gains nothing on float arrays and made writes of a 7 MB
-- mesh 3.8x slower (bench/pg_mesh_storage.py), time spent holding the write lock.
ALTER TABLE part_meshes ALTER COLUMN data SET STORAGE EXTERNAL;
"""),
)
SCHEMA_VERSION = MIGRATIONS[-1].version


class KeyTakenError(StoreError):
    """An add's idempotency key was used before: ``stored`` is the part that request added."""

    def __init__(self, stored: StoredPart, request_sha256: str | None):
        super().__init__(f"idempotency key already used for part {stored.part_id}")
        self.stored = stored
        self.request_sha256 = request_sha256


def redacted(url: str) -> str:
    """The URL without its password, for logs and errors."""
    try:
        p = conninfo_to_dict(url)
    except psycopg.ProgrammingError:
        return "the configured database URL (unparsable)"
    host = p.get("host") or "localhost"
    return f"postgresql://{p.get('user') or ''}@{host}:{p.get('port') or 5432}/{p.get('dbname') or ''}"


def conninfo(url: str, timeout: float, idle_seconds: float) -> str:
    """The URL with the connection parameters the store relies on (the URL's own ones win).

    ``lock_timeout`` bounds the wait for the write lock (``database_timeout``): a replica whose
    writer hangs inside a transaction must not stall every other replica's writes for long, and
    ``idle_in_transaction_session_timeout`` ends such a transaction (the request it belongs to
    has given up by then). TCP keepalives notice a vanished database host in about 25 s instead
    of the kernel's two hours.
    """
    given = conninfo_to_dict(url)
    options = (f"-c lock_timeout={int(timeout * 1000)} "
               f"-c idle_in_transaction_session_timeout={int(idle_seconds * 1000)}")
    extra: dict[str, Any] = {"connect_timeout": max(1, math.ceil(timeout)),
                             "application_name": "complementme", "keepalives": 1, "keepalives_idle": 10,
                             "keepalives_interval": 5, "keepalives_count": 3}
    extra = {k: v for k, v in extra.items() if k not in given}
    extra["options"] = f"{given['options']} {options}" if given.get("options") else options
    return make_conninfo(url, **extra)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip() or type(exc).__name__
    return text.splitlines()[0]


def schema_version(conn: psycopg.Connection[Any]) -> int:
    """The highest migration applied to the database (0 for an empty one)."""
    if conn.execute("SELECT to_regclass('schema_migrations')").fetchone() == (None,):
        return 0
    row = conn.execute("SELECT COALESCE(MAX(version), 0) FROM schema_migrations").fetchone()
    return int(row[0]) if row else 0


def migrate(conn: psycopg.Connection[Any]) -> list[int]:
    """Apply the migrations the database lacks, in one transaction; the versions applied.

    Idempotent, and safe when replicas run it together: the first takes an advisory lock, the
    others wait for it and then find nothing to do.
    """
    with conn.transaction():
        conn.execute("SELECT pg_advisory_xact_lock(%s)", (MIGRATION_LOCK,))
        conn.execute("CREATE TABLE IF NOT EXISTS schema_migrations (version integer PRIMARY KEY, "
                     "description text NOT NULL, applied_at timestamptz NOT NULL DEFAULT now())")
        applied = {int(r[0]) for r in conn.execute("SELECT version FROM schema_migrations")}
        newer = sorted(v for v in applied if v > SCHEMA_VERSION)
        if newer:
            raise StoreError(f"the catalog database has schema version {newer[-1]}, written by a newer "
                             f"version of the service (this one knows {SCHEMA_VERSION})")
        done = []
        for m in MIGRATIONS:
            if m.version in applied:
                continue
            conn.execute(m.sql.encode())  # several statements: sent as one simple query
            conn.execute("INSERT INTO schema_migrations (version, description) VALUES (%s, %s)",
                         (m.version, m.description))
            done.append(m.version)
    return done


def _blob(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a, dtype="<f4").tobytes()


def _vector(data: bytes | None) -> np.ndarray:
    return np.frombuffer(data or b"", dtype="<f4").astype(np.float32)


def _iso(at: datetime) -> str:
    return at.astimezone(timezone.utc).isoformat(timespec="milliseconds")


# parts' columns, then the embedding of the wanted model version (else of the latest other one,
# which makes the part stale for this replica: the writer re-embeds it from its mesh).
_SELECT_PARTS = """
SELECT p.id, p.part_id, p.shape_id, p.category, p.name, p.style, p.label, p.translation, p.bbox_min,
       p.bbox_max, p.area, e.embedding, e.part_feature, e.model_version, p.mesh_sha256, p.n_vertices,
       p.n_faces, p.added_seq, p.deleted_seq, p.created_at
FROM parts p
LEFT JOIN LATERAL (
    SELECT embedding, part_feature, model_version FROM part_embeddings
    WHERE part = p.id ORDER BY model_version = %(version)s DESC, computed_at DESC LIMIT 1) e ON true
"""


def _row_part(row: tuple[Any, ...]) -> StoredPart:
    (pid, part_id, shape_id, category, name, style, label, translation, bmin, bmax, area, emb, feat,
     version, sha, nv, nf, added, deleted, created) = row
    return StoredPart(
        id=int(pid), part_id=part_id, shape_id=shape_id, category=category, name=name, style=style,
        label=label, translation=list(translation), bbox_min=list(bmin), bbox_max=list(bmax),
        area=float(area), embedding=_vector(emb), part_feature=_vector(feat), model_version=version or "",
        geometry="", geometry_sha256=sha, n_vertices=int(nv), n_faces=int(nf), added_seq=int(added),
        deleted_seq=None if deleted is None else int(deleted), created_at=_iso(created))


class PgCatalogStore:
    """The added parts in a PostgreSQL database, through a connection pool; thread-safe.

    Args:
        url: the database's connection URL (``database_url``).
        model_version: the model whose embeddings ``parts`` returns.
        pool_size: most connections of the pool.
        timeout: seconds to wait for a connection, to connect, or for the write lock.
        idle_seconds: longest idle time inside a transaction before the database ends it.
        migrate_schema: apply missing migrations at start (else a schema that is not the current
            one raises ``StoreError`` naming the command that applies them).
    """

    backend = "postgres"
    index_path = None        # the index is a cache in memory only: the database is the truth
    supports_idempotency = True

    def __init__(self, url: str, model_version: str = "", *, pool_size: int = 4, timeout: float = 5.0,
                 idle_seconds: float = 60.0, migrate_schema: bool = False):
        self.location = redacted(url)
        self.model_version = model_version
        self.timeout = timeout
        try:
            self._conninfo = conninfo(url, timeout, idle_seconds)
        except psycopg.ProgrammingError as exc:
            raise StoreError(f"database_url is not a valid PostgreSQL URL ({_first_line(exc)})") from None
        self._local = threading.local()
        self._state_lock = threading.Lock()
        self.available = True
        self.last_error: str | None = None
        # check: a connection handed out is alive (one round trip), so a write after an outage
        # does not fail on a connection the database closed while it was down.
        self.pool: ConnectionPool[psycopg.Connection[Any]] = ConnectionPool(
            self._conninfo, min_size=1, max_size=pool_size, timeout=timeout, open=False,
            check=ConnectionPool.check_connection, name="complementme-catalog")
        try:
            self.pool.open(wait=True, timeout=timeout)
            with self._errors(), self.pool.connection() as conn:
                if migrate_schema:
                    applied = migrate(conn)
                    if applied:
                        log.info("%s: applied schema migration(s) %s", self.location, applied)
                found = schema_version(conn)
        except PoolTimeout as exc:
            self.pool.close()
            raise StoreError(f"{self.location}: cannot connect to the catalog database within "
                             f"{timeout:g} s (COMPLEMENTME_DATABASE_TIMEOUT): {_first_line(exc)}") from None
        except BaseException:
            self.pool.close()
            raise
        if found != SCHEMA_VERSION:
            self.pool.close()
            raise StoreError(
                f"{self.location}: the catalog database has schema version {found}, this service needs "
                f"{SCHEMA_VERSION}: run `complementme catalog migrate` (with COMPLEMENTME_DATABASE_URL "
                "set) or start with COMPLEMENTME_DATABASE_MIGRATE=true")

    def close(self) -> None:
        self.pool.close()

    # ------------------------------------------------------------------ plumbing
    def _set_state(self, error: BaseException | None) -> None:
        with self._state_lock:
            if error is None and not self.available:
                log.info("%s: the catalog database is reachable again", self.location)
            elif error is not None and self.available:
                log.warning("%s: the catalog database cannot be reached: %s", self.location,
                            _first_line(error))
            self.available = error is None
            self.last_error = None if error is None else _first_line(error)

    @contextmanager
    def _errors(self) -> Iterator[None]:
        """psycopg's errors as ``StoreError`` (``StoreUnavailableError`` for an unreachable database)."""
        try:
            yield
        except (psycopg.OperationalError, psycopg.InterfaceError, PoolTimeout) as exc:
            self._set_state(exc)
            raise StoreUnavailableError(f"{self.location}: the catalog database cannot be reached "
                                        f"({_first_line(exc)})") from exc
        except psycopg.Error as exc:
            raise StoreError(f"{self.location}: {_first_line(exc)}") from exc
        self._set_state(None)

    def connect_listener(self) -> psycopg.Connection[Any]:
        """A connection of its own (autocommit) for LISTEN; ``StoreUnavailableError`` if it fails."""
        with self._errors():
            return psycopg.connect(self._conninfo, autocommit=True)

    @contextmanager
    def transaction(self) -> Iterator[psycopg.Connection[Any]]:
        """A write transaction that holds the write lock (see the module doc) from its start."""
        with self._errors(), self.pool.connection() as conn, conn.transaction():
            conn.execute("LOCK TABLE changes IN EXCLUSIVE MODE")
            yield conn

    @staticmethod
    def _next_seq(conn: psycopg.Connection[Any], kind: str, part: int | None) -> int:
        row = conn.execute("INSERT INTO changes (seq, kind, part, at) "
                           "SELECT COALESCE(MAX(seq), 0) + 1, %s, %s, now() FROM changes RETURNING seq",
                           (kind, part)).fetchone()
        assert row is not None
        conn.execute("SELECT pg_notify(%s, %s)", (CHANNEL, str(row[0])))  # delivered at commit
        return int(row[0])

    @contextmanager
    def reading(self) -> Iterator[None]:
        """One consistent view of the database for every read inside (a repeatable-read transaction)."""
        if getattr(self._local, "conn", None) is not None:
            yield
            return
        with self._errors(), self.pool.connection() as conn, conn.transaction():
            conn.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ READ ONLY")
            self._local.conn = conn
            try:
                yield
            finally:
                self._local.conn = None

    def _query(self, sql: str, params: dict[str, Any] | tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
        conn = getattr(self._local, "conn", None)
        if conn is not None:
            with self._errors():
                return conn.execute(sql, params).fetchall()
        with self._errors(), self.pool.connection() as conn:
            return conn.execute(sql, params).fetchall()

    # ------------------------------------------------------------------ writes
    def add(self, part: NewPart, shape_id: str | None, may_commit: Callable[[], bool] | None = None, *,
            idempotency_key: str | None = None, request_sha256: str | None = None) -> StoredPart:
        """Store a part in one transaction and return its row; its id is ``<shape_id>/<n>``.

        As ``CatalogStore.add``; besides, an ``idempotency_key`` already used raises
        ``KeyTakenError`` with the part it added (and nothing is stored).
        """
        g = part.geometry
        data = encode_geometry(g)
        sha = hashlib.sha256(data).hexdigest()
        with self.transaction() as conn:
            if idempotency_key is not None:
                taken = self._by_key(conn, idempotency_key)
                if taken is not None:
                    raise KeyTakenError(*taken)
            row = conn.execute("SELECT nextval('part_ids')").fetchone()
            assert row is not None
            pid = int(row[0])
            shape = added_shape_id(shape_id, pid)
            counted = conn.execute("SELECT COUNT(*) FROM parts WHERE shape_id = %s", (shape,)).fetchone()
            new_id = format_part_id(shape, int(counted[0]) if counted else 0)
            seq = self._next_seq(conn, "add", pid)
            created = conn.execute(
                "INSERT INTO parts (id, part_id, shape_id, category, name, style, label, translation, "
                "bbox_min, bbox_max, area, n_vertices, n_faces, mesh_sha256, added_seq, created_at, "
                "idempotency_key, request_sha256) VALUES (%s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s, "
                "%s, %s, %s, now(), %s, %s) RETURNING created_at",
                (pid, new_id, shape, part.category, part.name, part.style, part.label,
                 vec6(part.translation), vec6(part.bbox_min), vec6(part.bbox_max), float(part.area),
                 len(g.vertices), len(g.faces), sha, seq, idempotency_key, request_sha256)).fetchone()
            assert created is not None
            conn.execute("INSERT INTO part_embeddings (part, model_version, embedding, part_feature, "
                         "computed_at) VALUES (%s, %s, %s, %s, now())",
                         (pid, part.model_version, _blob(part.embedding), _blob(part.part_feature)))
            conn.execute("INSERT INTO part_meshes (part, data) VALUES (%s, %s)", (pid, data))
            if may_commit is not None and not may_commit():
                raise CommitRefusedError(f"the add of {new_id} was rolled back: its request's "
                                         "deadline passed")
        return StoredPart(
            id=pid, part_id=new_id, shape_id=shape, category=part.category, name=part.name,
            style=part.style, label=part.label, translation=vec6(part.translation),
            bbox_min=vec6(part.bbox_min), bbox_max=vec6(part.bbox_max), area=float(part.area),
            embedding=np.asarray(part.embedding, np.float32),
            part_feature=np.asarray(part.part_feature, np.float32),
            model_version=part.model_version, geometry="", geometry_sha256=sha, n_vertices=len(g.vertices),
            n_faces=len(g.faces), added_seq=seq, deleted_seq=None, created_at=_iso(created[0]))

    def _by_key(self, conn: psycopg.Connection[Any], key: str) -> tuple[StoredPart, str | None] | None:
        found = conn.execute("SELECT id, request_sha256 FROM parts WHERE idempotency_key = %s",
                             (key,)).fetchone()
        if found is None:
            return None
        row = conn.execute(_SELECT_PARTS + " WHERE p.id = %(id)s",
                           {"version": self.model_version, "id": found[0]}).fetchone()
        assert row is not None
        return _row_part(row), found[1]

    def find_key(self, key: str) -> tuple[StoredPart, str | None] | None:
        """The part an idempotency key added and its request's SHA-256, or None if unused."""
        with self._errors(), self.pool.connection() as conn:
            return self._by_key(conn, key)

    def delete(self, part_id: str) -> int | None:
        """Mark an added part deleted; its change sequence number, or None if no such live part."""
        with self.transaction() as conn:
            row = conn.execute("SELECT id FROM parts WHERE part_id = %s AND deleted_seq IS NULL",
                               (part_id,)).fetchone()
            if row is None:
                return None
            seq = self._next_seq(conn, "delete", int(row[0]))
            conn.execute("UPDATE parts SET deleted_seq = %s WHERE id = %s", (seq, row[0]))
        return seq

    def update_embeddings(self, updates: list[tuple[int, np.ndarray, np.ndarray]], model_version: str) -> int:
        """``CatalogStore.update_embeddings`` (same arguments and result), but only ``model_version``'s
        embeddings and part features are replaced: other versions' stay, for replicas still on them."""
        with self.transaction() as conn:
            seq = self._next_seq(conn, "reembed", None)
            with conn.cursor() as cur:
                cur.executemany(
                    "INSERT INTO part_embeddings (part, model_version, embedding, part_feature, computed_at) "
                    "VALUES (%s, %s, %s, %s, now()) ON CONFLICT (part, model_version) DO UPDATE SET "
                    "embedding = EXCLUDED.embedding, part_feature = EXCLUDED.part_feature, "
                    "computed_at = EXCLUDED.computed_at",
                    [(pid, model_version, _blob(e), _blob(f)) for pid, e, f in updates])
        return seq

    # ------------------------------------------------------------------ reads
    def last_seq(self) -> int:
        """The sequence number of the latest change (0 for a new database)."""
        return int(self._query("SELECT COALESCE(MAX(seq), 0) FROM changes")[0][0])

    def changes_since(self, seq: int) -> list[Change]:
        rows = self._query("SELECT seq, kind, part FROM changes WHERE seq > %s ORDER BY seq", (seq,))
        return [Change(int(s), k, None if p is None else int(p)) for s, k, p in rows]

    def parts(self, ids: list[int] | None = None, alive_only: bool = True) -> list[StoredPart]:
        """Rows by ``parts.id`` (all when ``ids`` is None), in id order (= order of addition)."""
        where = ["p.deleted_seq IS NULL"] if alive_only else []
        params: dict[str, Any] = {"version": self.model_version}
        if ids is not None:
            if not ids:
                return []
            where.append("p.id = ANY(%(ids)s)")
            params["ids"] = list(ids)
        sql = _SELECT_PARTS + (" WHERE " + " AND ".join(where) if where else "") + " ORDER BY p.id"
        return [_row_part(r) for r in self._query(sql, params)]

    def shape_count(self, shape_id: str) -> int:
        """Parts ever added to a shape (deleted ones included)."""
        return int(self._query("SELECT COUNT(*) FROM parts WHERE shape_id = %s", (shape_id,))[0][0])

    def counts(self) -> tuple[int, int]:
        """(live parts, deleted parts)."""
        alive, deleted = self._query("SELECT COUNT(*) FILTER (WHERE deleted_seq IS NULL), "
                                     "COUNT(*) FILTER (WHERE deleted_seq IS NOT NULL) FROM parts")[0]
        return int(alive), int(deleted)

    def read_geometries(self, parts: list[StoredPart]) -> dict[int, PartGeometry | StoreError]:
        """The parts' meshes, checked against their SHA-256, by ``parts.id`` (a bad one: its error)."""
        found: dict[int, PartGeometry | StoreError] = {}
        for start in range(0, len(parts), MESH_BATCH):
            chunk = {p.id: p for p in parts[start:start + MESH_BATCH]}
            rows = dict(self._query("SELECT part, data FROM part_meshes WHERE part = ANY(%s)",
                                    (list(chunk),)))
            for pid, p in chunk.items():
                name = f"{self.location} part_meshes.part={pid}"
                data = rows.get(pid)
                try:
                    if data is None:
                        raise StoreError(f"{name}: the mesh of part {p.part_id!r} is missing")
                    if hashlib.sha256(data).hexdigest() != p.geometry_sha256:
                        raise StoreError(f"{name}: the mesh of part {p.part_id!r} does not match its "
                                         "checksum")
                    found[pid] = decode_geometry(bytes(data), name)
                except StoreError as exc:
                    found[pid] = exc
        return found

    def read_geometry(self, part: StoredPart) -> PartGeometry:
        """Load and check a part's mesh (SHA-256 against its row)."""
        got = self.read_geometries([part])[part.id]
        if isinstance(got, StoreError):
            raise got
        return got
