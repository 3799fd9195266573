"""How to keep part meshes in PostgreSQL: a bytea column or large objects (issue 21).

Writes ``count`` meshes of each size into a scratch table both ways, one transaction per mesh as
an add does, then reads them all back, and prints the median milliseconds per mesh and the MB/s.
Run against a scratch database (it creates and drops its own table and large objects):

    python -m bench.pg_mesh_storage postgresql://USER:PASSWORD@127.0.0.1:5432/scratch
"""

from __future__ import annotations

import functools
import statistics
import sys
import time
from collections.abc import Callable

import numpy as np
import psycopg

from service.catalog_store.store import PartGeometry, encode_geometry

SIZES = (1_000, 20_000, 200_000)   # vertices (faces: about twice as many) of the meshes measured


def mesh_bytes(vertices: int, seed: int) -> bytes:
    """An npz mesh as the store keeps it (``encode_geometry``), of about ``vertices`` vertices."""
    rng = np.random.default_rng(seed)
    g = PartGeometry(rng.normal(size=(vertices, 3)).astype(np.float32),
                     rng.integers(0, vertices, size=(2 * vertices, 3)).astype(np.int32),
                     rng.normal(size=(1024, 3)).astype(np.float16))
    return encode_geometry(g)


def timed(fn: Callable[[], object]) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def _write(conn: psycopg.Connection, sql: str, blob: bytes) -> None:
    with conn.transaction():  # one transaction per mesh, as an add
        conn.execute(sql, (blob,))


def _read(conn: psycopg.Connection, sql: str, row: int) -> None:
    conn.execute(sql, (row,)).fetchone()


def measure(conn: psycopg.Connection, data: list[bytes]) -> dict[str, dict[str, float]]:
    conn.execute("DROP TABLE IF EXISTS bench_bytea, bench_external, bench_lo")
    conn.execute("CREATE TABLE bench_bytea (id serial PRIMARY KEY, data bytea NOT NULL)")
    # STORAGE EXTERNAL: out of line, never compressed (pglz gains nothing on float arrays).
    conn.execute("CREATE TABLE bench_external (id serial PRIMARY KEY, data bytea NOT NULL)")
    conn.execute("ALTER TABLE bench_external ALTER COLUMN data SET STORAGE EXTERNAL")
    conn.execute("CREATE TABLE bench_lo (id serial PRIMARY KEY, data oid NOT NULL)")
    conn.commit()
    out: dict[str, dict[str, float]] = {}
    for kind, insert, select in (
        ("bytea", "INSERT INTO bench_bytea (data) VALUES (%s)", "SELECT data FROM bench_bytea WHERE id = %s"),
        ("bytea external", "INSERT INTO bench_external (data) VALUES (%s)",
         "SELECT data FROM bench_external WHERE id = %s"),
        ("large object", "INSERT INTO bench_lo (data) VALUES (lo_from_bytea(0, %s))",
         "SELECT lo_get(data) FROM bench_lo WHERE id = %s"),
    ):
        writes = [timed(functools.partial(_write, conn, insert, blob)) for blob in data]
        reads = [timed(functools.partial(_read, conn, select, i + 1)) for i in range(len(data))]
        mb = sum(map(len, data)) / 1e6
        out[kind] = {"write_ms": statistics.median(writes) * 1000, "read_ms": statistics.median(reads) * 1000,
                     "write_mb_s": mb / sum(writes), "read_mb_s": mb / sum(reads)}
    conn.execute("SELECT lo_unlink(data) FROM bench_lo")
    conn.execute("DROP TABLE bench_bytea, bench_external, bench_lo")
    conn.commit()
    return out


def main(url: str, count: int = 10) -> None:
    with psycopg.connect(url) as conn:
        conn.autocommit = True
        for vertices in SIZES:
            data = [mesh_bytes(vertices, s) for s in range(count)]
            result = measure(conn, data)
            size = len(data[0]) / 1e6
            for kind, r in result.items():
                print(f"{vertices:>7} vertices ({size:6.2f} MB) {kind:>14}: write {r['write_ms']:7.1f} ms "
                      f"({r['write_mb_s']:6.0f} MB/s), read {r['read_ms']:7.1f} ms "
                      f"({r['read_mb_s']:6.0f} MB/s)")


if __name__ == "__main__":
    main(sys.argv[1])
