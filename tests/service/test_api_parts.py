"""Catalog reads: ``GET /parts``, ``/parts/{id}``, ``/parts/{id}/mesh``, ``/parts/{id}/points``."""

from __future__ import annotations

import io
from urllib.parse import quote

import numpy as np
import pytest
import trimesh
from fastapi.testclient import TestClient

from service.api.schemas import CategoryOut, PartOut, PartPointsOut, PartsPage
from service.artifacts.catalog import Catalog
from service.geometry.inputs import points_from_base64


def test_pages_cover_the_catalog_once(client: TestClient, catalog: Catalog) -> None:
    seen: list[str] = []
    offset = 0
    while True:
        page = PartsPage.model_validate(client.get("/parts", params={"offset": offset, "limit": 37}).json())
        assert page.total == len(catalog) and page.offset == offset and page.limit == 37
        seen += [p.part_id for p in page.items]
        if len(page.items) < 37:
            break
        offset += 37
    assert seen == catalog.part_ids


def test_category_and_shape_filters(client: TestClient, catalog: Catalog) -> None:
    for category in catalog.categories:
        response = client.get("/parts", params={"category": category, "limit": 100})
        page = PartsPage.model_validate(response.json())
        assert page.total == int(np.sum(catalog.category_of == catalog.categories.index(category)))
        assert {p.category for p in page.items} == {category}
    shape = catalog.records[0]["shape_id"]
    page = PartsPage.model_validate(client.get("/parts", params={"shape_id": shape}).json())
    expected = [r["part_id"] for r in catalog.records if r["shape_id"] == shape]
    assert [p.part_id for p in page.items] == expected


def _search(client: TestClient, **params: object) -> tuple[int, list[str]]:
    response = client.get("/parts", params={"limit": 100, **params})
    assert response.status_code == 200, response.text
    page = PartsPage.model_validate(response.json())
    return page.total, [p.part_id for p in page.items]


def _containing(catalog: Catalog, text: str, category: str | None = None) -> list[str]:
    """What the search should find: parts whose id or name contains the text, case-insensitive."""
    return [r["part_id"] for r in catalog.records
            if (category is None or r["category"] == category)
            and any(text.lower() in str(r.get(key) or "").lower() for key in ("part_id", "name"))]


def test_text_search_pages_and_combines_with_the_category(client: TestClient, catalog: Catalog) -> None:
    chair_ids = _containing(catalog, "chair-00", "chair")
    assert len(chair_ids) > 100  # two pages
    total, first = _search(client, category="chair", q="CHAIR-00")
    assert total == len(chair_ids) and first == chair_ids[:100]
    _, second = _search(client, category="chair", q="CHAIR-00", offset=100)
    assert second == chair_ids[100:200]
    total, shape = _search(client, q=" chair-0007/ ")  # trimmed
    assert shape == _containing(catalog, "chair-0007/") and total == len(shape) > 0
    assert _search(client, q="no part is called this") == (0, [])
    chairs = int(np.sum(catalog.category_of == catalog.categories.index("chair")))
    assert _search(client, category="chair", q="")[0] == chairs
    response = client.get("/parts", params={"q": "x" * 101})
    assert response.status_code == 422 and response.json()["error"]["code"] == "validation_error"


def test_text_search_never_reads_labels(client: TestClient, catalog: Catalog) -> None:
    """Labels of the data are for measuring only: a label's text finds only ids and names holding it."""
    labels = sorted({str(r["label"]) for r in catalog.records if r["category"] == "chair" and r["label"]})
    labelled = 0
    for label in labels:
        expected = _containing(catalog, label, "chair")
        assert _search(client, category="chair", q=label) == (len(expected), expected[:100]), label
        labelled += sum(r["category"] == "chair" and r["label"] == label and r["part_id"] not in expected
                        for r in catalog.records)
    assert labelled > 0  # parts a label search would have found: the check above can fail


def test_categories(client: TestClient, catalog: Catalog) -> None:
    cats = [CategoryOut.model_validate(c) for c in client.get("/categories").json()]
    assert [c.name for c in cats] == catalog.categories
    assert sum(c.parts for c in cats) == len(catalog)


def test_part_record(client: TestClient, catalog: Catalog) -> None:
    dup = next((i for i, r in enumerate(catalog.records) if r["duplicate_of"] is not None), 0)
    rec = catalog.records[dup]
    part = PartOut.model_validate(client.get(f"/parts/{rec['part_id']}").json())
    assert part.part_id == rec["part_id"] and part.shape_id == rec["shape_id"]
    np.testing.assert_allclose(part.translation, rec["translation"])
    if rec["duplicate_of"] is not None:
        assert part.duplicate_of == catalog.part_ids[rec["duplicate_of"]] and part.duplicates >= 2
    # The slash may also come percent-encoded.
    encoded = client.get("/parts/" + quote(rec["part_id"], safe=""))
    assert encoded.status_code == 200 and encoded.json()["part_id"] == rec["part_id"]


@pytest.mark.parametrize("fmt", ["glb", "obj", "ply"])
def test_part_mesh_formats(client: TestClient, catalog: Catalog, fmt: str) -> None:
    pid = catalog.part_ids[len(catalog) // 2]
    v, f = catalog.mesh(catalog.lookup(pid))
    response = client.get(f"/parts/{pid}/mesh", params={"format": fmt})
    assert response.status_code == 200
    media = response.headers["content-type"].split(";")[0]
    assert media == {"glb": "model/gltf-binary", "obj": "model/obj", "ply": "application/x-ply"}[fmt]
    mesh = trimesh.load(io.BytesIO(response.content), file_type=fmt, force="mesh", process=False)
    assert len(mesh.faces) == len(f)
    np.testing.assert_allclose(mesh.bounds, [v.min(axis=0), v.max(axis=0)], atol=1e-5)


def test_default_mesh_is_glb(client: TestClient, catalog: Catalog) -> None:
    response = client.get(f"/parts/{catalog.part_ids[0]}/mesh")
    assert response.headers["content-type"] == "model/gltf-binary" and response.content[:4] == b"glTF"


def test_part_points(client: TestClient, catalog: Catalog) -> None:
    pid = catalog.part_ids[-1]
    expected = catalog.part_points(catalog.lookup(pid))
    as_json = PartPointsOut.model_validate(client.get(f"/parts/{pid}/points").json())
    np.testing.assert_array_equal(np.array(as_json.points, np.float32), expected)
    response = client.get(f"/parts/{pid}/points", params={"encoding": "base64"})
    as_b64 = PartPointsOut.model_validate(response.json())
    assert as_b64.points is None and as_b64.n_points == len(expected)
    np.testing.assert_array_equal(points_from_base64(as_b64.points_base64 or "", 10**6), expected)
