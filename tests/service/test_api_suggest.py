"""``POST /suggest``, ``/suggest/mesh``, ``/suggest/batch`` and ``/place`` on the real app."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh
from fastapi.testclient import TestClient
from service_testkit import TEST_LIMITS, AssemblyQuery, assembly_query, make_settings, multi_part_shapes

from service.api.app import create_app
from service.api.schemas import BatchResponse, PlaceResponse, SuggestResponse
from service.artifacts.catalog import Catalog
from service.geometry.inputs import points_to_base64
from service.geometry.mesh import load_mesh_bytes, sample_surface
from service.settings import Settings
from service.suggest.engine import SuggestionEngine


def suggest(client: TestClient, **body: Any) -> dict[str, Any]:
    response = client.post("/suggest", json=body)
    assert response.status_code == 200, response.text
    return SuggestResponse.model_validate(response.json()).model_dump()


def ranking(answer: dict[str, Any]) -> list[str]:
    return [s["part_id"] for s in answer["suggestions"]]


def test_suggest_answers_ranked_placed_parts(client: TestClient, query: AssemblyQuery,
                                             engine: SuggestionEngine, catalog: Catalog) -> None:
    response = client.post("/suggest", json={"points": query.points.tolist(), "k": 7})
    assert response.status_code == 200
    assert response.headers["x-model-version"] == engine.model_version
    answer = SuggestResponse.model_validate(response.json())
    assert answer.model_version == engine.model_version
    assert answer.input_points == len(query.points)
    assert len(answer.suggestions) == 7 and [s.rank for s in answer.suggestions] == list(range(1, 8))
    # Each mode's own parts come in the order of their rank scores (in the default share order the
    # slots after the first few are dealt to modes by weight; in the likelihood order all parts
    # are ranked), each at most its log-likelihood (the key subtracts fit penalties).
    for mode in {s.mode for s in answer.suggestions}:
        keys = [s.rank_score for s in answer.suggestions if s.mode == mode]
        assert keys == sorted(keys, reverse=True)
    assert all(s.rank_score <= s.score + 1e-9 for s in answer.suggestions)
    assert len(answer.modes) == engine.artifacts.n_modes
    assert abs(sum(m.weight for m in answer.modes) - 1.0) < 1e-4
    for s in answer.suggestions:
        i = catalog.lookup(s.part_id)
        rec = catalog.records[i]
        assert (s.shape_id, s.category, s.label) == (rec["shape_id"], rec["category"], rec["label"])
        assert s.mode_weight == pytest.approx(answer.modes[s.mode].weight)
        t, lo, hi = np.array(s.translation), np.array(s.bbox_min), np.array(s.bbox_max)
        assert np.all(np.isfinite(t)) and np.all(lo <= t + 1e-6) and np.all(t <= hi + 1e-6)
        # The placed box is the catalog's centred box scaled by the fitting scale, moved to the
        # translation.
        extent = (np.array(rec["bbox_max"]) - rec["bbox_min"]) * np.array(s.scale)
        np.testing.assert_allclose(hi - lo, extent, atol=1e-5)
        assert client.get(s.links.part).json()["part_id"] == s.part_id


def test_default_k_and_determinism(client: TestClient, query: AssemblyQuery, settings: Settings) -> None:
    a = suggest(client, points=query.points.tolist())
    b = suggest(client, points=query.points.tolist())
    assert len(a["suggestions"]) == min(settings.default_k, a["candidates"])
    assert a == b


def test_duplicates_are_collapsed(artifacts: Path, query: AssemblyQuery, catalog: Catalog) -> None:
    # Likelihood order without fit penalties (the complement check and the fit key reorder each
    # shortlist on its own, and the share order deals each list to the modes on its own).
    with TestClient(create_app(make_settings(artifacts, suggest_order="likelihood", rank_scale_weight=0.0,
                                             rank_move_weight=0.0))) as client:
        collapsed = suggest(client, points=query.points.tolist(), k=TEST_LIMITS["max_k"],
                            complement_check=False)
        full = suggest(client, points=query.points.tolist(), k=TEST_LIMITS["max_k"],
                       collapse_duplicates=False, complement_check=False)
    groups = [int(catalog.group[catalog.lookup(p)]) for p in ranking(collapsed)]
    assert len(groups) == len(set(groups))
    # Without collapsing, the best member of every group still comes in the same order.
    firsts: dict[int, str] = {}
    for p in ranking(full):
        firsts.setdefault(int(catalog.group[catalog.lookup(p)]), p)
    assert list(firsts.values())[:len(groups)] == ranking(collapsed)[:len(firsts)]


def test_category_filter(client: TestClient, query: AssemblyQuery, catalog: Catalog) -> None:
    for category in catalog.categories:
        answer = suggest(client, points=query.points.tolist(), k=5, category=category)
        assert answer["suggestions"], category
        assert {s["category"] for s in answer["suggestions"]} == {category}
    two = catalog.categories[:2]
    answer = suggest(client, points=query.points.tolist(), k=20, category=two)
    assert {s["category"] for s in answer["suggestions"]} <= set(two)


def test_exclusions(client: TestClient, query: AssemblyQuery, catalog: Catalog) -> None:
    before = suggest(client, points=query.points.tolist(), k=10)
    top = before["suggestions"][0]
    after = suggest(client, points=query.points.tolist(), k=10, exclude_parts=[top["part_id"]])
    group = catalog.group[catalog.lookup(top["part_id"])]
    assert all(catalog.group[catalog.lookup(p)] != group for p in ranking(after))
    after = suggest(client, points=query.points.tolist(), k=10, exclude_shapes=[top["shape_id"]])
    assert all(s["shape_id"] != top["shape_id"] for s in after["suggestions"])


def test_resampling_is_deterministic(client: TestClient, query: AssemblyQuery) -> None:
    many = np.concatenate([query.points, query.points[::-1] + 1e-4])  # not the model's count
    a = suggest(client, points_base64=points_to_base64(many))
    b = suggest(client, points_base64=points_to_base64(many))
    assert a == b and a["input_points"] == len(many)


def _mesh_without(catalog: Catalog, query: AssemblyQuery) -> trimesh.Trimesh:
    """The query's shape as one mesh: the kept parts' catalog meshes at their translations."""
    meshes = []
    for pid in query.kept:
        i = catalog.lookup(pid)
        v, f = catalog.mesh(i)
        meshes.append(trimesh.Trimesh(v + catalog.translations[i], f, process=False))
    return trimesh.util.concatenate(meshes)


@pytest.mark.parametrize("fmt", ["obj", "ply", "stl", "off", "glb"])
def test_json_base64_and_mesh_inputs_agree(client: TestClient, catalog: Catalog, query: AssemblyQuery,
                                           engine: SuggestionEngine, settings: Settings, fmt: str) -> None:
    data = _mesh_without(catalog, query).export(file_type=fmt)
    data = data.encode() if isinstance(data, str) else data
    response = client.post("/suggest/mesh", files={"file": (f"query.{fmt}", io.BytesIO(data))},
                           data={"options": '{"k": 8, "fit_frame": false}'})
    assert response.status_code == 200, response.text
    from_mesh = SuggestResponse.model_validate(response.json()).model_dump()
    # The same surface samples the service takes: same loader, same seed, the model's count.
    mesh = load_mesh_bytes(data, fmt, max_vertices=10**6, max_faces=10**6, ignore_obj_materials=True)
    pts = sample_surface(mesh.vertices, mesh.faces, engine.artifacts.query_points, settings.seed)
    from_json = suggest(client, points=pts.tolist(), k=8)
    from_b64 = suggest(client, points_base64=points_to_base64(pts), k=8)
    assert ranking(from_mesh) == ranking(from_json) == ranking(from_b64)
    for a, b in zip(from_mesh["suggestions"], from_b64["suggestions"], strict=True):
        np.testing.assert_allclose(a["translation"], b["translation"], atol=1e-6)
        assert a["score"] == pytest.approx(b["score"], rel=1e-9)


def test_mesh_upload_with_format_field_and_frame(client: TestClient, catalog: Catalog,
                                                 query: AssemblyQuery) -> None:
    mesh = _mesh_without(catalog, query)
    # The caller's mesh is z-up, twice as large and shifted; it says so in the options.
    turn = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # y-up -> z-up
    mesh.vertices = 2.0 * mesh.vertices @ turn.T + [0.5, 0.25, 1.0]
    data = mesh.export(file_type="ply")
    options = '{"k": 5, "frame": {"center": [0.5, 0.25, 1.0], "radius": 2.0, "up_axis": "z"}}'
    response = client.post("/suggest/mesh", files={"file": ("blob", io.BytesIO(data))},
                           data={"options": options, "format": "ply"})
    assert response.status_code == 200, response.text
    answer = response.json()
    assert answer["frame"]["up_axis"] == "z" and answer["frame"]["scale"] == 2.0
    np.testing.assert_allclose(answer["frame"]["rotation"], turn, atol=1e-12)


def test_frames_round_trip_exactly(client: TestClient, query: AssemblyQuery) -> None:
    """A query scaled by 2, shifted and z-up gives the same parts at the mapped translations.

    Scale 2 and binary-fraction offsets keep every coordinate exact in float, so the canonical
    points the networks see are bit-identical and so are rankings and scores.
    """
    center, radius = np.array([0.5, -1.25, 3.0]), 2.0
    turn = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # canonical (y-up) -> caller (z-up)
    caller = radius * query.points.astype(np.float64) @ turn.T + center
    canonical = suggest(client, points=query.points.tolist(), k=10)
    framed = suggest(client, points=caller.tolist(), k=10,
                     frame={"center": center.tolist(), "radius": radius, "up_axis": "z"})
    assert ranking(framed) == ranking(canonical)
    assert framed["frame"]["scale"] == radius
    for a, b in zip(canonical["suggestions"], framed["suggestions"], strict=True):
        assert a["score"] == b["score"]
        back = (np.array(b["translation"]) - center) / radius @ turn  # caller -> canonical
        np.testing.assert_allclose(back, a["translation"], atol=1e-6)
        lo = (np.array(b["bbox_min"]) - center) / radius @ turn
        hi = (np.array(b["bbox_max"]) - center) / radius @ turn
        np.testing.assert_allclose(np.minimum(lo, hi), a["bbox_min"], atol=1e-6)
        np.testing.assert_allclose(np.maximum(lo, hi), a["bbox_max"], atol=1e-6)


def test_frames_round_trip_generally(client: TestClient, query: AssemblyQuery, catalog: Catalog) -> None:
    """Any frame: parts found in both answers sit at consistently mapped translations."""
    rng = np.random.default_rng(5)
    center, radius = rng.normal(size=3) * 10, 0.37
    turn = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    caller = radius * query.points.astype(np.float64) @ turn.T + center
    canonical = {s["part_id"]: s for s in suggest(client, points=query.points.tolist(), k=20)["suggestions"]}
    framed = suggest(client, points=caller.tolist(), k=20,
                     frame={"center": center.tolist(), "radius": radius, "up_axis": "z"})
    common = [s for s in framed["suggestions"] if s["part_id"] in canonical]
    assert len(common) >= 10
    for s in common:
        back = (np.array(s["translation"]) - center) / radius @ turn
        np.testing.assert_allclose(back, canonical[s["part_id"]]["translation"], atol=1e-3)


@pytest.mark.parametrize("refine", [False, True])
def test_place_matches_suggest(client: TestClient, query: AssemblyQuery, refine: bool) -> None:
    """/place and /suggest agree, with contact refinement on in both or off in both."""
    flag = {"refine_contact": True} if refine else {}
    answer = suggest(client, points=query.points.tolist(), k=5, **flag)
    ids = ranking(answer)
    response = client.post("/place", json={"points_base64": points_to_base64(query.points), "part_ids": ids,
                                           **({} if refine else {"refine_contact": False})})
    assert response.status_code == 200, response.text
    placed = PlaceResponse.model_validate(response.json())
    assert [p.part_id for p in placed.placements] == ids
    for p, s in zip(placed.placements, answer["suggestions"], strict=True):
        np.testing.assert_allclose(p.translation, s["translation"], atol=1e-6)
        np.testing.assert_allclose(p.bbox_min, s["bbox_min"], atol=1e-6)


def test_place_the_missing_part(client: TestClient, query: AssemblyQuery) -> None:
    frame = {"center": [1.0, 2.0, 3.0], "radius": 4.0, "up_axis": "z"}
    turn = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    caller = 4.0 * query.points.astype(np.float64) @ turn.T + [1.0, 2.0, 3.0]
    plain = client.post("/place", json={"points": query.points.tolist(), "part_ids": [query.missing]}).json()
    framed = client.post("/place", json={"points": caller.tolist(), "part_ids": [query.missing],
                                         "frame": frame}).json()
    t = np.array(framed["placements"][0]["translation"])
    np.testing.assert_allclose((t - [1.0, 2.0, 3.0]) / 4.0 @ turn, plain["placements"][0]["translation"],
                               atol=1e-5)
    # Where the placement network puts the missing part vs. where it was (quality, on trained
    # artifacts): err = np.linalg.norm(plain_translation - query.missing_translation).
    assert np.all(np.isfinite(plain["placements"][0]["translation"]))


def test_batch_answers_good_items_and_flags_bad_ones(client: TestClient, catalog: Catalog,
                                                     engine: SuggestionEngine) -> None:
    shapes = multi_part_shapes(catalog, 3)
    queries = []
    for shape in shapes:
        parts = [r["part_id"] for r in catalog.records if r["shape_id"] == shape]
        queries.append(assembly_query(catalog, shape, parts[0], engine.artifacts.n_points, seed=1))
    bad_nan = [[float("nan")] * 3] * 20
    items: list[Any] = [
        {"points_base64": points_to_base64(queries[0].points), "k": 4},
        {"points": bad_nan},
        {"points": queries[1].points.tolist(), "k": 3, "category": catalog.categories[0]},
        {"points": queries[1].points.tolist(), "k": "many"},
        {"points": queries[2].points.tolist(), "category": "spaceship"},
        {"points_base64": points_to_base64(queries[2].points), "k": 2, "exclude_parts": ["no-such/0"]},
        {"points": queries[2].points.tolist(), "k": 6},
        42,
    ]
    import json

    text = json.dumps({"items": items})  # NaN survives as a literal, as a careless client would send
    response = client.post("/suggest/batch", content=text, headers={"content-type": "application/json"})
    assert response.status_code == 200, response.text
    answer = BatchResponse.model_validate(response.json())
    assert [r.index for r in answer.results] == list(range(len(items)))
    assert [r.ok for r in answer.results] == [True, False, True, False, False, False, True, False]
    codes = [r.error.code if r.error else None for r in answer.results]
    assert codes == [None, "non_finite_points", None, "validation_error", "unknown_category", "unknown_part",
                     None, "validation_error"]
    # Each good item equals the same query sent alone.
    for r, item in zip(answer.results, items, strict=True):
        if r.ok:
            assert r.result is not None
            alone = suggest(client, **item)
            assert r.result.model_dump() == alone


def test_batch_of_one_bad_item(client: TestClient) -> None:
    response = client.post("/suggest/batch", json={"items": [{"points": []}]})
    assert response.status_code == 200
    assert response.json()["results"] == [
        {"index": 0, "ok": False, "error": {"code": "empty_points", "message": response.json()["results"][0]
                                            ["error"]["message"]}}]
