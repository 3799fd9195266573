"""The catalog additions' store: SQLite (WAL, synchronous=FULL) plus one geometry file per part.

Layout of a data folder (``COMPLEMENTME_DATA_DIR``)::

    catalog.sqlite3         the source of truth: one row per added part (its record, its
                            embedding and placement feature as float32 BLOBs, the model version
                            that computed them, its geometry file's name and SHA-256) and a change
                            log whose sequence numbers order every add, delete and re-embedding
    catalog.sqlite3-wal     SQLite's write-ahead log (part of the database while it is open)
    geometry/00000042.npz   one part's centred mesh and preview points, immutable once written
    added-index.npz         FAISS index of the added embeddings, tagged with the change sequence
                            it reflects; derived, rebuilt whenever it does not match the database

Write order of an add: one ``BEGIN IMMEDIATE`` transaction (SQLite's write lock, which also
holds across processes) inserts the change and the row, writes the geometry file (temporary
file, fsync, rename, fsync of the folder) and commits. A crash before the commit leaves at most
an orphan file, removed at the next open; once the commit returns, the file is durable too.
Deleted parts keep their row (marked with the delete's sequence number) and their file.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
import re
import shutil
import sqlite3
import threading
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
DB_FILE = "catalog.sqlite3"
GEOMETRY_DIR = "geometry"
INDEX_FILE = "added-index.npz"

_SCHEMA = """
CREATE TABLE IF NOT EXISTS meta (
    key TEXT PRIMARY KEY,
    value TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS changes (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    kind TEXT NOT NULL CHECK (kind IN ('add', 'delete', 'reembed')),
    part INTEGER,                    -- parts.id; NULL for a re-embedding of every part
    at TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS parts (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    part_id TEXT NOT NULL UNIQUE,
    shape_id TEXT NOT NULL,
    category TEXT NOT NULL,
    name TEXT,
    style TEXT,
    label TEXT,
    translation TEXT NOT NULL,       -- JSON [x, y, z]: bounding-box centre, canonical frame
    bbox_min TEXT NOT NULL,          -- JSON [x, y, z]: centred bounding box
    bbox_max TEXT NOT NULL,
    area REAL NOT NULL,
    embedding BLOB NOT NULL,         -- little-endian float32, the model's embedding size
    part_feature BLOB NOT NULL,      -- little-endian float32, h's part feature
    model_version TEXT NOT NULL,     -- the model that computed embedding and part_feature
    geometry TEXT NOT NULL,          -- file name under geometry/
    geometry_sha256 TEXT NOT NULL,
    n_vertices INTEGER NOT NULL,
    n_faces INTEGER NOT NULL,
    added_seq INTEGER NOT NULL,
    deleted_seq INTEGER,             -- NULL while the part is in the catalog
    created_at TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS parts_shape ON parts (shape_id);
"""


class StoreError(RuntimeError):
    """The data folder cannot be used (unreadable database, damaged geometry file, newer schema)."""


@dataclass
class PartGeometry:
    """A part's centred mesh and preview samples, as kept in its geometry file.

    Shapes:
        vertices: (V, 3) float32; faces: (F, 3) int32; points: (S, 3) float16.
    """

    vertices: np.ndarray
    faces: np.ndarray
    points: np.ndarray


@dataclass
class NewPart:
    """Everything an add stores: metadata, the model's outputs and the geometry.

    Shapes:
        translation, bbox_min, bbox_max: (3,) float; embedding: (D,) float32;
        part_feature: (Fp,) float32.
    """

    category: str
    name: str | None
    style: str | None
    label: str | None
    translation: np.ndarray
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    area: float
    embedding: np.ndarray
    part_feature: np.ndarray
    model_version: str
    geometry: PartGeometry


@dataclass
class StoredPart:
    """One row of ``parts`` (geometry not loaded: see ``CatalogStore.read_geometry``)."""

    id: int
    part_id: str
    shape_id: str
    category: str
    name: str | None
    style: str | None
    label: str | None
    translation: list[float]
    bbox_min: list[float]
    bbox_max: list[float]
    area: float
    embedding: np.ndarray
    part_feature: np.ndarray
    model_version: str
    geometry: str
    geometry_sha256: str
    n_vertices: int
    n_faces: int
    added_seq: int
    deleted_seq: int | None
    created_at: str


@dataclass
class Change:
    seq: int
    kind: str          # "add", "delete" or "reembed"
    part: int | None   # parts.id


_COLUMNS = ("id, part_id, shape_id, category, name, style, label, translation, bbox_min, bbox_max, area, "
            "embedding, part_feature, model_version, geometry, geometry_sha256, n_vertices, n_faces, "
            "added_seq, deleted_seq, created_at")


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


def _vec_json(v: np.ndarray) -> str:
    # Six decimals, as the exporter writes catalog.json: float32 noise is not information.
    return json.dumps([round(float(x), 6) for x in v])


def _blob(a: np.ndarray) -> bytes:
    return np.ascontiguousarray(a, dtype="<f4").tobytes()


def _row_part(row: tuple[Any, ...]) -> StoredPart:
    (pid, part_id, shape_id, category, name, style, label, translation, bmin, bmax, area, emb, feat,
     version, geometry, sha, nv, nf, added, deleted, created) = row
    return StoredPart(
        id=pid, part_id=part_id, shape_id=shape_id, category=category, name=name, style=style, label=label,
        translation=json.loads(translation), bbox_min=json.loads(bmin), bbox_max=json.loads(bmax),
        area=float(area), embedding=np.frombuffer(emb, dtype="<f4").astype(np.float32),
        part_feature=np.frombuffer(feat, dtype="<f4").astype(np.float32), model_version=version,
        geometry=geometry, geometry_sha256=sha, n_vertices=nv, n_faces=nf, added_seq=added,
        deleted_seq=deleted, created_at=created)


# --------------------------------------------------------------------------------------------
# Durable files.


def fsync_dir(folder: Path) -> None:
    """Make a rename or a new file in ``folder`` durable (POSIX needs the directory synced)."""
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


_TMP = re.compile(r"^\.(?P<name>.+)\.(?P<pid>\d+)\.(?P<tid>\d+)\.tmp$")


def write_file_atomic(path: Path, data: bytes) -> None:
    """Write ``data`` so that readers see the old file or the whole new one, never a part.

    Temporary file in the same folder, fsync, rename over ``path``, fsync of the folder.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(fd, view):]
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    fsync_dir(path.parent)


def remove_stale_temporaries(folder: Path) -> int:
    """Remove temporary files of ``write_file_atomic`` left by processes that no longer run."""
    removed = 0
    for p in Path(folder).glob(".*.tmp"):
        m = _TMP.match(p.name)
        if m is None:
            continue
        pid = int(m.group("pid"))
        alive = True
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            alive = False
        except PermissionError:
            alive = True
        if not alive or pid == os.getpid():
            p.unlink(missing_ok=True)
            removed += 1
    return removed


def encode_geometry(geometry: PartGeometry) -> bytes:
    """The geometry file's bytes: an uncompressed npz of vertices, faces and points."""
    buf = io.BytesIO()
    np.savez(buf, vertices=np.ascontiguousarray(geometry.vertices, dtype="<f4"),
             faces=np.ascontiguousarray(geometry.faces, dtype="<i4"),
             points=np.ascontiguousarray(geometry.points, dtype="<f2"))
    return buf.getvalue()


def decode_geometry(data: bytes, name: str) -> PartGeometry:
    """Parse a geometry file's bytes; ``StoreError`` naming the file if anything is off."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            v, f, p = z["vertices"], z["faces"], z["points"]
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as exc:
        raise StoreError(f"{name}: not a readable geometry file ({exc})") from exc
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or p.ndim != 2 or p.shape[1] != 3:
        raise StoreError(f"{name}: arrays of unexpected shapes {v.shape}, {f.shape}, {p.shape}")
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise StoreError(f"{name}: faces index vertices outside the mesh")
    return PartGeometry(v.astype(np.float32), f.astype(np.int32), p.astype(np.float16))


# --------------------------------------------------------------------------------------------
# The database.


def _connect(path: Path) -> sqlite3.Connection:
    # Autocommit mode: transactions are explicit (BEGIN IMMEDIATE ... COMMIT).
    conn = sqlite3.connect(path, isolation_level=None, check_same_thread=False, timeout=30.0)
    conn.execute("PRAGMA busy_timeout = 30000")
    conn.execute("PRAGMA synchronous = FULL")
    return conn


class CatalogStore:
    """The data folder: thread-safe (one writer and one reader connection, each behind a lock).

    SQLite serialises writers across processes too, so several server workers (or the server
    and ``complementme catalog add --data-dir``) may share one folder.
    """

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.geometry_dir = self.folder / GEOMETRY_DIR
        self.db_path = self.folder / DB_FILE
        self.index_path = self.folder / INDEX_FILE
        try:
            self.geometry_dir.mkdir(parents=True, exist_ok=True)
            self._w = _connect(self.db_path)
            mode = self._w.execute("PRAGMA journal_mode = WAL").fetchone()[0]
            if str(mode).lower() != "wal":
                raise StoreError(f"{self.db_path}: cannot switch to WAL mode (got {mode!r}); is the "
                                 "folder on a network file system?")
            self._w.executescript(_SCHEMA)
            self._r = _connect(self.db_path)
        except (OSError, sqlite3.Error) as exc:
            raise StoreError(f"{self.db_path}: cannot open the catalog database ({exc})") from exc
        self._wlock = threading.Lock()
        self._rlock = threading.RLock()
        self._check_schema()

    def close(self) -> None:
        with self._wlock, self._rlock:
            self._r.close()
            self._w.close()

    def _check_schema(self) -> None:
        with self._transaction() as conn:
            row = conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
            if row is None:
                conn.execute("INSERT INTO meta VALUES ('schema_version', ?), ('created_at', ?)",
                             (str(SCHEMA_VERSION), _now()))
            elif int(row[0]) > SCHEMA_VERSION:
                raise StoreError(f"{self.db_path}: schema version {row[0]} was written by a newer "
                                 f"version of the service (this one knows {SCHEMA_VERSION})")

    @contextmanager
    def _transaction(self) -> Iterator[sqlite3.Connection]:
        """A write transaction that holds SQLite's write lock from its start (BEGIN IMMEDIATE)."""
        with self._wlock:
            self._w.execute("BEGIN IMMEDIATE")
            try:
                yield self._w
            except BaseException:
                self._w.execute("ROLLBACK")
                raise
            self._w.execute("COMMIT")

    # ------------------------------------------------------------------ writes
    def add(self, part: NewPart, shape_id: str | None) -> StoredPart:
        """Store a part durably and return its row; its id is ``<shape_id>/<n>``.

        ``shape_id`` groups parts of one source object (``exclude_shapes`` acts on it); None
        gives the part a shape of its own, ``added-<row id>``. ``n`` counts the parts ever added
        to that shape, so ids are never reused.
        """
        data = encode_geometry(part.geometry)
        digest = hashlib.sha256(data).hexdigest()
        with self._transaction() as conn:
            pid = conn.execute("SELECT COALESCE((SELECT seq FROM sqlite_sequence WHERE name = 'parts'), 0) "
                               "+ 1").fetchone()[0]
            pid = max(pid, conn.execute("SELECT COALESCE(MAX(id), 0) + 1 FROM parts").fetchone()[0])
            shape = shape_id or f"added-{pid}"
            local = conn.execute("SELECT COUNT(*) FROM parts WHERE shape_id = ?", (shape,)).fetchone()[0]
            now = _now()
            seq = conn.execute("INSERT INTO changes (kind, part, at) VALUES ('add', ?, ?)",
                               (pid, now)).lastrowid
            geometry = f"{pid:08d}.npz"
            g = part.geometry
            conn.execute(
                f"INSERT INTO parts ({_COLUMNS}) VALUES ({', '.join('?' * 21)})",
                (pid, f"{shape}/{local}", shape, part.category, part.name, part.style, part.label,
                 _vec_json(part.translation), _vec_json(part.bbox_min), _vec_json(part.bbox_max),
                 float(part.area), _blob(part.embedding), _blob(part.part_feature), part.model_version,
                 geometry, digest, len(g.vertices), len(g.faces), seq, None, now))
            # Inside the transaction: the file is durable before the row that names it commits.
            write_file_atomic(self.geometry_dir / geometry, data)
            row = conn.execute(f"SELECT {_COLUMNS} FROM parts WHERE id = ?", (pid,)).fetchone()
        return _row_part(row)

    def delete(self, part_id: str) -> int | None:
        """Mark an added part deleted; its change sequence number, or None if no such live part."""
        with self._transaction() as conn:
            row = conn.execute("SELECT id FROM parts WHERE part_id = ? AND deleted_seq IS NULL",
                               (part_id,)).fetchone()
            if row is None:
                return None
            seq = conn.execute("INSERT INTO changes (kind, part, at) VALUES ('delete', ?, ?)",
                               (row[0], _now())).lastrowid
            conn.execute("UPDATE parts SET deleted_seq = ? WHERE id = ?", (seq, row[0]))
        return int(seq) if seq is not None else None

    def update_embeddings(self, updates: list[tuple[int, np.ndarray, np.ndarray]], model_version: str) -> int:
        """Replace embeddings and part features (after a model change) in one transaction.

        Args:
            updates: (parts.id, embedding (D,), part_feature (Fp,)) per part.

        Returns:
            the change's sequence number.
        """
        with self._transaction() as conn:
            seq = conn.execute("INSERT INTO changes (kind, part, at) VALUES ('reembed', NULL, ?)",
                               (_now(),)).lastrowid
            conn.executemany("UPDATE parts SET embedding = ?, part_feature = ?, model_version = ? "
                             "WHERE id = ?",
                             [(_blob(e), _blob(f), model_version, pid) for pid, e, f in updates])
        return int(seq) if seq is not None else 0

    def remove_orphans(self) -> int:
        """Delete geometry files no row names (left by a crash before a commit) and temporaries.

        Runs under the database's write lock, so no writer (in any process) is between writing
        a file and committing its row.
        """
        removed = 0
        with self._transaction() as conn:
            named = {r[0] for r in conn.execute("SELECT geometry FROM parts")}
            for p in self.geometry_dir.iterdir():
                if p.name not in named:
                    p.unlink(missing_ok=True)
                    removed += 1
        if removed:
            fsync_dir(self.geometry_dir)
            log.warning("%s: removed %d geometry file(s) of additions that never committed",
                        self.geometry_dir, removed)
        remove_stale_temporaries(self.folder)
        return removed

    # ------------------------------------------------------------------ reads
    @contextmanager
    def reading(self) -> Iterator[None]:
        """One consistent view of the database for every read inside (a read transaction)."""
        with self._rlock:
            self._r.execute("BEGIN")
            try:
                yield
            finally:
                self._r.execute("COMMIT")

    def last_seq(self) -> int:
        """The sequence number of the latest change (0 for a new folder)."""
        with self._rlock:
            return int(self._r.execute("SELECT COALESCE(MAX(seq), 0) FROM changes").fetchone()[0])

    def changes_since(self, seq: int) -> list[Change]:
        with self._rlock:
            rows = self._r.execute("SELECT seq, kind, part FROM changes WHERE seq > ? ORDER BY seq",
                                   (seq,)).fetchall()
        return [Change(*r) for r in rows]

    def parts(self, ids: list[int] | None = None, alive_only: bool = True) -> list[StoredPart]:
        """Rows by ``parts.id`` (all when ``ids`` is None), in id order (= order of addition)."""
        where = ["deleted_seq IS NULL"] if alive_only else []
        params: list[Any] = []
        if ids is not None:
            if not ids:
                return []
            where.append(f"id IN ({', '.join('?' * len(ids))})")
            params.extend(ids)
        sql = (f"SELECT {_COLUMNS} FROM parts" + (" WHERE " + " AND ".join(where) if where else "")
               + " ORDER BY id")
        with self._rlock:
            rows = self._r.execute(sql, params).fetchall()
        return [_row_part(r) for r in rows]

    def shape_count(self, shape_id: str) -> int:
        """Parts ever added to a shape (deleted ones included)."""
        with self._rlock:
            row = self._r.execute("SELECT COUNT(*) FROM parts WHERE shape_id = ?", (shape_id,)).fetchone()
        return int(row[0])

    def counts(self) -> tuple[int, int]:
        """(live parts, deleted parts)."""
        with self._rlock:
            alive, deleted = self._r.execute(
                "SELECT COALESCE(SUM(deleted_seq IS NULL), 0), COALESCE(SUM(deleted_seq IS NOT NULL), 0) "
                "FROM parts").fetchone()
        return int(alive), int(deleted)

    def read_geometry(self, part: StoredPart) -> PartGeometry:
        """Load and check a part's geometry file (SHA-256 against its row)."""
        path = self.geometry_dir / part.geometry
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise StoreError(f"{path}: geometry of part {part.part_id!r} cannot be read "
                             f"({exc.strerror})") from exc
        if hashlib.sha256(data).hexdigest() != part.geometry_sha256:
            raise StoreError(f"{path}: geometry of part {part.part_id!r} does not match its checksum")
        return decode_geometry(data, str(path))

    def integrity(self) -> str:
        """SQLite's own integrity check: ``"ok"`` or the problems it found."""
        with self._rlock:
            return "; ".join(r[0] for r in self._r.execute("PRAGMA integrity_check").fetchall())

    def backup(self, dest: Path) -> int:
        """Copy the data folder consistently while it is in use; returns the files copied.

        SQLite's online backup takes a consistent copy of the database; every geometry file it
        names was durable before its row committed and never changes, so copying those files
        afterwards completes the copy. The derived index is left out (rebuilt at start).
        """
        dest = Path(dest)
        if dest.exists() and any(dest.iterdir()):
            raise StoreError(f"backup destination {dest} is not empty")
        (dest / GEOMETRY_DIR).mkdir(parents=True, exist_ok=True)
        target = sqlite3.connect(dest / DB_FILE)
        try:
            with self._rlock:
                self._r.backup(target)
            names = [r[0] for r in target.execute("SELECT geometry FROM parts")]
        finally:
            target.close()
        for name in names:
            shutil.copy2(self.geometry_dir / name, dest / GEOMETRY_DIR / name)
        fsync_dir(dest / GEOMETRY_DIR)
        return len(names) + 1
