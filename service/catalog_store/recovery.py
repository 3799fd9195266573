"""Checking and repairing a data folder: ``complementme catalog verify`` and ``... recover``.

``verify`` compares the three records of a folder against each other without changing
anything: the database (SQLite's integrity check; every row's geometry file present and
matching its SHA-256, and the copy of the row inside the file agreeing with it), the geometry
files (every file under its final name has a row: a final name is only given after the commit,
so one without a row is a lost commit), and the index file (the change it reflects is not past
the database's last one; the parts it holds are live ones).

``recover`` rebuilds what a database lost from the files: every geometry file (in ``geometry/``
or ``quarantine/``) whose row is missing and that carries a copy of its row gets the row back
(same id, same part id, same change number when that number is free), the files move back to
``geometry/``, the id and change counters are raised past every number the folder has used (so
no id or change number is ever issued twice), and the index file is set aside to be rebuilt.
What files cannot tell is reported, not guessed: deletes and re-embeddings that were lost (the
parts they deleted are live again), and adds that never committed (pending files, left in
quarantine). Run it with every server of the folder stopped.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from service.artifacts.files import fsync_dir
from service.catalog_store.snapshot import read_index_file
from service.catalog_store.store import (
    DB_FILE,
    GEOMETRY_DIR,
    INDEX_FILE,
    PENDING,
    CatalogStore,
    StoreError,
    geometry_name,
    raise_sequence,
    read_index_seq,
    read_record,
    scan_files,
)

log = logging.getLogger(__name__)


@dataclass
class Report:
    """What a check or a repair found; every line names the file it is about."""

    problems: list[str] = field(default_factory=list)   # mismatches (verify) or what was not restored
    notes: list[str] = field(default_factory=list)      # harmless findings, fixed at the next start
    restored: list[str] = field(default_factory=list)   # part ids whose rows were rebuilt (recover)

    @property
    def ok(self) -> bool:
        return not self.problems


def verify(folder: Path) -> Report:
    """Check database, geometry files and index against each other (read-only)."""
    folder = Path(folder)
    report = Report()
    db_path = folder / DB_FILE
    if not db_path.is_file():
        report.problems.append(f"{db_path}: the database is missing")
        rows: dict[str, tuple[int, str, str, int | None]] = {}
        last = 0
    else:
        try:
            rows, last = _read_database(db_path, report)
        except sqlite3.DatabaseError as exc:
            report.problems.append(f"{db_path}: {exc}")
            return report
    files = scan_files(folder)
    geometry = folder / GEOMETRY_DIR
    for name, (pid, part_id, sha, _) in rows.items():
        path = geometry / name if name in files.final else geometry / (name + PENDING)
        if name not in files.final and name not in files.pending:
            report.problems.append(f"{geometry / name}: missing (part {part_id!r}); the part is not served")
            continue
        if name not in files.final:
            report.notes.append(f"{path}: committed but not yet renamed (done at the next start)")
        data = path.read_bytes()
        if hashlib.sha256(data).hexdigest() != sha:
            report.problems.append(f"{path}: does not match its checksum (part {part_id!r})")
            continue
        try:
            record = read_record(data, str(path))
        except StoreError as exc:
            report.problems.append(str(exc))
            continue
        if record is not None and (record.id != pid or record.fields["part_id"] != part_id):
            report.problems.append(f"{path}: its copy of the row says id {record.id} "
                                   f"({record.fields['part_id']!r}), the database {pid} ({part_id!r})")
    lost = sorted(set(files.final) - set(rows))
    for name in lost:
        report.problems.append(f"{geometry / name}: no row in {db_path}: a committed add the database lost "
                               "(`complementme catalog recover` restores it)")
    for name in sorted(set(files.pending) - set(rows)):
        report.notes.append(f"{geometry / (name + PENDING)}: an add that never committed (moved to "
                            "quarantine at the next start)")
    for path in files.quarantined:
        report.notes.append(f"{path}: in quarantine")
    _verify_index(folder, rows, last, report)
    return report


def _read_database(db_path: Path, report: Report) -> tuple[dict[str, tuple[int, str, str, int | None]], int]:
    """Rows by geometry file name, and the last change; SQLite's integrity problems into ``report``."""
    conn = sqlite3.connect(f"file:{db_path}?mode=ro", uri=True)
    try:
        check = [r[0] for r in conn.execute("PRAGMA integrity_check").fetchall()]
        if check != ["ok"]:
            report.problems.append(f"{db_path}: SQLite's integrity check: {'; '.join(check[:5])}")
        rows = {g: (pid, part_id, sha, deleted) for pid, part_id, g, sha, deleted in conn.execute(
            "SELECT id, part_id, geometry, geometry_sha256, deleted_seq FROM parts")}
        last = int(conn.execute("SELECT COALESCE(MAX(seq), 0) FROM changes").fetchone()[0])
    finally:
        conn.close()
    return rows, last


def _verify_index(folder: Path, rows: dict[str, tuple[int, str, str, int | None]], last: int,
                  report: Report) -> None:
    path = folder / INDEX_FILE
    found = read_index_file(path) if path.is_file() else None
    if found is None:
        report.notes.append(f"{path}: missing or unreadable (rebuilt at the next start)")
        return
    if found.seq > last:
        report.problems.append(f"{path}: reflects change {found.seq}, past the database's last change "
                               f"{last}: the database lost changes")
        return
    live = {pid for pid, _, _, deleted in rows.values() if deleted is None}
    indexed = set(found.row_ids.tolist())
    extra = indexed - live
    if extra:
        report.problems.append(f"{path}: holds {len(extra)} part(s) that are not live in the database "
                               f"(ids {sorted(extra)[:5]})")
    elif found.seq == last and live - indexed:
        # An index written at the database's last change holds every live part: one missing means
        # the file was damaged or replaced. The next start rebuilds it; until then it is wrong.
        missing = sorted(live - indexed)
        report.problems.append(f"{path}: reflects change {found.seq}, the database's last, but lacks "
                               f"{len(missing)} live part(s) (ids {missing[:5]}); the next start "
                               "rebuilds it from the database")
    elif found.seq < last:
        report.notes.append(f"{path}: reflects change {found.seq}, the database is at {last} (brought up to "
                            "date at the next start)")


def recover(folder: Path) -> Report:
    """Rebuild rows the database lost from the geometry files (see the module doc).

    Every server using the folder must be stopped. Safe to run again: files whose rows exist are
    left alone.
    """
    folder = Path(folder)
    report = Report()
    index_seq = read_index_seq(folder / INDEX_FILE)
    store = CatalogStore(folder)  # creates an empty database if it was missing
    try:
        with store.transaction() as conn:
            taken_ids = {r[0] for r in conn.execute("SELECT id FROM parts")}
            taken_names = {r[0] for r in conn.execute("SELECT part_id FROM parts")}
            taken_seqs = {r[0] for r in conn.execute("SELECT seq FROM changes")}
            files = scan_files(folder)
            candidates = [(store.geometry_dir / n, pid) for n, pid in files.final.items()
                          if pid not in taken_ids]
            candidates += [(p, int(p.name[:8])) for p in files.quarantined
                           if p.name.endswith(".npz") and p.name[:8].isdigit()]
            for path, pid in sorted(candidates, key=lambda c: c[1]):
                _restore(store, conn, path, pid, taken_ids, taken_names, taken_seqs, report)
            for path in files.quarantined:
                if path.name.endswith(PENDING) or PENDING + "." in path.name:
                    report.notes.append(f"{path}: an add that never committed; left in quarantine")
            high = max([files.high_water, *taken_ids], default=0)
            raise_sequence(conn, "parts", high)
            last = int(conn.execute("SELECT COALESCE(MAX(seq), 0) FROM changes").fetchone()[0])
            raise_sequence(conn, "changes", max(last, index_seq or 0))
        fsync_dir(store.geometry_dir)
        if index_seq is not None and index_seq > last:
            report.problems.append(
                f"{store.index_path}: reflected change {index_seq}, the database with the restored adds "
                f"ends at {last}: {index_seq - last} change(s) (deletes or re-embeddings) cannot be rebuilt "
                "from files; parts deleted by them are live again (delete them again if needed)")
        if store.index_path.exists() and (report.restored or (index_seq or 0) != last):
            aside = store.index_path.with_name(store.index_path.name + ".before-recover")
            os.replace(store.index_path, aside)
            report.notes.append(f"{store.index_path}: moved to {aside.name}; rebuilt at the next start")
    finally:
        store.close()
    return report


def _restore(store: CatalogStore, conn: sqlite3.Connection, path: Path, pid: int, taken_ids: set[int],
             taken_names: set[str], taken_seqs: set[int], report: Report) -> None:
    """Insert the row a geometry file carries a copy of, and put the file back in ``geometry/``."""
    data = path.read_bytes()
    try:
        record = read_record(data, str(path))
    except StoreError as exc:
        report.problems.append(f"{exc}; not restored")
        return
    if record is None:
        report.problems.append(f"{path}: written before files carried a copy of their row; not restored")
        return
    f = record.fields
    if record.id != pid or pid in taken_ids or f["part_id"] in taken_names:
        report.problems.append(f"{path}: part {f['part_id']!r} (id {record.id}) clashes with a row of the "
                               "database; not restored")
        return
    seq = record.added_seq if record.added_seq not in taken_seqs else None
    seq = conn.execute("INSERT INTO changes (seq, kind, part, at) VALUES (?, 'add', ?, ?)",
                       (seq, pid, f["created_at"])).lastrowid
    assert seq is not None
    fields = {**f, **{k: json.dumps(f[k]) for k in ("translation", "bbox_min", "bbox_max")}}
    name = geometry_name(pid)
    store.insert_row(conn, pid, seq, fields, np.asarray(record.embedding), np.asarray(record.part_feature),
                      name, hashlib.sha256(data).hexdigest())
    if path.parent != store.geometry_dir:
        os.replace(path, store.geometry_dir / name)
    taken_ids.add(pid)
    taken_names.add(f["part_id"])
    taken_seqs.add(seq)
    report.restored.append(f["part_id"])
    log.info("restored part %s from %s", f["part_id"], path)
