"""The benchmark query: 1000 points, k = 10, and its two request bodies."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import orjson
import pytest

from bench.query import EXAMPLE, load_query
from service.api.schemas import SuggestRequest


def test_example_query_has_1000_points_and_k_10() -> None:
    q = load_query(EXAMPLE)
    assert q.points.shape == (1000, 3) and q.points.dtype == np.float32
    assert q.k == 10


def test_both_bodies_decode_to_the_same_points() -> None:
    q = load_query(EXAMPLE)
    for kind, tol in (("json", 1e-6), ("base64", 0.0)):
        req = SuggestRequest.model_validate(json.loads(q.body(kind)))
        assert req.k == 10
        np.testing.assert_allclose(req.to_points(10_000), q.points, atol=tol)
    body = orjson.loads(q.body("base64", refine_contact=False))
    assert body["refine_contact"] is False
    with pytest.raises(ValueError, match="unknown body kind"):
        q.body("msgpack")


def test_other_point_counts_are_resampled(tmp_path: Path) -> None:
    path = tmp_path / "q.json"
    path.write_text(json.dumps({"points": np.random.default_rng(0).normal(size=(300, 3)).tolist()}))
    a, b = load_query(path), load_query(path)
    assert a.points.shape == (1000, 3)
    np.testing.assert_array_equal(a.points, b.points)  # seeded


def test_bad_query_file_names_the_file(tmp_path: Path) -> None:
    path = tmp_path / "bad.json"
    path.write_text('{"points": [[1, 2]]}')
    with pytest.raises(ValueError, match=r"bad\.json"):
        load_query(path)
