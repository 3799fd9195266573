"""A damaged data folder is refused or recovered, never silently shrunk (issue 16, finding 7).

The deleted-WAL case runs the real server in its own process: parts are added, the server is
killed with SIGKILL, ``catalog.sqlite3-wal`` is deleted (the operator's mistake), and the
restart must refuse, naming the files and the recovery command; ``complementme catalog
recover`` then brings every acknowledged part back, and no id is issued twice. The other cases
damage a folder in process: an empty or missing database beside geometry files, a quarantined
file, a verify mismatch, a malformed database file, and an add whose deadline passes.
"""

from __future__ import annotations

import shutil
import sqlite3
import threading
import time
from contextlib import closing
from pathlib import Path

import faiss
import httpx
import pytest
from catalog_testkit import LiveServer, add_part, writable_settings
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from service.api.app import create_app
from service.api.routes import catalog_write
from service.catalog_store.recovery import verify
from service.catalog_store.snapshot import read_index_file, write_index_file
from service.catalog_store.store import (
    GEOMETRY_DIR,
    INDEX_FILE,
    QUARANTINE_DIR,
    CatalogDamagedError,
    StoreError,
)
from training.catalog_cli import catalog_app

LOST = 20  # acknowledged adds that live only in the WAL when it is deleted


def _run_cli(*args: str) -> tuple[int, str]:
    result = CliRunner().invoke(catalog_app, list(args))
    return result.exit_code, result.output


def _refused_start(settings, match: str) -> str:
    with pytest.raises(CatalogDamagedError, match=match) as info, TestClient(create_app(settings)):
        pass
    return str(info.value)


def test_deleted_wal_refuses_to_start_and_recover_brings_the_parts_back(artifacts: Path,
                                                                        tmp_path: Path) -> None:
    data = tmp_path / "data"
    server = LiveServer(artifacts, data).start()
    try:
        acked: list[str] = []
        with httpx.Client(base_url=server.url, timeout=60) as http:
            for seed in range(5):
                acked.append(add_part(http, seed, category="kept").json()["part_id"])
            with closing(sqlite3.connect(data / "catalog.sqlite3")) as db:  # these five reach the main file
                assert db.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()[0] == 0
            for seed in range(5, 5 + LOST):
                r = add_part(http, seed, category="in-wal")
                assert r.status_code == 201, r.text
                acked.append(r.json()["part_id"])
        server.kill()
    finally:
        server.stop()
    (data / "catalog.sqlite3-wal").unlink()  # the operator's mistake after the crash

    settings = writable_settings(artifacts, data)
    message = _refused_start(settings, "lost acknowledged changes")
    assert f"{LOST} geometry file(s) of committed parts have no row" in message
    assert str(data / "catalog.sqlite3") in message and str(data / "added-index.npz") in message
    assert f"complementme catalog recover {data}" in message
    assert len(list((data / GEOMETRY_DIR).iterdir())) == 5 + LOST, "the refusal moved or deleted files"

    code, out = _run_cli("verify", str(data))
    assert code == 1 and out.count("a committed add the database lost") == LOST, out
    code, out = _run_cli("recover", str(data))
    assert code == 0 and f"{LOST} part(s) restored" in out, out
    assert _run_cli("verify", str(data))[0] == 0

    with TestClient(create_app(settings)) as c:
        status = c.get("/catalog").json()
        assert status["added_parts"] == 5 + LOST and status["left_out"] == []
        assert status["sequence"] == status["index_sequence"] == status["database_sequence"]
        for pid in acked:
            assert c.get(f"/parts/{pid}").status_code == 200, f"acknowledged part {pid} is lost"
        fresh = add_part(c, 999).json()["part_id"]
        assert fresh not in acked and fresh == f"added-{5 + LOST + 1}/0", "an id was issued twice"


def test_empty_or_missing_database_beside_geometry_refuses(artifacts: Path, tmp_path: Path) -> None:
    data = tmp_path / "data"
    settings = writable_settings(artifacts, data)
    with TestClient(create_app(settings)) as c:
        ids = [add_part(c, s).json()["part_id"] for s in range(3)]
    (data / "catalog.sqlite3").unlink()
    _refused_start(settings, "catalog.sqlite3 was missing or empty beside existing geometry")
    assert len(list((data / GEOMETRY_DIR).iterdir())) == 3, "geometry files were removed"
    (data / "catalog.sqlite3").write_bytes(b"")  # emptied rather than deleted: the same damage
    (data / "catalog.sqlite3-wal").unlink(missing_ok=True)
    (data / "catalog.sqlite3-shm").unlink(missing_ok=True)
    _refused_start(settings, "3 geometry file")
    assert _run_cli("recover", str(data))[0] == 0
    with TestClient(create_app(settings)) as c:
        assert all(c.get(f"/parts/{pid}").status_code == 200 for pid in ids)
        assert add_part(c, 7).json()["part_id"] == "added-4/0"


def test_uncommitted_file_is_quarantined_not_deleted_and_its_id_never_reissued(artifacts: Path,
                                                                               tmp_path: Path) -> None:
    data = tmp_path / "data"
    settings = writable_settings(artifacts, data)
    with TestClient(create_app(settings)) as c:
        first = add_part(c, 1).json()
    geometry = data / GEOMETRY_DIR
    # What a crash between writing the file and committing its row leaves (a later id).
    uncommitted = geometry / "00000007.npz.pending"
    shutil.copy(geometry / "00000001.npz", uncommitted)
    with TestClient(create_app(settings)) as c:
        assert (data / QUARANTINE_DIR / uncommitted.name).is_file() and not uncommitted.exists()
        assert c.get(f"/parts/{first['part_id']}").status_code == 200
        assert add_part(c, 2).json()["part_id"] == "added-8/0", "the quarantined file's id was reissued"
    code, out = _run_cli("verify", str(data))
    assert code == 0 and "in quarantine" in out, out


def _folder_with_three_parts(artifacts: Path, data: Path) -> Path:
    """A data folder holding three added parts, which ``verify`` finds sound."""
    with TestClient(create_app(writable_settings(artifacts, data))) as c:
        for s in range(3):
            add_part(c, s)
    assert verify(data).ok
    return data


def test_verify_reports_mismatches_naming_files(tmp_path: Path, artifacts: Path) -> None:
    data = _folder_with_three_parts(artifacts, tmp_path / "data")
    victim = data / GEOMETRY_DIR / "00000002.npz"
    victim.write_bytes(victim.read_bytes()[:-7])
    (data / GEOMETRY_DIR / "00000003.npz").unlink()
    report = verify(data)
    assert any(str(victim) in p and "checksum" in p for p in report.problems), report.problems
    assert any("00000003.npz: missing" in p for p in report.problems), report.problems
    code, out = _run_cli("verify", str(data))
    assert code == 1 and "2 problem(s)" in out


def test_verify_reports_an_index_that_lacks_a_live_part(tmp_path: Path, artifacts: Path) -> None:
    data = _folder_with_three_parts(artifacts, tmp_path / "data")
    found = read_index_file(data / INDEX_FILE)
    assert found is not None and len(found.row_ids) == 3
    # The same change number, one part fewer: what a damaged or swapped index file looks like.
    write_index_file(data / INDEX_FILE, found.seq, found.model_version, found.row_ids[:2].tolist(),
                     found.embeddings[:2], faiss.METRIC_L2)
    report = verify(data)
    assert any(str(data / INDEX_FILE) in p and "lacks 1 live part" in p for p in report.problems), report
    code, out = _run_cli("verify", str(data))
    assert code == 1 and "1 problem(s)" in out
    with TestClient(create_app(writable_settings(artifacts, data))) as c:  # a start rebuilds it
        assert c.get("/catalog").json()["index_rebuilt_at_start"] is True
    assert verify(data).ok


def test_malformed_database_is_an_error_naming_the_file(artifacts: Path, tmp_path: Path) -> None:
    data = tmp_path / "data"
    settings = writable_settings(artifacts, data)
    with TestClient(create_app(settings)) as c:
        for s in range(40):  # enough rows for the tables to span several pages
            add_part(c, s)
    db = data / "catalog.sqlite3"
    raw = bytearray(db.read_bytes())
    assert len(raw) > 8 * 4096, len(raw)
    raw[3 * 4096:6 * 4096] = b"\xff" * (3 * 4096)  # pages in the middle of the file, not the header
    db.write_bytes(bytes(raw))
    with pytest.raises(StoreError) as info, TestClient(create_app(settings)):
        pass
    assert str(db) in str(info.value) and "catalog verify" in str(info.value), info.value
    code, out = _run_cli("verify", str(data))
    assert code == 1 and str(db) in out, out


def test_an_add_past_its_deadline_stores_nothing(artifacts: Path, tmp_path: Path,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    """The request's deadline passes while the part is prepared: 504, and nothing is stored, also
    after the worker thread has finished."""
    data = tmp_path / "data"
    settings = writable_settings(artifacts, data, request_timeout=2.0, write_commit_margin=1.0)
    real = catalog_write.prepare_part
    finished = threading.Event()

    def slow_prepare(*args, **kwargs):  # a fault injected: preparing takes past the commit window
        time.sleep(1.5)
        try:
            return real(*args, **kwargs)
        finally:
            finished.set()

    with TestClient(create_app(settings)) as c:
        monkeypatch.setattr(catalog_write, "prepare_part", slow_prepare)
        r = add_part(c, 1)
        assert r.status_code == 504, r.text
        assert r.json()["error"]["code"] == "deadline_exceeded" and "nothing was stored" in r.text
        assert finished.wait(30)
        time.sleep(0.2)  # the thread's rollback follows prepare_part
        assert c.get("/catalog").json()["database_sequence"] == 0
        monkeypatch.setattr(catalog_write, "prepare_part", real)
        ok = add_part(c, 2)
        assert ok.status_code == 201 and c.get(f"/parts/{ok.json()['part_id']}").status_code == 200
    with sqlite3.connect(data / "catalog.sqlite3") as db:
        assert db.execute("SELECT COUNT(*) FROM parts").fetchone()[0] == 1
    assert [p.name for p in (data / GEOMETRY_DIR).iterdir()] == ["00000001.npz"]


def test_commit_window_decides_once() -> None:
    from service.api.routes.catalog_write import CommitWindow

    late = CommitWindow(time.monotonic() - 1)
    assert late.may_commit() is False and late.expire() is True
    on_time = CommitWindow(time.monotonic() + 60)
    assert on_time.may_commit() is True and on_time.expire() is False, "a started commit is waited for"
    given_up = CommitWindow(time.monotonic() + 60)
    assert given_up.expire() is True and given_up.may_commit() is False


def test_recover_reports_lost_changes_and_never_reissues_their_numbers(tmp_path: Path) -> None:
    """An index ahead of the database by changes no file records (lost deletes): refused; recover
    says how many are lost, and later changes are numbered past them."""
    import numpy as np
    from test_store import _new_part

    from service.catalog_store.snapshot import write_index_file
    from service.catalog_store.store import CatalogStore

    store = CatalogStore(tmp_path)
    for seed in range(3):
        store.add(_new_part(seed), None)
    write_index_file(store.index_path, 9, "m1", [1, 2], np.zeros((2, 8), np.float32), 1)
    with pytest.raises(CatalogDamagedError, match="reflects change 9, the database ends at change 3"):
        store.check_folder()
    store.close()
    code, out = _run_cli("recover", str(tmp_path))
    assert code == 1 and "6 change(s) (deletes or re-embeddings) cannot be rebuilt" in out, out
    store = CatalogStore(tmp_path)
    store.check_folder()
    assert store.add(_new_part(7), None).added_seq == 10
    store.close()


def test_serve_refuses_a_malformed_database_in_one_line(tmp_path: Path, artifacts: Path) -> None:
    """`complementme serve` names the damaged file and exits 1, without uvicorn's traceback."""
    import os
    import subprocess
    import sys

    from catalog_testkit import KEY

    data = tmp_path / "data"
    data.mkdir()
    (data / "catalog.sqlite3").write_bytes(b"not a database " * 2000)
    env = {**os.environ, "COMPLEMENTME_API_KEY": KEY, "COMPLEMENTME_DATA_DIR": str(data),
           "COMPLEMENTME_ARTIFACTS": str(artifacts)}
    done = subprocess.run([sys.executable, "-m", "training", "serve", "--port", "0"], env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 1
    assert str(data / "catalog.sqlite3") in done.stderr
    assert "Traceback" not in done.stderr + done.stdout
