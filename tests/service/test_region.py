""""Suggest for this spot": a ``region`` on ``/suggest``, ``/suggest/mesh`` and ``/suggest/batch``.

On the real app and the shipped artifacts. Membership is checked on the answers' own placed
boxes; labels are read only to measure that the spot changes what is offered.
"""

from __future__ import annotations

import io
import json
from typing import Any

import numpy as np
import pytest
import trimesh
from fastapi.testclient import TestClient

from service.api.schemas import BatchResponse, SuggestResponse
from service.artifacts.catalog import Catalog
from service.errors import InputError
from service.geometry.frames import Frame
from service.settings import Settings
from service.suggest.region import Region

SEAT, BACK, LEG = "chair-0000/1", "chair-0000/2", "chair-0000/3"  # one chair's parts, the seat the query


def suggest(client: TestClient, **body: Any) -> dict[str, Any]:
    response = client.post("/suggest", json=body)
    assert response.status_code == 200, response.text
    return SuggestResponse.model_validate(response.json()).model_dump()


def labels(answer: dict[str, Any]) -> list[str | None]:
    return [s["label"] for s in answer["suggestions"]]


@pytest.fixture(scope="module")
def seat(catalog: Catalog) -> np.ndarray:
    """A lone chair seat as points in the canonical frame: (256, 3)."""
    i = catalog.lookup(SEAT)
    return catalog.part_points(i) + catalog.translations[i]


def spot(catalog: Catalog, part_id: str) -> list[float]:
    """Where a part of the seat's own chair sits (its box centre)."""
    return catalog.translations[catalog.lookup(part_id)].astype(np.float64).tolist()


def reach(s: dict[str, Any], point: np.ndarray) -> float:
    """Distance from a point to a suggestion's placed box (0 inside)."""
    lo, hi = np.array(s["bbox_min"]), np.array(s["bbox_max"])
    return float(np.linalg.norm(np.maximum(np.maximum(lo - point, point - hi), 0)))


@pytest.mark.parametrize("where, label", [(BACK, "back"), (LEG, "leg")])
def test_a_spot_gets_parts_placed_there(client: TestClient, catalog: Catalog, settings: Settings,
                                        seat: np.ndarray, where: str, label: str) -> None:
    point, radius = spot(catalog, where), 0.1
    answer = suggest(client, points=seat.tolist(), k=10, category="chair",
                     region={"point": point, "radius": radius})
    assert len(answer["suggestions"]) == 10
    for s in answer["suggestions"]:
        assert reach(s, np.array(point)) <= radius + 1e-6, s
    report = answer["region"]
    assert report["placed"] <= settings.region_candidates and report["inside"] >= 10
    assert report["nearest_gap"] is None and not any(w["code"] == "region_empty" for w in answer["warnings"])
    # Measured with the labels: the spot decides the kind. Without a region the seat gets a mix.
    assert labels(answer).count(label) >= 8, labels(answer)
    free = suggest(client, points=seat.tolist(), k=10, category="chair")
    assert free["region"] is None
    assert labels(answer).count(label) > labels(free).count(label) or labels(free).count(label) == 10


def test_a_box_keeps_parts_whose_box_overlaps(client: TestClient, catalog: Catalog, seat: np.ndarray) -> None:
    leg = catalog.lookup(LEG)
    lo = catalog.translations[leg] + catalog.bbox_min[leg]
    hi = catalog.translations[leg] + catalog.bbox_max[leg]
    answer = suggest(client, points=seat.tolist(), k=8, category="chair",
                     region={"min": lo.tolist(), "max": hi.tolist()})
    assert answer["suggestions"]
    for s in answer["suggestions"]:
        assert np.all(np.array(s["bbox_min"]) <= hi + 1e-6), s
        assert np.all(np.array(s["bbox_max"]) >= lo - 1e-6), s


def test_ranked_as_without_the_region(client: TestClient, catalog: Catalog, seat: np.ndarray) -> None:
    """The region filters the ranking; it does not reorder it: the region's answer is the free
    ranking (over as many candidates) with the parts placed elsewhere left out."""
    # A spot where the seat's free top 50 has parts (the legs': the likelihood order's first
    # mode); the region looks deeper (region_candidates), so those are the answer's first ones.
    point, radius = spot(catalog, LEG), 0.1
    free = suggest(client, points=seat.tolist(), k=50, category="chair", complement_check=False)
    there = suggest(client, points=seat.tolist(), k=5, category="chair", complement_check=False,
                    region={"point": point, "radius": radius})
    expected = [s["part_id"] for s in free["suggestions"] if reach(s, np.array(point)) <= radius + 1e-6][:5]
    answer = [s["part_id"] for s in there["suggestions"]]
    assert expected and len(answer) == 5
    assert answer[:len(expected)] == expected


def test_region_in_the_callers_frame(client: TestClient, catalog: Catalog, seat: np.ndarray) -> None:
    """A z-up frame at twice the size, shifted: the same parts as the canonical request."""
    center, radius = np.array([0.5, -1.25, 3.0]), 2.0
    turn = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # canonical (y-up) -> caller (z-up)
    point = np.array(spot(catalog, LEG))
    canonical = suggest(client, points=seat.tolist(), k=6, category="chair",
                        region={"point": point.tolist(), "radius": 0.1})
    framed = suggest(client, points=(radius * seat.astype(np.float64) @ turn.T + center).tolist(), k=6,
                     category="chair", frame={"center": center.tolist(), "radius": radius, "up_axis": "z"},
                     region={"point": (radius * point @ turn.T + center).tolist(), "radius": 0.1 * radius})
    assert [s["part_id"] for s in framed["suggestions"]] == [s["part_id"] for s in canonical["suggestions"]]
    caller_point = radius * point @ turn.T + center
    for s in framed["suggestions"]:
        assert reach(s, caller_point) <= 0.1 * radius + 1e-6


def test_an_empty_spot_says_why(client: TestClient, seat: np.ndarray, settings: Settings) -> None:
    frame = {"center": [0, 0, 0], "radius": 10.0}  # the caller's units: tenths of the model's
    answer = suggest(client, points=(10 * seat).tolist(), k=5, category="chair", frame=frame,
                     region={"point": [40.0, 40.0, 40.0], "radius": 1.0})
    assert answer["suggestions"] == []
    report = answer["region"]
    assert report["inside"] == 0 and 0 < report["placed"] <= settings.region_candidates
    # The gap is in the caller's units: the spot is about 60 units from the chair.
    assert 30 < report["nearest_gap"] < 70
    (warning,) = [w for w in answer["warnings"] if w["code"] == "region_empty"]
    assert warning["guess"] is False      # it says where the candidates are, not that they are guesses
    assert str(report["placed"]) in warning["message"] and "larger region" in warning["message"]


def test_mesh_upload_with_a_region(client: TestClient, catalog: Catalog) -> None:
    i = catalog.lookup(SEAT)
    vertices, faces = catalog.mesh(i)
    data = trimesh.Trimesh(vertices + catalog.translations[i], faces, process=False).export(file_type="obj")
    point = spot(catalog, BACK)
    options = json.dumps({"k": 5, "category": "chair", "region": {"point": point, "radius": 0.1},
                          "fit_frame": False})
    response = client.post("/suggest/mesh", files={"file": ("seat.obj", io.BytesIO(data.encode()))},
                           data={"options": options})
    assert response.status_code == 200, response.text
    answer = response.json()
    assert answer["region"]["inside"] >= 5 and len(answer["suggestions"]) == 5
    for s in answer["suggestions"]:
        assert reach(s, np.array(point)) <= 0.1 + 1e-6


def _error(response: Any, code: str) -> dict[str, Any]:
    assert response.status_code == 422, response.text
    body = response.json()
    assert body["error"]["code"] == code, body
    return body["error"]


@pytest.mark.parametrize("region, code, says", [
    ({"point": [0, 0, 0]}, "invalid_region", "found point"),
    ({"radius": 0.2}, "invalid_region", "found radius"),
    ({}, "invalid_region", "none of them"),
    ({"min": [0, 0, 0]}, "invalid_region", "min and max"),
    ({"point": [0, 0, 0], "radius": 0.1, "min": [0, 0, 0], "max": [1, 1, 1]}, "invalid_region", "either"),
    ({"min": [0, 0.5, 0], "max": [1, 0.2, 1]}, "invalid_region", "y: 0.5 > 0.2"),
    ({"point": [0, 0, 0], "radius": 0}, "validation_error", "region.radius"),
    ({"point": [0, 0, 0], "radius": -1}, "validation_error", "region.radius"),
    ({"point": [0, 0], "radius": 0.1}, "validation_error", "region.point"),
    ({"point": [0, 0, "a"], "radius": 0.1}, "validation_error", "region.point"),
    ({"point": [0, 0, 1e300], "radius": 0.1}, "validation_error", "region.point"),
    ({"point": [0, 0, 0], "radius": 1e300}, "validation_error", "region.radius"),
    ({"centre": [0, 0, 0], "radius": 0.1}, "validation_error", "region.centre"),
    ([0, 0, 0], "validation_error", "region"),
])
def test_bad_regions_are_refused(client: TestClient, seat: np.ndarray, region: Any, code: str,
                                 says: str) -> None:
    err = _error(client.post("/suggest", json={"points": seat[:64].tolist(), "region": region}), code)
    assert says in err["message"], err
    # The same refusal from the mesh route's options, and as one failed item of a batch.
    files = {"file": ("t.obj", io.BytesIO(b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"))}
    options = json.dumps({"region": region})
    err = _error(client.post("/suggest/mesh", files=files, data={"options": options}), code)
    batch = client.post("/suggest/batch", json={"items": [{"points": seat[:64].tolist(), "region": region},
                                                           {"points": seat[:64].tolist(), "k": 2}]})
    assert batch.status_code == 200, batch.text
    first, second = BatchResponse.model_validate(batch.json()).results
    assert not first.ok and first.error is not None and first.error.code == code
    assert second.ok


def test_region_non_finite_in_the_models_frame() -> None:
    region = Region.ball(np.array([1e15, 0, 0]), 1.0)
    with pytest.raises(InputError, match="not finite in the model's frame"):
        region.in_frame(Frame(radius=1e-300))


def test_gap_of_balls_and_boxes() -> None:
    lo = np.array([[0.0, 0, 0], [2, 0, 0], [0, 0, 0]])
    hi = np.array([[1.0, 1, 1], [3, 1, 1], [0.5, 1, 1]])
    ball = Region.ball(np.array([1.5, 0.5, 0.5]), 0.5)
    np.testing.assert_allclose(ball.gap(lo, hi), [0.0, 0.0, 0.5])
    box = Region.box(np.array([1.2, 0, 0]), np.array([1.8, 1, 1]))
    np.testing.assert_allclose(box.gap(lo, hi), [0.2, 0.2, 0.7])
    # Frames: a z-up frame twice as large keeps the region axis-aligned and halves its size.
    framed = Region.box(np.array([0.0, 0, 0]), np.array([2.0, 4, 6])).in_frame(Frame(radius=2.0, up_axis="z"))
    assert framed.box_min is not None and framed.box_max is not None
    np.testing.assert_allclose(framed.box_min, [0, 0, -2])
    np.testing.assert_allclose(framed.box_max, [1, 3, 0])
