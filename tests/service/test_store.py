"""Catalog additions: the SQLite store, the snapshot swap, and POST/DELETE /parts end to end."""

from __future__ import annotations

import io
import sqlite3
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh
from catalog_testkit import AUTH, add_part, part_mesh, writable_settings
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.catalog_store.store import (
    INDEX_FILE,
    CatalogStore,
    NewPart,
    PartGeometry,
    StoreError,
    decode_geometry,
)
from service.geometry.mesh import sample_surface
from service.settings import Settings


def _new_part(seed: int, category: str = "widget") -> NewPart:
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(6, 3)).astype(np.float32)
    f = np.array([[0, 1, 2], [3, 4, 5]], np.int32)
    return NewPart(category=category, name=f"n{seed}", style=None, label="leg", translation=np.zeros(3),
                   bbox_min=v.min(0), bbox_max=v.max(0), area=1.0,
                   embedding=rng.normal(size=8).astype(np.float32),
                   part_feature=rng.normal(size=4).astype(np.float32), model_version="m1",
                   geometry=PartGeometry(v, f, rng.normal(size=(16, 3)).astype(np.float16)))


def _boot(settings: Settings) -> TestClient:
    return TestClient(create_app(settings))


def _state(c: TestClient) -> Any:
    return c.app.state  # type: ignore[attr-defined]


@pytest.fixture()
def data_dir(tmp_path: Path) -> Path:
    return tmp_path / "data"


@pytest.fixture()
def writable(artifacts: Path, data_dir: Path) -> Iterator[TestClient]:
    with _boot(writable_settings(artifacts, data_dir)) as c:
        yield c


# ------------------------------------------------------------------------------ the store alone


def test_store_keeps_rows_files_and_a_change_log(tmp_path: Path) -> None:
    store = CatalogStore(tmp_path)
    a = store.add(_new_part(1), None)
    b = store.add(_new_part(2), "lamp-x")
    c = store.add(_new_part(3), "lamp-x")
    assert (a.part_id, b.part_id, c.part_id) == ("added-1/0", "lamp-x/0", "lamp-x/1")
    assert store.delete("lamp-x/0") == 4 and store.delete("lamp-x/0") is None
    d = store.add(_new_part(4), "lamp-x")
    assert d.part_id == "lamp-x/2", "ids are never reused, even after a delete"
    assert [ch.kind for ch in store.changes_since(0)] == ["add", "add", "add", "delete", "add"]
    assert [p.part_id for p in store.parts()] == ["added-1/0", "lamp-x/1", "lamp-x/2"]
    assert store.counts() == (3, 1) and store.last_seq() == 5
    g = store.read_geometry(c)
    np.testing.assert_array_equal(g.vertices, _new_part(3).geometry.vertices)
    np.testing.assert_array_equal(store.parts([c.id])[0].embedding, _new_part(3).embedding)
    assert store.integrity() == "ok"
    with sqlite3.connect(tmp_path / "catalog.sqlite3") as db:
        assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    store.close()


def test_damaged_geometry_is_detected_and_uncommitted_files_quarantined(tmp_path: Path) -> None:
    store = CatalogStore(tmp_path)
    p = store.add(_new_part(1), None)
    assert sorted(x.name for x in store.geometry_dir.iterdir()) == [p.geometry], "no pending name left"
    orphan = store.geometry_dir / "00000099.npz.pending"
    orphan.write_bytes(b"left by a crash before the commit")
    assert store.check_folder() == 1 and not orphan.exists()
    assert (tmp_path / "quarantine" / orphan.name).read_bytes() == b"left by a crash before the commit"
    assert store.add(_new_part(2), None).id == 100, "the quarantined file's id is not issued again"
    path = store.geometry_dir / p.geometry
    path.write_bytes(path.read_bytes()[:-10])
    with pytest.raises(StoreError, match="does not match its checksum"):
        store.read_geometry(p)
    with pytest.raises(StoreError, match="not a readable geometry file"):
        decode_geometry(b"garbage", "x.npz")
    store.close()


def test_backup_is_a_working_copy(tmp_path: Path) -> None:
    store = CatalogStore(tmp_path / "live")
    parts = [store.add(_new_part(i), None) for i in range(3)]
    assert store.backup(tmp_path / "copy") == 4
    copy = CatalogStore(tmp_path / "copy")
    assert [p.part_id for p in copy.parts()] == [p.part_id for p in parts]
    assert all(copy.read_geometry(p) is not None for p in copy.parts())
    with pytest.raises(StoreError, match="not empty"):
        store.backup(tmp_path / "copy")
    store.close()
    copy.close()


# ------------------------------------------------------------------------------ through the API


def test_added_part_is_searchable_at_once_and_persists(artifacts: Path, data_dir: Path) -> None:
    settings = writable_settings(artifacts, data_dir)
    with _boot(settings) as c:
        before = _state(c).served.snapshot
        r = add_part(c, 1, category="widget", label="plank", name="a block", style="plain")
        assert r.status_code == 201, r.text
        part = r.json()
        assert r.headers["location"] == f"/parts/{part['part_id']}"
        assert part["origin"] == "added" and part["split"] == "added" and part["label"] == "plank"
        got = c.get(f"/parts/{part['part_id']}").json()
        assert got == part
        # The snapshot in use before the write is untouched; the next request sees the part.
        assert len(before.catalog) == len(_state(c).served.snapshot.catalog) - 1
        mesh = trimesh.load_mesh(io.BytesIO(part_mesh(1)), file_type="ply")
        query = {"points": sample_surface(mesh.vertices, mesh.faces, 200, 0).tolist(), "category": "widget",
                 "k": 5}
        answer = c.post("/suggest", json=query).json()
        assert [s["part_id"] for s in answer["suggestions"]] == [part["part_id"]]
        assert {"name": "widget", "parts": 1} in c.get("/categories").json()
        # The page's part search finds it by its name, never by its label.
        found = c.get("/parts", params={"q": "A BLOCK"}).json()
        assert [p["part_id"] for p in found["items"]] == [part["part_id"]]
        assert c.get("/parts", params={"q": "plank"}).json()["total"] == 0
        obj = c.get(f"/parts/{part['part_id']}/mesh?format=obj")
        assert obj.status_code == 200 and obj.text.count("\nf ") == 12
        status = c.get("/catalog").json()
        assert status["added_parts"] == 1 and status["sequence"] == status["index_sequence"] == 1
    with _boot(settings) as c:  # a restart on the same folder
        assert c.get(f"/parts/{part['part_id']}").json() == part
        assert c.post("/suggest", json=query).json()["suggestions"][0]["part_id"] == part["part_id"]
        status = c.get("/catalog").json()
        assert status["index_rebuilt_at_start"] is False and status["added_parts"] == 1


def test_delete_removes_an_added_part_at_once(writable: TestClient, catalog) -> None:
    ids = [add_part(writable, s, category="gadget").json()["part_id"] for s in (1, 2)]
    query = {"points": np.random.default_rng(0).normal(size=(64, 3)).tolist(), "category": "gadget", "k": 5}
    assert {s["part_id"] for s in writable.post("/suggest", json=query).json()["suggestions"]} == set(ids)
    assert writable.delete(f"/parts/{ids[0]}", headers=AUTH).status_code == 204
    assert writable.get(f"/parts/{ids[0]}").status_code == 404
    assert [s["part_id"] for s in writable.post("/suggest", json=query).json()["suggestions"]] == [ids[1]]
    again = writable.delete(f"/parts/{ids[0]}", headers=AUTH)
    assert again.status_code == 404 and again.json()["error"]["code"] == "unknown_part"
    shipped = writable.delete(f"/parts/{catalog.part_ids[0]}", headers=AUTH)
    assert shipped.status_code == 409 and shipped.json()["error"]["code"] == "shipped_part"
    assert writable.get("/catalog").json()["deleted_parts"] == 1


def test_upload_refusals(writable: TestClient, catalog, settings: Settings) -> None:
    def post(files: dict | None = None, **data: str):
        files = files or {"file": ("p.ply", part_mesh(0))}
        return writable.post("/parts", files=files, data=data, headers=AUTH)

    cases = [
        (writable.post("/parts", data={"category": "x"}, headers=AUTH), 422, "missing_file"),
        (post(category="bad/category"), 422, "invalid_category"),
        (post(category="ok", shape_id="added-7"), 422, "invalid_shape_id"),
        (post(category="ok", colour="red"), 422, "validation_error"),
        (post(category="ok", shape_id=catalog.shape_ids[0]), 409, "shipped_shape"),
        (post({"file": ("p.xyz", b"1 2 3")}, category="ok"), 415, "unsupported_format"),
        (post({"file": ("p.ply", b"ply\nformat ascii 1.0\nend_header\n")}, category="ok"), 422, "empty_mesh"),
        (post(category="ok", frame='{"radius": 0.01}'), 422, "part_too_large"),
        (post(category="ok", frame='{"radius": -1}'), 422, "validation_error"),
    ]
    for response, status, code in cases:
        assert response.status_code == status, response.text
        assert response.json()["error"]["code"] == code, response.text
    big = writable.post("/parts", files={"file": ("p.ply", b"x" * (settings.max_upload_bytes + 10))},
                        data={"category": "ok"}, headers=AUTH)
    assert big.status_code == 413
    assert writable.get("/catalog").json()["added_parts"] == 0


def test_frame_maps_an_upload_into_the_canonical_frame(writable: TestClient) -> None:
    canonical = trimesh.creation.box(extents=(0.1, 0.2, 0.3))
    canonical.apply_translation((0.2, 0.3, -0.1))
    # The same part in millimetres, z up, with the complete object centred at (100, 200, 300).
    mm = canonical.copy()
    mm.apply_transform(np.array([[1, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]], float))
    mm.apply_scale(500.0)
    mm.apply_translation((100.0, 200.0, 300.0))
    frame = '{"center": [100, 200, 300], "radius": 500, "up_axis": "z"}'
    a = writable.post("/parts", files={"file": ("a.stl", canonical.export(file_type="stl"))},
                      data={"category": "frames"}, headers=AUTH).json()
    b = writable.post("/parts", files={"file": ("b.stl", mm.export(file_type="stl"))},
                      data={"category": "frames", "frame": frame}, headers=AUTH).json()
    np.testing.assert_allclose(a["translation"], [0.2, 0.3, -0.1], atol=1e-6)
    np.testing.assert_allclose(b["translation"], a["translation"], atol=1e-5)
    np.testing.assert_allclose(b["bbox_max"], a["bbox_max"], atol=1e-5)


def test_damaged_or_stale_data_is_repaired_at_start(artifacts: Path, data_dir: Path) -> None:
    settings = writable_settings(artifacts, data_dir)
    with _boot(settings) as c:
        ids = [add_part(c, s).json()["part_id"] for s in range(3)]
        embedding = _state(c).served.snapshot.catalog.embeddings[-1].copy()
    (data_dir / INDEX_FILE).write_bytes(b"half an index")
    with sqlite3.connect(data_dir / "catalog.sqlite3") as db:  # as if made by another model version
        db.execute("UPDATE parts SET model_version = 'older-model'")
    victim = sorted((data_dir / "geometry").iterdir())[0]
    victim.write_bytes(victim.read_bytes()[:100])
    with _boot(settings) as c:
        status = c.get("/catalog").json()
        assert status["index_rebuilt_at_start"] is True and status["reembedded_at_start"] == 2
        assert [x["part_id"] for x in status["left_out"]] == [ids[0]]
        assert status["added_parts"] == 2 and status["index_sequence"] == status["sequence"]
        assert c.get(f"/parts/{ids[0]}").status_code == 404
        assert c.get(f"/parts/{ids[2]}").status_code == 200
        # The same model on the same geometry: the same embedding, up to float rounding.
        np.testing.assert_allclose(_state(c).served.snapshot.catalog.embeddings[-1], embedding,
                                   rtol=1e-4, atol=1e-6)


def test_other_processes_additions_are_picked_up(artifacts: Path, data_dir: Path) -> None:
    """Two apps on one folder stand for two workers: one's additions reach the other on sync."""
    settings = writable_settings(artifacts, data_dir)
    with _boot(settings) as a, _boot(settings) as b:
        pid = add_part(a, 5, category="shared").json()["part_id"]
        assert b.get(f"/parts/{pid}").status_code == 404
        assert _state(b).served.writer.sync() is True  # what the polling thread calls
        assert b.get(f"/parts/{pid}").status_code == 200
        assert b.delete(f"/parts/{pid}", headers=AUTH).status_code == 204
        _state(a).served.writer.sync()
        assert a.get(f"/parts/{pid}").status_code == 404
        assert a.get("/catalog").json()["sequence"] == b.get("/catalog").json()["sequence"] == 2


def test_snapshots_extend_to_what_a_full_build_gives(catalog) -> None:
    """Appended snapshots are built incrementally; they must equal a Catalog built in full."""
    from service.artifacts.catalog import Catalog
    from service.catalog_store.snapshot import AddedPart, CatalogBuilder, _extension_ok

    builder = CatalogBuilder(catalog)
    rng = np.random.default_rng(0)
    S, D, Fp = catalog.n_points, catalog.embeddings.shape[1], catalog.part_features.shape[1]
    first = builder.catalog()
    assert _extension_ok(first), "the incremental path is the one under test"
    for round_, cats in enumerate((["zzz-new"], ["aaa-first", catalog.categories[0]], ["zzz-new"])):
        parts = []
        for j, cat in enumerate(cats):
            faces = np.array([[0, 1, 2], [1, 2, 3]], np.int32)
            g = PartGeometry(rng.normal(size=(4, 3)).astype(np.float32), faces,
                             rng.normal(size=(S, 3)).astype(np.float16))
            rec = {"part_id": f"r{round_}-{j}/0", "shape_id": f"{'0' if j else 'z'}-shape-{round_}-{j}",
                   "category": cat, "style": None, "label": None, "translation": [0.1, 0.2, 0.3],
                   "bbox_min": [-1, -1, -1], "bbox_max": [1, 1, 1], "area": 1.0, "split": "added",
                   "duplicate_of": None}
            parts.append(AddedPart(round_ * 10 + j, rec, rng.normal(size=D).astype(np.float32),
                                   rng.normal(size=Fp).astype(np.float32), g))
        builder.append(parts)
        fast = builder.catalog()
        full = Catalog(records=list(fast.records), embeddings=fast.embeddings,
                       part_features=fast.part_features, points=fast.points, mesh_vertices=fast.mesh_vertices,
                       mesh_faces=fast.mesh_faces, vertex_first=fast.vertex_first, face_first=fast.face_first)
        assert set(vars(fast)) == set(vars(full))
        for name, value in vars(full).items():
            got = getattr(fast, name)
            if isinstance(value, np.ndarray):
                np.testing.assert_array_equal(got, value, err_msg=name)
                assert got.dtype == value.dtype, name
            else:
                assert got == value, name
        np.testing.assert_array_equal(fast.mesh(len(fast) - 1)[1], parts[-1].geometry.faces)
    assert len(first) == len(catalog), "earlier snapshots are untouched by later appends"
