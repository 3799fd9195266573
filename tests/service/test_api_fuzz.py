"""Random malformed requests: the answer is always a client error or a success, never a 500.

The session's TestClient re-raises any server exception, so an unhandled case fails here.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
from fastapi.testclient import TestClient
from service_testkit import AssemblyQuery

from service.geometry.inputs import points_to_base64

_SCALARS: list[Any] = [None, True, 0, -1, 1, 3, 10**30, 1.5, -0.0, 1e308, "", "x", "chair", "NaN", [], {}]


def _value(rng: np.random.Generator, good: Any) -> Any:
    roll = rng.random()
    if roll < 0.4:
        return good
    if roll < 0.8:
        return _SCALARS[rng.integers(len(_SCALARS))]
    return [_SCALARS[rng.integers(len(_SCALARS))] for _ in range(rng.integers(0, 4))]


def test_random_suggest_bodies(client: TestClient, query: AssemblyQuery) -> None:
    rng = np.random.default_rng(0)
    pts = query.points[:64]
    good: dict[str, Any] = {
        "points": pts.tolist(), "points_base64": points_to_base64(pts), "k": 3, "category": None,
        "exclude_parts": [], "exclude_shapes": [], "collapse_duplicates": True,
        "frame": {"center": [0.0, 0.0, 0.0], "radius": 1.0, "up_axis": "z"},
    }
    statuses = set()
    for _ in range(150):
        body = {k: _value(rng, v) for k, v in good.items() if rng.random() < 0.7}
        if "frame" in body and isinstance(body["frame"], dict) and rng.random() < 0.5:
            body["frame"] = {k: _value(rng, v) for k, v in body["frame"].items()}
        for path in ("/suggest", "/place"):
            if path == "/place":
                body = {k: v for k, v in body.items() if k in ("points", "points_base64", "frame")}
                body["part_ids"] = _value(rng, [query.kept[0]])
            response = client.post(path, content=json.dumps(body).encode(),
                                   headers={"content-type": "application/json"})
            statuses.add(response.status_code)
            assert response.status_code < 500, (path, body, response.text)
            if response.status_code >= 400:
                assert set(response.json()) == {"error"}
    assert 200 in statuses and 422 in statuses


def test_frames_that_blow_points_up(client: TestClient, query: AssemblyQuery) -> None:
    response = client.post("/suggest", json={"points": query.points.tolist(),
                                             "frame": {"center": [0, 0, 0], "radius": 1e-300}})
    assert response.status_code == 422 and response.json()["error"]["code"] == "non_finite_points"
