"""The catalog additions' store: SQLite (WAL, synchronous=FULL) plus one geometry file per part.

Layout of a data folder (``COMPLEMENTME_DATA_DIR``)::

    catalog.sqlite3         the source of truth: one row per added part (its record, its
                            embedding and placement feature as float32 BLOBs, the model version
                            that computed them, its geometry file's name and SHA-256) and a change
                            log whose sequence numbers order every add, delete and re-embedding
    catalog.sqlite3-wal     SQLite's write-ahead log (part of the database while it is open)
    geometry/00000042.npz   one part's centred mesh and preview points, immutable once written,
                            with a copy of its row (record, embedding, part feature, change
                            number) inside: enough to rebuild the row if the database loses it
    added-index.npz         FAISS index of the added embeddings, tagged with the change sequence
                            it reflects; derived, rebuilt whenever it does not match the database
    quarantine/             files that no row explains, moved aside at start (never deleted)

Write order of an add: one ``BEGIN IMMEDIATE`` transaction (SQLite's write lock, which also
holds across processes) inserts the change and the row, writes the geometry file under a
*pending* name (``00000042.npz.pending``: temporary file, fsync, rename, fsync of the folder)
and commits; only then is the file renamed to its final name. So a final name without a row is
proof that a committed add was lost (a deleted ``catalog.sqlite3-wal``, an older database put
back): the server refuses to start and ``complementme catalog recover`` rebuilds the rows from
the files (``service.catalog_store.recovery``). A pending file without a row is an add that never committed
(a crash before the commit): it is moved to ``quarantine/`` at the next start. A pending file
whose row exists (a crash between the commit and the rename) is renamed at the next start, and
read under its pending name until then. Deleted parts keep their row (marked with the delete's
sequence number) and their file. Ids are never reused: the id counter is raised past every
geometry file at start, quarantined ones included.
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
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np

from service.artifacts.files import fsync_dir, remove_stale_temporaries, write_file_atomic
from service.artifacts.layout import format_part_id

log = logging.getLogger(__name__)

SCHEMA_VERSION = 1
DB_FILE = "catalog.sqlite3"
GEOMETRY_DIR = "geometry"
QUARANTINE_DIR = "quarantine"
INDEX_FILE = "added-index.npz"
PENDING = ".pending"       # suffix of a geometry file whose row is not known to be committed
RECORD_FORMAT = 1          # version of the row copy kept inside each geometry file
# A part added without a shape id gets a shape of its own named after its row; a client may not
# choose such a name (``service.catalog_store.writer``).
ADDED_SHAPE_PREFIX = "added-"


def added_shape_id(shape_id: str | None, row_id: int) -> str:
    """The shape an added part belongs to: the one the client named, else a shape of its own."""
    return shape_id or f"{ADDED_SHAPE_PREFIX}{row_id}"

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


class CatalogDamagedError(StoreError):
    """The database lacks commits that the folder's other files prove were made (see module doc)."""


class CommitRefusedError(StoreError):
    """An add was rolled back because its request's deadline would not leave time to answer."""


class StoreUnavailableError(StoreError):
    """The database cannot be reached now (PostgreSQL down, a timeout): nothing was written."""


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


def vec6(v: np.ndarray) -> list[float]:
    # Six decimals, as the exporter writes catalog.json: float32 noise is not information.
    return [round(float(x), 6) for x in v]


def _vec_json(v: np.ndarray) -> str:
    return json.dumps(vec6(v))


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


def encode_geometry(geometry: PartGeometry, record: dict[str, Any] | None = None,
                    embedding: np.ndarray | None = None, part_feature: np.ndarray | None = None) -> bytes:
    """The geometry file's bytes: an uncompressed npz of vertices, faces and points, plus (for a
    stored part) a copy of its row: ``record`` as JSON, ``embedding`` and ``part_feature``."""
    arrays: dict[str, Any] = {"vertices": np.ascontiguousarray(geometry.vertices, dtype="<f4"),
              "faces": np.ascontiguousarray(geometry.faces, dtype="<i4"),
              "points": np.ascontiguousarray(geometry.points, dtype="<f2")}
    if record is not None:
        assert embedding is not None and part_feature is not None, "a record goes with its vectors"
        meta = {"format": RECORD_FORMAT, **record}
        arrays.update(record=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8),
                      embedding=np.ascontiguousarray(embedding, dtype="<f4"),
                      part_feature=np.ascontiguousarray(part_feature, dtype="<f4"))
    buf = io.BytesIO()
    np.savez(buf, **arrays)
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


@dataclass
class FileRecord:
    """The copy of a part's row kept in its geometry file (what ``catalog recover`` restores).

    Shapes:
        embedding: (D,) float32; part_feature: (Fp,) float32.
    """

    id: int
    added_seq: int
    fields: dict[str, Any]   # the row's other columns, JSON values (translation etc. as lists)
    embedding: np.ndarray
    part_feature: np.ndarray


_RECORD_FIELDS = ("part_id", "shape_id", "category", "name", "style", "label", "translation", "bbox_min",
                  "bbox_max", "area", "model_version", "n_vertices", "n_faces", "created_at")


def read_record(data: bytes, name: str) -> FileRecord | None:
    """The row copy inside a geometry file; None for a file written before copies were kept.

    Raises ``StoreError`` naming the file when the file or its copy is unreadable (the zip
    members' CRC-32 is checked as they are read).
    """
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            if "record" not in z.files:
                decode_geometry(data, name)  # an old file: still check that it is whole
                return None
            meta = json.loads(bytes(z["record"]).decode())
            emb = z["embedding"].astype(np.float32)
            feat = z["part_feature"].astype(np.float32)
        fields = {k: meta[k] for k in _RECORD_FIELDS}
        record = FileRecord(int(meta["id"]), int(meta["added_seq"]), fields, emb, feat)
    except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile, EOFError) as exc:
        raise StoreError(f"{name}: not a readable geometry file ({exc})") from exc
    decode_geometry(data, name)
    return record


def geometry_name(pid: int) -> str:
    return f"{pid:08d}.npz"


_GEOMETRY = re.compile(r"^(?P<id>\d{8,})\.npz(?P<pending>\.pending)?$")


def read_index_seq(path: Path) -> int | None:
    """The change an index file says it reflects (None if there is no readable one)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return int(json.loads(bytes(z["meta"]).decode())["seq"])
    except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile, EOFError):
        return None


# --------------------------------------------------------------------------------------------
# The database.


def _connect(path: Path) -> sqlite3.Connection:
    # Autocommit mode: transactions are explicit (BEGIN IMMEDIATE ... COMMIT).
    conn = sqlite3.connect(path, isolation_level=None, check_same_thread=False, timeout=30.0)
    conn.execute("PRAGMA busy_timeout = 30000")
    conn.execute("PRAGMA synchronous = FULL")
    return conn


def _has_schema(path: Path) -> bool:
    """Whether ``path`` is a database that already holds the store's tables (read-only look)."""
    if not path.is_file() or path.stat().st_size == 0:
        return False
    conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        return conn.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'meta'"
                            ).fetchone() is not None
    finally:
        conn.close()


def raise_sequence(conn: sqlite3.Connection, table: str, value: int) -> None:
    """Make the next AUTOINCREMENT id of ``table`` larger than ``value`` (never lower it)."""
    cur = conn.execute("UPDATE sqlite_sequence SET seq = MAX(seq, ?) WHERE name = ?", (value, table))
    if cur.rowcount == 0 and value > 0:
        conn.execute("INSERT INTO sqlite_sequence (name, seq) VALUES (?, ?)", (table, value))


@dataclass
class FolderFiles:
    """The geometry files of a data folder, sorted by what their names say (see module doc)."""

    final: dict[str, int]                # file name -> parts.id, final names in geometry/
    pending: dict[str, int]              # final name -> parts.id, for the pending files
    temporaries: list[Path]              # unfinished writes (never complete: safe to remove)
    quarantined: list[Path]              # everything in quarantine/
    high_water: int                      # the largest part id any file (quarantined too) carries


def scan_files(folder: Path) -> FolderFiles:
    geometry, quarantine = Path(folder) / GEOMETRY_DIR, Path(folder) / QUARANTINE_DIR
    final: dict[str, int] = {}
    pending: dict[str, int] = {}
    temporaries: list[Path] = []
    high = 0
    for path in sorted(geometry.iterdir()) if geometry.is_dir() else []:
        m = _GEOMETRY.match(path.name)
        if m is None:
            if path.name.endswith(".tmp"):
                temporaries.append(path)
            continue
        pid = int(m.group("id"))
        high = max(high, pid)
        if m.group("pending"):
            pending[path.name[:-len(PENDING)]] = pid
        else:
            final[path.name] = pid
    quarantined = sorted(quarantine.iterdir()) if quarantine.is_dir() else []
    for path in quarantined:
        m = re.match(r"^(\d{8,})\.npz", path.name)
        if m is not None:
            high = max(high, int(m.group(1)))
    return FolderFiles(final, pending, temporaries, quarantined, high)


def damage_message(folder: Path, problems: list[str]) -> str:
    """The refusal to start on a damaged folder: what is wrong, and how to recover."""
    return (f"{folder}: the catalog database has lost acknowledged changes, refusing to start: "
            + "; ".join(problems) + ". No file was moved or deleted. Usual causes: catalog.sqlite3-wal "
            "deleted or lost after a crash, an older catalog.sqlite3 put back, the database emptied. Stop "
            f"every process using the folder, then run `complementme catalog recover {folder}` (it "
            "rebuilds the lost rows from the geometry files, which carry a copy of them); "
            f"`complementme catalog verify {folder}` lists every mismatch.")


class CatalogStore:
    """The data folder: thread-safe (one writer and one reader connection, each behind a lock).

    SQLite serialises writers across processes too, so several server workers (or the server
    and ``complementme catalog add --data-dir``) may share one folder. ``service.catalog_store.pg_store``
    offers the same methods on PostgreSQL.
    """

    backend = "sqlite"

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.geometry_dir = self.folder / GEOMETRY_DIR
        self.quarantine_dir = self.folder / QUARANTINE_DIR
        self.db_path = self.folder / DB_FILE
        self.index_path = self.folder / INDEX_FILE
        try:
            # A database missing or empty (no tables yet) beside geometry or index files is damage
            # (check_folder), not a new folder: the database is created before any other file.
            self.database_was_missing = not _has_schema(self.db_path) and (
                self.index_path.exists() or (self.geometry_dir.is_dir()
                                             and any(self.geometry_dir.glob("*.npz*"))))
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

    @contextmanager
    def _named_errors(self) -> Iterator[None]:
        """SQLite's errors as ``StoreError`` naming the database file ("database disk image is
        malformed" alone does not say which file to restore)."""
        try:
            yield
        except sqlite3.DatabaseError as exc:
            damaged = "malformed" in str(exc) or "not a database" in str(exc)
            hint = ("; the file is damaged: restore it from a backup, or run `complementme catalog "
                    f"verify {self.folder}`") if damaged else ""
            raise StoreError(f"{self.db_path}: {exc}{hint}") from exc

    def _check_schema(self) -> None:
        with self.transaction() as conn:
            row = conn.execute("SELECT value FROM meta WHERE key = 'schema_version'").fetchone()
            if row is None:
                conn.execute("INSERT INTO meta VALUES ('schema_version', ?), ('created_at', ?)",
                             (str(SCHEMA_VERSION), _now()))
            elif int(row[0]) > SCHEMA_VERSION:
                raise StoreError(f"{self.db_path}: schema version {row[0]} was written by a newer "
                                 f"version of the service (this one knows {SCHEMA_VERSION})")

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """A write transaction that holds SQLite's write lock from its start (BEGIN IMMEDIATE)."""
        with self._wlock, self._named_errors():
            self._w.execute("BEGIN IMMEDIATE")
            try:
                yield self._w
            except BaseException:
                self._w.execute("ROLLBACK")
                raise
            self._w.execute("COMMIT")

    # ------------------------------------------------------------------ writes
    def add(self, part: NewPart, shape_id: str | None,
            may_commit: Callable[[], bool] | None = None) -> StoredPart:
        """Store a part durably and return its row; its id is ``<shape_id>/<n>``.

        ``shape_id`` groups parts of one source object (``exclude_shapes`` acts on it); None
        gives the part a shape of its own, ``added-<row id>``. ``n`` counts the parts ever added
        to that shape, so ids are never reused. ``may_commit`` is asked last, just before the
        commit: False rolls the add back (``CommitRefusedError``) and nothing is stored.
        """
        with self.transaction() as conn:
            pid = conn.execute("SELECT COALESCE((SELECT seq FROM sqlite_sequence WHERE name = 'parts'), 0) "
                               "+ 1").fetchone()[0]
            pid = max(pid, conn.execute("SELECT COALESCE(MAX(id), 0) + 1 FROM parts").fetchone()[0])
            shape = added_shape_id(shape_id, pid)
            local = conn.execute("SELECT COUNT(*) FROM parts WHERE shape_id = ?", (shape,)).fetchone()[0]
            now = _now()
            seq = conn.execute("INSERT INTO changes (kind, part, at) VALUES ('add', ?, ?)",
                               (pid, now)).lastrowid
            assert seq is not None
            geometry = geometry_name(pid)
            g = part.geometry
            fields: dict[str, Any] = {
                "part_id": format_part_id(shape, local), "shape_id": shape, "category": part.category,
                "name": part.name, "style": part.style, "label": part.label,
                "translation": _vec_json(part.translation), "bbox_min": _vec_json(part.bbox_min),
                "bbox_max": _vec_json(part.bbox_max), "area": float(part.area),
                "model_version": part.model_version, "n_vertices": len(g.vertices),
                "n_faces": len(g.faces), "created_at": now}
            record = {"id": pid, "added_seq": seq, **fields,
                      **{k: json.loads(fields[k]) for k in ("translation", "bbox_min", "bbox_max")}}
            data = encode_geometry(g, record, part.embedding, part.part_feature)
            self.insert_row(conn, pid, seq, fields, part.embedding, part.part_feature, geometry,
                             hashlib.sha256(data).hexdigest())
            pending = self.geometry_dir / (geometry + PENDING)
            try:
                # Inside the transaction: the file is durable before the row that names it commits.
                write_file_atomic(pending, data)
                row = conn.execute(f"SELECT {_COLUMNS} FROM parts WHERE id = ?", (pid,)).fetchone()
                if may_commit is not None and not may_commit():
                    raise CommitRefusedError(f"the add of {fields['part_id']} was rolled back: its "
                                             "request's deadline passed")
            except BaseException:
                pending.unlink(missing_ok=True)  # still under the write lock: nobody else saw it
                raise
        self._finalize(geometry)
        return _row_part(row)

    @staticmethod
    def insert_row(conn: sqlite3.Connection, pid: int, seq: int, fields: dict[str, Any],
                    embedding: np.ndarray, part_feature: np.ndarray, geometry: str, sha: str) -> None:
        f = fields
        conn.execute(
            f"INSERT INTO parts ({_COLUMNS}) VALUES ({', '.join('?' * 21)})",
            (pid, f["part_id"], f["shape_id"], f["category"], f["name"], f["style"], f["label"],
             f["translation"], f["bbox_min"], f["bbox_max"], float(f["area"]), _blob(embedding),
             _blob(part_feature), f["model_version"], geometry, sha, int(f["n_vertices"]),
             int(f["n_faces"]), seq, None, f["created_at"]))

    def _finalize(self, geometry: str) -> None:
        """Give a committed part's file its final name (see the module doc)."""
        try:
            os.replace(self.geometry_dir / (geometry + PENDING), self.geometry_dir / geometry)
        except FileNotFoundError:
            if not (self.geometry_dir / geometry).is_file():
                raise
            return  # another process's start-up renamed it first
        fsync_dir(self.geometry_dir)

    def delete(self, part_id: str) -> int | None:
        """Mark an added part deleted; its change sequence number, or None if no such live part."""
        with self.transaction() as conn:
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
        with self.transaction() as conn:
            seq = conn.execute("INSERT INTO changes (kind, part, at) VALUES ('reembed', NULL, ?)",
                               (_now(),)).lastrowid
            conn.executemany("UPDATE parts SET embedding = ?, part_feature = ?, model_version = ? "
                             "WHERE id = ?",
                             [(_blob(e), _blob(f), model_version, pid) for pid, e, f in updates])
        return int(seq) if seq is not None else 0

    def check_folder(self) -> int:
        """At start: refuse a folder whose database lost commits; tidy what crashes leave.

        Under the database's write lock (no writer of any process is inside an add): a geometry
        file under its final name without a row, an index file ahead of the database, or geometry
        or index files beside a database that was missing or empty mean that acknowledged changes
        are lost: ``CatalogDamagedError`` naming the files, and nothing is touched. Otherwise
        pending files of committed rows get their final names, pending files of adds that never
        committed (and old-format files without a row) move to ``quarantine/``, unfinished
        temporaries are removed, and the id counter is raised past every file's id.

        Returns:
            the number of files moved to quarantine.
        """
        with self.transaction() as conn:
            named = {r[0] for r in conn.execute("SELECT geometry FROM parts")}
            last = int(conn.execute("SELECT COALESCE(MAX(seq), 0) FROM changes").fetchone()[0])
            files = scan_files(self.folder)
            index_seq = read_index_seq(self.index_path)
            lost: list[str] = []
            legacy: list[str] = []
            for name in sorted(set(files.final) - named):
                path = self.geometry_dir / name
                try:
                    has_record = read_record(path.read_bytes(), str(path)) is not None
                except (OSError, StoreError):
                    has_record = True  # unreadable: it cannot be explained as an old orphan either
                (lost if has_record else legacy).append(name)
            problems = [f"{len(lost)} geometry file(s) of committed parts have no row in "
                        f"{self.db_path} ({_names(self.geometry_dir, lost)})"] if lost else []
            if index_seq is not None and index_seq > last:
                problems.append(f"the index file {self.index_path} reflects change {index_seq}, the database "
                                f"ends at change {last}")
            if self.database_was_missing:
                problems.insert(0, f"{self.db_path} was missing or empty beside existing geometry or index "
                                   "files")
            if problems:
                raise CatalogDamagedError(damage_message(self.folder, problems))
            for path in files.temporaries:
                path.unlink(missing_ok=True)
            moved = [self._quarantine(self.geometry_dir / n) for n in legacy]
            for name in files.pending:
                if name in named:
                    self._finalize(name)
                else:
                    moved.append(self._quarantine(self.geometry_dir / (name + PENDING)))
            raise_sequence(conn, "parts", files.high_water)
        if moved:
            log.warning("%s: moved %d geometry file(s) that no committed row names to %s: %s", self.folder,
                        len(moved), self.quarantine_dir, ", ".join(p.name for p in moved))
        remove_stale_temporaries(self.folder)
        return len(moved)

    def _quarantine(self, path: Path) -> Path:
        """Move a file into ``quarantine/`` (never over another one there) durably."""
        self.quarantine_dir.mkdir(exist_ok=True)
        dest = self.quarantine_dir / path.name
        n = 0
        while dest.exists():
            n += 1
            dest = self.quarantine_dir / f"{path.name}.{n}"
        os.replace(path, dest)
        fsync_dir(self.quarantine_dir)
        fsync_dir(path.parent)
        return dest

    # ------------------------------------------------------------------ reads
    @contextmanager
    def reading(self) -> Iterator[None]:
        """One consistent view of the database for every read inside (a read transaction)."""
        with self._rlock, self._named_errors():
            self._r.execute("BEGIN")
            try:
                yield
            finally:
                self._r.execute("COMMIT")

    def _query(self, sql: str, params: tuple[Any, ...] | list[Any] = ()) -> list[Any]:
        with self._rlock, self._named_errors():
            return self._r.execute(sql, params).fetchall()

    def last_seq(self) -> int:
        """The sequence number of the latest change (0 for a new folder)."""
        return int(self._query("SELECT COALESCE(MAX(seq), 0) FROM changes")[0][0])

    def changes_since(self, seq: int) -> list[Change]:
        rows = self._query("SELECT seq, kind, part FROM changes WHERE seq > ? ORDER BY seq", (seq,))
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
        return [_row_part(r) for r in self._query(sql, params)]

    def shape_count(self, shape_id: str) -> int:
        """Parts ever added to a shape (deleted ones included)."""
        return int(self._query("SELECT COUNT(*) FROM parts WHERE shape_id = ?", (shape_id,))[0][0])

    def counts(self) -> tuple[int, int]:
        """(live parts, deleted parts)."""
        alive, deleted = self._query(
            "SELECT COALESCE(SUM(deleted_seq IS NULL), 0), COALESCE(SUM(deleted_seq IS NOT NULL), 0) "
            "FROM parts")[0]
        return int(alive), int(deleted)

    def geometry_path(self, name: str) -> Path:
        """Where a row's file is: its final name, or its pending name while its writer renames it."""
        path = self.geometry_dir / name
        if not path.exists() and (self.geometry_dir / (name + PENDING)).exists():
            return self.geometry_dir / (name + PENDING)
        return path

    @property
    def location(self) -> str:
        """Where the store is, for logs and errors."""
        return str(self.folder)

    def read_geometries(self, parts: list[StoredPart]) -> dict[int, PartGeometry | StoreError]:
        """``read_geometry`` of several parts, by ``parts.id``; a part that fails gets its error."""
        found: dict[int, PartGeometry | StoreError] = {}
        for p in parts:
            try:
                found[p.id] = self.read_geometry(p)
            except StoreError as exc:
                found[p.id] = exc
        return found

    def read_geometry(self, part: StoredPart) -> PartGeometry:
        """Load and check a part's geometry file (SHA-256 against its row)."""
        path = self.geometry_path(part.geometry)
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
        return "; ".join(r[0] for r in self._query("PRAGMA integrity_check"))

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
            with self._rlock, self._named_errors():
                self._r.backup(target)
            names = [r[0] for r in target.execute("SELECT geometry FROM parts")]
        finally:
            target.close()
        for name in names:
            shutil.copy2(self.geometry_path(name), dest / GEOMETRY_DIR / name)
        fsync_dir(dest / GEOMETRY_DIR)
        return len(names) + 1


def _names(folder: Path, names: list[str], most: int = 5) -> str:
    shown = ", ".join(str(folder / n) for n in names[:most])
    return shown + (f" and {len(names) - most} more" if len(names) > most else "")
