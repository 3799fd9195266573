"""Crash safety: SIGKILL the server while clients add parts; every acknowledged part survives.

One data folder, three rounds. Each round starts the service (uvicorn, its own process), lets
several clients add parts concurrently, kills the process with SIGKILL once a given number of
adds were acknowledged (others are in flight, at every stage of their write), starts it again
and checks the folder: every acknowledged part is served (by id, by its mesh, and by a
suggestion query filtered to its round's category, a category only additions have); nothing
half-written is served (every served part's geometry file is whole, no orphan file is left,
SQLite's integrity check passes); the index file and the database agree.
"""

from __future__ import annotations

import hashlib
import sqlite3
import threading
import time
from pathlib import Path

import httpx
import numpy as np
from catalog_testkit import AUTH, LiveServer, part_mesh

from service.geometry.inputs import points_to_base64

WRITERS = 6
KILL_AFTER = (3, 12, 25)  # acknowledged adds of the round before the SIGKILL


def _writer(url: str, category: str, first_seed: int, stop: threading.Event,
            acks: dict[str, str], lock: threading.Lock) -> None:
    seed = first_seed
    with httpx.Client(base_url=url, timeout=60) as http:
        while not stop.is_set():
            try:
                r = http.post("/parts", files={"file": (f"p{seed}.ply", part_mesh(seed))},
                              data={"category": category}, headers=AUTH)
            except httpx.HTTPError:
                return  # the server died with this add in flight: it was never acknowledged
            if r.status_code == 201:
                with lock:
                    acks[r.json()["part_id"]] = category
            else:
                assert r.status_code == 503, r.text  # overload is the only acceptable refusal
            seed += 1


def _check(url: str, data: Path, acks: dict[str, str], categories: list[str]) -> dict[str, int]:
    """Everything the module doc promises about a restarted server and its folder."""
    with httpx.Client(base_url=url, timeout=60) as http:
        status = http.get("/catalog").json()
        assert status["left_out"] == [], status
        assert status["sequence"] == status["database_sequence"] == status["index_sequence"], status
        for pid, category in acks.items():
            part = http.get(f"/parts/{pid}")
            assert part.status_code == 200, f"acknowledged part {pid} is lost"
            assert part.json()["category"] == category
            assert http.get(f"/parts/{pid}/mesh").status_code == 200
        db = sqlite3.connect(f"file:{data / 'catalog.sqlite3'}?mode=ro", uri=True)
        try:
            assert db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
            rows = db.execute("SELECT part_id, category, geometry, geometry_sha256 FROM parts "
                              "WHERE deleted_seq IS NULL").fetchall()
            last = db.execute("SELECT MAX(seq) FROM changes").fetchone()[0]
        finally:
            db.close()
        assert last == status["database_sequence"]
        assert status["added_parts"] == len(rows), "served additions differ from the database's"
        files = {p.name for p in (data / "geometry").iterdir()}
        assert files == {r[2] for r in rows}, "orphan or missing geometry files"
        for _, _, name, digest in rows:
            assert hashlib.sha256((data / "geometry" / name).read_bytes()).hexdigest() == digest
        index = np.load(data / "added-index.npz")
        assert len(index["row_ids"]) == len(rows)
        query = points_to_base64(np.random.default_rng(0).uniform(-0.5, 0.5, (256, 3)).astype(np.float32))
        for category in categories:
            expected = {r[0] for r in rows if r[1] == category}
            assert {p for p, c in acks.items() if c == category} <= expected
            answer = http.post("/suggest", json={"points_base64": query, "category": category, "k": 100})
            assert answer.status_code == 200, answer.text
            assert {s["part_id"] for s in answer.json()["suggestions"]} == expected
    return {"served": len(rows), "unacknowledged_but_kept": len(rows) - len(acks)}


def test_acknowledged_parts_survive_sigkill(artifacts: Path, tmp_path: Path) -> None:
    data = tmp_path / "data"
    acks: dict[str, str] = {}
    lock = threading.Lock()
    server = LiveServer(artifacts, data, max_queue=64).start()
    categories: list[str] = []
    try:
        for round_, kill_after in enumerate(KILL_AFTER):
            category = f"crash-{round_}"
            categories.append(category)
            before = sum(c == category for c in acks.values())
            stop = threading.Event()
            seeds = [100_000 * round_ + 1000 * w for w in range(WRITERS)]
            threads = [threading.Thread(target=_writer, args=(server.url, category, seed, stop, acks, lock))
                       for seed in seeds]
            t0 = time.monotonic()
            for t in threads:
                t.start()
            while sum(c == category for c in acks.values()) - before < kill_after:
                assert time.monotonic() - t0 < 60, "adds did not get acknowledged"
                time.sleep(0.002)
            server.kill()
            killed_at = sum(c == category for c in acks.values())
            stop.set()
            for t in threads:
                t.join(timeout=60)
            server = LiveServer(artifacts, data, max_queue=64).start()
            result = _check(server.url, data, acks, categories)
            print(f"crash round {round_}: killed after {killed_at} acks in the round; served after restart "
                  f"{result['served']}, committed-but-unacknowledged {result['unacknowledged_but_kept']}")
    finally:
        server.stop()
