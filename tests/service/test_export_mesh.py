"""POST /export and service.modeling.export_mesh: placed catalog parts as one GLB or OBJ file."""

from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh
from fastapi.testclient import TestClient

from service.artifacts.catalog import Catalog
from service.errors import InputError, NotFoundError
from service.geometry.frames import Frame
from service.modeling.export_mesh import ExportItem, export_assembly
from service.settings import Settings


def _items(catalog: Catalog, n: int) -> list[ExportItem]:
    out = []
    for i in range(n):
        x, y, z = (float(v) for v in catalog.translations[i])
        out.append(ExportItem(catalog.part_ids[i], (x, y, z)))
    return out


@pytest.mark.parametrize("fmt", ["glb", "obj"])
def test_export_places_every_part(catalog: Catalog, fmt: str) -> None:
    items = _items(catalog, 3)
    data = export_assembly(catalog, items, fmt)  # type: ignore[arg-type]
    scene = trimesh.load_scene(io.BytesIO(data), file_type=fmt)
    placed = np.concatenate([catalog.mesh(i)[0] + catalog.translations[i] for i in range(3)])
    np.testing.assert_allclose(scene.bounds, [placed.min(axis=0), placed.max(axis=0)], atol=1e-3)
    faces = sum(len(catalog.mesh(i)[1]) for i in range(3))
    assert sum(len(g.faces) for g in scene.geometry.values()) == faces
    if fmt == "glb":  # one node per part, named by index and part id
        names = sorted(scene.graph.nodes_geometry)
        assert names == sorted(f"{n}_{it.part_id.replace('/', '_')}" for n, it in enumerate(items))
    else:
        assert data.decode().count("\no ") == 3


def test_export_scale_and_frame(catalog: Catalog) -> None:
    """scale multiplies the part about its centre; a frame maps like every answer of the API."""
    v, _ = catalog.mesh(0)
    pid = catalog.part_ids[0]
    data = export_assembly(catalog, [ExportItem(pid, (1.0, 2.0, 3.0), 2.0)], "glb",
                           Frame(center=np.array([1.0, 2.0, 3.0]), radius=10.0, up_axis="z"))
    mesh = next(iter(trimesh.load_scene(io.BytesIO(data), file_type="glb").geometry.values()))
    expected = 10.0 * (2.0 * v.astype(np.float64)) @ Frame(up_axis="z").part_rotation.T + [1.0, 2.0, 3.0]
    np.testing.assert_allclose(np.sort(mesh.vertices, axis=0), np.sort(expected, axis=0), atol=1e-3)


def test_export_refusals(catalog: Catalog) -> None:
    with pytest.raises(InputError) as err:
        export_assembly(catalog, [], "glb")
    assert err.value.code == "no_parts"
    with pytest.raises(InputError) as err:
        export_assembly(catalog, _items(catalog, 3), "glb", max_parts=2)
    assert err.value.code == "too_many_parts"
    with pytest.raises(NotFoundError):
        export_assembly(catalog, [ExportItem("no-such/0", (0.0, 0.0, 0.0))], "glb")
    with pytest.raises(InputError) as err:
        export_assembly(catalog, [ExportItem(catalog.part_ids[0], (1e308, 0.0, 0.0), 1.0)], "glb",
                        Frame(radius=1e10))
    assert err.value.code == "non_finite_geometry"


def test_api_export(client: TestClient, catalog: Catalog, settings: Settings) -> None:
    parts = [{"part_id": catalog.part_ids[i], "translation": [float(x) for x in catalog.translations[i]]}
             for i in range(2)]
    r = client.post("/export", json={"parts": parts})
    assert r.status_code == 200 and r.headers["content-type"] == "model/gltf-binary"
    assert 'filename="assembly.glb"' in r.headers["content-disposition"]
    assert len(trimesh.load_scene(io.BytesIO(r.content), file_type="glb").geometry) == 2
    r = client.post("/export", json={"parts": parts, "format": "obj"})
    assert r.status_code == 200 and r.headers["content-type"] == "model/obj"
    assert r.content.decode().count("\no ") == 2


@pytest.mark.parametrize(("body", "status", "code"), [
    ({"parts": []}, 422, "no_parts"),
    ({"parts": [{"part_id": "no-such/0", "translation": [0, 0, 0]}]}, 404, "unknown_part"),
    ({"parts": [{"part_id": "P", "translation": [0, 0]}]}, 422, "validation_error"),
    ({"parts": [{"part_id": "P", "translation": [0, 0, 0], "scale": 0}]}, 422, "validation_error"),
    ({"parts": [{"part_id": "P", "translation": [0, 0, 0], "scale": -1}]}, 422, "validation_error"),
    ({"parts": [{"part_id": "P", "translation": [0, "x", 0]}]}, 422, "validation_error"),
    ({"parts": [{"part_id": "P", "translation": [0, 0, 0]}], "format": "stl"}, 422, "validation_error"),
    ({"parts": [{"part_id": "P", "translation": [0, 0, 0]}], "extra": 1}, 422, "validation_error"),
])
def test_api_export_errors(client: TestClient, catalog: Catalog, body: dict, status: int, code: str) -> None:
    for p in body.get("parts", []):
        if p["part_id"] == "P":
            p["part_id"] = catalog.part_ids[0]
    r = client.post("/export", json=body)
    assert r.status_code == status, r.text
    assert r.json()["error"]["code"] == code


def test_api_export_part_limit(client: TestClient, catalog: Catalog, settings: Settings) -> None:
    n = settings.max_export_parts + 1
    parts = [{"part_id": catalog.part_ids[0], "translation": [0, 0, 0]}] * n
    r = client.post("/export", json={"parts": parts})
    assert r.status_code == 422 and r.json()["error"]["code"] == "too_many_parts"
    assert str(settings.max_export_parts) in r.json()["error"]["message"]
