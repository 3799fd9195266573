"""Concurrent writers and readers on a live server: every add is kept, no request fails.

Eight clients add 50 parts each while eight others query; all 400 parts must be present and
searchable afterwards. Query latency under this load is printed (not asserted: timing depends
on the machine).
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import httpx
import numpy as np
from catalog_testkit import AUTH, LiveServer, part_mesh
from service_testkit import AssemblyQuery, stop_and_join

from service.geometry.inputs import points_to_base64

WRITERS, ADDS_EACH, READERS = 8, 50, 8


def test_many_writers_and_readers(artifacts: Path, tmp_path: Path, query: AssemblyQuery) -> None:
    server = LiveServer(artifacts, tmp_path / "data", max_inflight=4, max_queue=64).start()
    errors: list[str] = []
    added: list[str] = []
    add_seconds: list[float] = []
    query_seconds: list[float] = []
    lock = threading.Lock()
    writers_done = threading.Event()
    body = {"points_base64": points_to_base64(query.points), "k": 10}

    def write(w: int) -> None:
        with httpx.Client(base_url=server.url, timeout=120) as http:
            for i in range(ADDS_EACH):
                seed = 1000 * w + i
                t = time.perf_counter()
                r = http.post("/parts", files={"file": (f"p{seed}.ply", part_mesh(seed))},
                              data={"category": "concurrent", "shape_id": f"writer-{w}"}, headers=AUTH)
                with lock:
                    add_seconds.append(time.perf_counter() - t)
                    if r.status_code == 201:
                        added.append(r.json()["part_id"])
                    else:
                        errors.append(f"add {seed}: {r.status_code} {r.text}")

    def read() -> None:
        with httpx.Client(base_url=server.url, timeout=120) as http:
            while not writers_done.is_set():
                t = time.perf_counter()
                r = http.post("/suggest", json=body)
                with lock:
                    query_seconds.append(time.perf_counter() - t)
                    if r.status_code != 200:
                        errors.append(f"query: {r.status_code} {r.text}")

    try:
        writers = [threading.Thread(target=write, args=(w,)) for w in range(WRITERS)]
        readers = [threading.Thread(target=read) for _ in range(READERS)]
        t0 = time.perf_counter()
        for t in writers + readers:
            t.start()
        for t in writers:
            t.join(timeout=600)
        stop_and_join(writers_done, readers, 120)
        wall = time.perf_counter() - t0
        assert not errors, errors[:5]
        assert len(added) == len(set(added)) == WRITERS * ADDS_EACH
        with httpx.Client(base_url=server.url, timeout=60) as http:
            listed = []
            for offset in range(0, len(added), 100):
                page = http.get("/parts", params={"category": "concurrent", "offset": offset, "limit": 100})
                listed += [p["part_id"] for p in page.json()["items"]]
            assert sorted(listed) == sorted(added)
            # Each writer's parts form one shape, numbered in the order they were added.
            writer3 = {p for p in added if p.startswith("writer-3/")}
            assert writer3 == {f"writer-3/{i}" for i in range(ADDS_EACH)}
            answer = http.post("/suggest", json={**body, "category": "concurrent", "k": 20}).json()
            assert len(answer["suggestions"]) == 20
            assert all(s["part_id"] in set(added) for s in answer["suggestions"])
            status = http.get("/catalog").json()
            assert status["added_parts"] == len(added) and status["index_sequence"] == status["sequence"]
    finally:
        server.stop()
    q = np.array(query_seconds) * 1000
    a = np.array(add_seconds) * 1000
    print(f"\nconcurrency: {len(added)} adds and {len(q)} queries in {wall:.1f} s; query latency ms "
          f"p50 {np.percentile(q, 50):.1f} p95 {np.percentile(q, 95):.1f} max {q.max():.1f}; add latency ms "
          f"p50 {np.percentile(a, 50):.1f} p95 {np.percentile(a, 95):.1f} max {a.max():.1f}")
