"""The postgres catalog backend in one process: schema migrations, the order of changes,
idempotent adds, two replicas (two apps) on one database, and the SQLite default's refusal of
idempotency keys. A real PostgreSQL server (``pg_testkit``); the multi-process acceptance tests
are in ``test_pg_replicas.py``.
"""

from __future__ import annotations

import dataclasses
import threading
from pathlib import Path
from typing import Any

import numpy as np
import psycopg
import pytest
from catalog_testkit import AUTH, add_part, part_mesh, writable_settings
from fastapi.testclient import TestClient
from pg_testkit import PG_PASSWORD, PG_USER, PostgresCluster, wait_until

from service.api.app import create_app
from service.catalog_store.pg_store import SCHEMA_VERSION, PgCatalogStore
from service.catalog_store.store import NewPart, PartGeometry, StoreError
from service.geometry.inputs import points_to_base64
from service.settings import Settings


def pg_settings(artifacts: Path, url: str, **overrides: Any) -> Settings:
    return writable_settings(artifacts, None, catalog_backend="postgres", database_url=url,
                             database_migrate=True, catalog_poll_seconds=1, **overrides)


def new_part(seed: int, category: str = "widget") -> NewPart:
    rng = np.random.default_rng(seed)
    geometry = PartGeometry(rng.normal(size=(8, 3)).astype(np.float32),
                            rng.integers(0, 8, size=(6, 3)).astype(np.int32),
                            rng.normal(size=(16, 3)).astype(np.float16))
    return NewPart(category=category, name=None, style=None, label=None, translation=np.zeros(3),
                   bbox_min=-np.ones(3), bbox_max=np.ones(3), area=1.0,
                   embedding=rng.normal(size=8).astype(np.float32),
                   part_feature=rng.normal(size=4).astype(np.float32), model_version="m1", geometry=geometry)


def test_schema_is_applied_by_migrate_once(database_url: str) -> None:
    with pytest.raises(StoreError, match="complementme catalog migrate"):
        PgCatalogStore(database_url)
    stores: list[PgCatalogStore] = []
    errors: list[BaseException] = []

    def open_one() -> None:
        try:
            stores.append(PgCatalogStore(database_url, migrate_schema=True))
        except BaseException as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=open_one) for _ in range(3)]  # replicas starting together
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors
    for s in stores:
        s.close()
    with psycopg.connect(database_url) as conn:
        versions = conn.execute("SELECT version FROM schema_migrations").fetchall()
    assert versions == [(SCHEMA_VERSION,)]
    PgCatalogStore(database_url).close()  # migrated: no setting needed any more
    with psycopg.connect(database_url) as conn:
        conn.execute("INSERT INTO schema_migrations (version, description) VALUES (%s, 'future')",
                     (SCHEMA_VERSION + 1,))
    with pytest.raises(StoreError, match="newer version"):
        PgCatalogStore(database_url, migrate_schema=True)


def test_changes_commit_in_the_order_of_their_numbers(database_url: str) -> None:
    """Concurrent writers; a follower reading `seq > last` never finds a gap it would skip."""
    store = PgCatalogStore(database_url, "m1", migrate_schema=True, pool_size=8)
    stop = threading.Event()
    seen: list[int] = []
    problems: list[str] = []

    def follow() -> None:
        last = 0
        while not stop.is_set() or last < store.last_seq():
            for change in store.changes_since(last):
                if change.seq != last + 1:
                    problems.append(f"after change {last} came {change.seq}")
                last = change.seq
                seen.append(change.seq)

    def write(first: int) -> None:
        for i in range(15):
            stored = store.add(new_part(first + i), shape_id=f"s{(first // 1000) % 2}")
            if i % 5 == 4:
                store.delete(stored.part_id)

    follower = threading.Thread(target=follow)
    follower.start()
    writers = [threading.Thread(target=write, args=(1000 * w,)) for w in range(6)]
    for t in writers:
        t.start()
    for t in writers:
        t.join()
    stop.set()
    follower.join()
    try:
        assert not problems, problems
        assert seen == list(range(1, 6 * 18 + 1))
        parts = store.parts(alive_only=False)
        assert len({p.part_id for p in parts}) == len(parts) == 90
        assert store.counts() == (72, 18)
        assert sorted(int(p.part_id.split("/")[1]) for p in parts if p.shape_id == "s0") == list(range(45))
        # Each stored mesh is its own part's (found by its embedding: which writer got which id
        # is up to the scheduler).
        seeds = [1000 * w + i for w in range(6) for i in range(15)]
        seed_of = {new_part(s).embedding.tobytes(): s for s in seeds}
        for p in parts[:12]:
            got = store.read_geometry(p)
            made = new_part(seed_of[np.asarray(p.embedding, np.float32).tobytes()])
            assert np.array_equal(got.vertices, made.geometry.vertices), p.part_id
    finally:
        store.close()


def _suggested(client: TestClient, seed: int, category: str) -> list[str]:
    mesh = part_mesh(seed)
    import trimesh

    loaded = trimesh.load(trimesh.util.wrap_as_stream(mesh), file_type="ply")
    points = np.asarray(trimesh.sample.sample_surface(loaded, 256, seed=seed)[0], dtype=np.float32)
    r = client.post("/suggest", json={"points_base64": points_to_base64(points), "category": category,
                                      "k": 5})
    assert r.status_code == 200, r.text
    return [s["part_id"] for s in r.json()["suggestions"]]


def test_two_replicas_in_one_process_follow_each_other(artifacts: Path, database_url: str) -> None:
    settings = pg_settings(artifacts, database_url)
    with TestClient(create_app(settings)) as a, TestClient(create_app(settings)) as b:
        r = add_part(a, 1, category="pg-one")
        assert r.status_code == 201, r.text
        pid = r.json()["part_id"]
        assert a.get(f"/parts/{pid}").status_code == 200  # at once on the replica that added it
        wait_until(lambda: b.get(f"/parts/{pid}").status_code == 200, f"replica b serves {pid}")
        assert _suggested(b, 1, "pg-one") == [pid]
        assert b.delete(f"/parts/{pid}", headers=AUTH).status_code == 204
        wait_until(lambda: a.get(f"/parts/{pid}").status_code == 404, f"replica a drops {pid}")
        for client in (a, b):
            status = client.get("/catalog").json()
            assert status["backend"] == "postgres"
            assert status["sequence"] == status["database_sequence"] == 2, status
            assert status["added_parts"] == 0 and status["deleted_parts"] == 1
            ready = client.get("/readyz").json()
            assert ready["status"] == "ready"
            assert ready["catalog"]["database"] == "up"
            wait_until(lambda c=client: c.get("/readyz").json()["catalog"]["lag_changes"] == 0, "no lag")
            metrics = client.get("/metrics").text
            assert "complementme_catalog_applied_change 2.0" in metrics
            assert "complementme_catalog_database_up 1.0" in metrics
        # A replica of another model (a rolling update) adds a part: these replicas embed it from
        # its mesh with their own model and serve it, instead of leaving it out.
        other = PgCatalogStore(database_url, "another-model")
        try:
            made = dataclasses.replace(new_part(3, "foreign"), model_version="another-model")
            foreign = other.add(made, None)
        finally:
            other.close()
        for client in (a, b):
            wait_until(lambda c=client: c.get(f"/parts/{foreign.part_id}").status_code == 200, "foreign part")
            status = client.get("/catalog").json()
            assert status["left_out"] == [] and status["added_parts"] == 1, status


def test_an_idempotency_key_makes_a_retried_add_safe(artifacts: Path, database_url: str) -> None:
    settings = pg_settings(artifacts, database_url)
    with TestClient(create_app(settings)) as a, TestClient(create_app(settings)) as b:
        key = {"Idempotency-Key": "3f1c2a9e-first-add"}
        first = a.post("/parts", files={"file": ("p.ply", part_mesh(5))}, data={"category": "keyed"},
                       headers={**AUTH, **key})
        assert first.status_code == 201, first.text
        assert "Idempotent-Replayed" not in first.headers
        for client in (a, b):  # the retry may reach any replica
            again = client.post("/parts", files={"file": ("p.ply", part_mesh(5))},
                                data={"category": "keyed"}, headers={**AUTH, **key})
            assert again.status_code == 201, again.text
            assert again.headers["Idempotent-Replayed"] == "true"
            assert again.json() == first.json()
            assert client.get(f"/parts/{first.json()['part_id']}").status_code == 200
        other = a.post("/parts", files={"file": ("p.ply", part_mesh(6))}, data={"category": "keyed"},
                       headers={**AUTH, **key})
        assert other.status_code == 422
        assert other.json()["error"]["code"] == "idempotency_key_reused"
        bad = a.post("/parts", files={"file": ("p.ply", part_mesh(6))}, data={"category": "keyed"},
                     headers={**AUTH, "Idempotency-Key": "has spaces"})
        assert bad.status_code == 422
        assert bad.json()["error"]["code"] == "invalid_idempotency_key"
        assert a.get("/catalog").json()["added_parts"] == 1


def test_an_outage_is_reported_writes_refused_at_once_and_recovered(artifacts: Path,
                                                                  own_postgres: PostgresCluster) -> None:
    # Once the replica knows the database is away, /readyz says degraded and a write is refused
    # at once ("known to be unreachable") rather than after the pool's whole timeout; when the
    # database is back the replica says so and takes writes again, without a restart.
    settings = pg_settings(artifacts, own_postgres.new_database())
    with TestClient(create_app(settings)) as client:
        wait_until(lambda: client.get("/readyz").json()["status"] == "ready", "ready")
        assert add_part(client, 1, category="before").status_code == 201
        own_postgres.stop()
        wait_until(lambda: client.get("/readyz").json()["status"] == "degraded", "degraded")
        ready = client.get("/readyz")
        assert ready.status_code == 200  # still serving from the last snapshot
        assert ready.json()["catalog"]["database"] == "unreachable"
        assert ready.json()["catalog"]["last_error"]
        assert "complementme_catalog_database_up 0.0" in client.get("/metrics").text
        refused = add_part(client, 2, category="during")
        assert refused.status_code == 503, refused.text
        assert refused.json()["error"]["code"] == "database_unavailable"
        assert "known to be unreachable" in refused.json()["error"]["message"]
        assert int(refused.headers["Retry-After"]) >= 1
        assert client.get("/catalog").json()["added_parts"] == 1  # reads go on
        own_postgres.start()
        wait_until(lambda: client.get("/readyz").json()["status"] == "ready", "ready again", timeout=60)
        assert add_part(client, 3, category="after").status_code == 201
        assert client.get("/catalog").json()["added_parts"] == 2


def test_sqlite_backend_refuses_idempotency_keys(artifacts: Path, tmp_path: Path) -> None:
    with TestClient(create_app(writable_settings(artifacts, tmp_path / "data"))) as client:
        r = client.post("/parts", files={"file": ("p.ply", part_mesh(1))}, data={"category": "x"},
                        headers={**AUTH, "Idempotency-Key": "k-1"})
        assert r.status_code == 422
        assert r.json()["error"]["code"] == "idempotency_unsupported"
        assert client.get("/catalog").json()["added_parts"] == 0
        ready = client.get("/readyz").json()
        assert ready["status"] == "ready" and "catalog" not in ready  # nothing to follow


def test_migrate_command_applies_the_schema_once(database_url: str) -> None:
    from typer.testing import CliRunner

    from training.cli import app

    runner = CliRunner()
    first = runner.invoke(app, ["catalog", "migrate", "--database-url", database_url])
    assert first.exit_code == 0, first.output
    assert f"schema version {SCHEMA_VERSION} (applied migration(s) 1)" in first.output
    again = runner.invoke(app, ["catalog", "migrate"], env={"COMPLEMENTME_DATABASE_URL": database_url})
    assert again.exit_code == 0 and "nothing to apply" in again.output, again.output
    PgCatalogStore(database_url).close()  # the server starts on it without migrating
    unreachable = f"postgresql://{PG_USER}:{PG_PASSWORD}@127.0.0.1:9/x"  # nothing listens on port 9
    failed = runner.invoke(app, ["catalog", "migrate", "--database-url", unreachable, "--timeout", "2"])
    assert failed.exit_code == 2 and "error: postgresql://complementme@127.0.0.1:9/x" in failed.output
    assert PG_PASSWORD not in first.output + again.output + failed.output
