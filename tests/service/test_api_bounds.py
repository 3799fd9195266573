"""Integer and float bounds on every numeric field and query parameter: never a 500.

schemathesis (``test_fuzz_schemathesis.py``) draws values from the OpenAPI schema, which holds no
bound where the code had none, so it never sent a negative seed or an offset past 64 bits. These
property tests send the extremes of each numeric field on its own, into an otherwise valid
request: the answer must be a success or a client error with the JSON error body. The session's
TestClient re-raises any server exception, so an unhandled case fails here.
"""

from __future__ import annotations

from typing import Any

import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from service_testkit import AssemblyQuery

from service.geometry.inputs import points_to_base64

# A value at a bound must not overflow on its way through the engine (a float32 square of a
# wrong-frame query's distances did, and only warned).
pytestmark = pytest.mark.filterwarnings("error::RuntimeWarning")

# Integers around every boundary that matters: signs, 32, 53, 63 and 64 bits, and beyond.
_EDGES = [0, -1, 1, 2, 3, 2**31 - 1, 2**31, 2**53 + 1, 2**63 - 1, 2**63, 2**64 - 1, 2**64, 2**100]
INTEGERS = st.one_of(st.sampled_from(_EDGES + [-e for e in _EDGES]),
                     st.integers(min_value=-2**70, max_value=2**70))
FLOATS = st.one_of(st.floats(allow_nan=False, allow_infinity=False),
                   st.sampled_from([1.7e308, -1.7e308, 5e-324, -0.0, 1e15, 1e16]))
NUMBERS = st.one_of(INTEGERS, FLOATS)
_FAST = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _set(body: dict[str, Any], path: tuple[str | int, ...], value: Any) -> dict[str, Any]:
    node: Any = body
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return body


def _check(response: Any) -> None:
    assert response.status_code < 500, response.text
    if response.status_code >= 400:
        assert set(response.json()) == {"error"}, response.text
        assert response.json()["error"]["code"]
    else:
        assert b"Infinity" not in response.content and b"NaN" not in response.content


def _suggest_body(query: AssemblyQuery) -> dict[str, Any]:
    return {"points_base64": points_to_base64(query.points[:64]), "k": 3, "mode_weights": None,
            "exclude_modes": [], "frame": {"center": [0.0, 0.0, 0.0], "radius": 1.0}}


SUGGEST_FIELDS = [("k",), ("exclude_modes",), ("mode_weights",), ("frame", "center"), ("frame", "radius")]
ASSEMBLE_FIELDS = [("seed",), ("max_parts",), ("branching",), ("temperature",), ("exclude_modes",),
                   ("mode_weights",), ("frame", "radius"), ("frame", "center")]


@pytest.mark.parametrize("field", SUGGEST_FIELDS, ids=".".join)
def test_suggest_numbers_at_their_bounds(client: TestClient, query: AssemblyQuery,
                                         field: tuple[str, ...]) -> None:
    @_FAST
    @given(value=NUMBERS)
    def run(value: Any) -> None:
        if field[-1] in ("center", "exclude_modes", "mode_weights"):
            value = [value, value, value]
        _check(client.post("/suggest", json=_set(_suggest_body(query), field, value)))
        _check(client.post("/place", json={"points_base64": _suggest_body(query)["points_base64"],
                                           "part_ids": [query.kept[0]], "refine_contact": False,
                                           **({"frame": {field[1]: value}} if field[0] == "frame" else {})}))
    run()


@pytest.mark.parametrize("field", ASSEMBLE_FIELDS, ids=".".join)
def test_assemble_numbers_at_their_bounds(client: TestClient, query: AssemblyQuery,
                                          field: tuple[str, ...]) -> None:
    @settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(value=NUMBERS)
    def run(value: Any) -> None:
        if field[-1] in ("center", "exclude_modes", "mode_weights"):
            value = [value, value, value]
        body: dict[str, Any] = {"part_id": query.kept[0], "max_parts": 2, "refine_contact": False,
                                "strategy": "sample", "frame": {"center": [0, 0, 0], "radius": 1.0}}
        if field == ("max_parts",) and isinstance(value, int) and 2 < value <= 1000:
            value = 3  # a valid count; larger valid ones only cost time
        _check(client.post("/assemble", json=_set(body, field, value)))
    run()


@pytest.mark.parametrize("param", ["offset", "limit"])
def test_parts_paging_at_its_bounds(client: TestClient, param: str) -> None:
    @_FAST
    @given(value=INTEGERS)
    def run(value: int) -> None:
        _check(client.get("/parts", params={param: str(value)}))
    run()


def test_export_numbers_at_their_bounds(client: TestClient, query: AssemblyQuery) -> None:
    @_FAST
    @given(t=NUMBERS, scale=NUMBERS)
    def run(t: Any, scale: Any) -> None:
        part = {"part_id": query.kept[0], "translation": [t, t, t], "scale": scale}
        body = {"format": "obj", "parts": [part]}
        _check(client.post("/export", json=body))
    run()


def test_the_two_500s_found_by_hand_are_client_errors(client: TestClient) -> None:
    r = client.post("/assemble", json={"part_id": "chair-0007/0", "seed": -1})
    assert r.status_code == 422 and r.json()["error"]["details"][0]["loc"] == ["body", "seed"]
    r = client.get("/parts?offset=18446744073709551616")
    assert r.status_code == 422 and r.json()["error"]["details"][0]["loc"] == ["query", "offset"]


def test_an_extreme_frame_is_refused_not_answered_with_nulls(client: TestClient,
                                                             query: AssemblyQuery) -> None:
    frame = {"center": [-1.7e308] * 3, "radius": 1.7e308}
    for path, body in (("/suggest", {"points": query.points.tolist(), "frame": frame}),
                       ("/place", {"points": query.points.tolist(), "part_ids": [query.kept[0]],
                                   "frame": frame})):
        r = client.post(path, json=body)
        assert r.status_code == 422, r.text
        assert r.json()["error"]["details"][0]["loc"][:3] == ["body", "frame", "center"]
    # The largest frame allowed still answers finite numbers.
    r = client.post("/place", json={"points": query.points.tolist(), "part_ids": [query.kept[0]],
                                    "frame": {"center": [-1e15] * 3, "radius": 1e15}})
    assert r.status_code == 200 and b"null" not in r.content


def test_assemble_is_as_strict_as_suggest(client: TestClient, query: AssemblyQuery) -> None:
    for field, value in (("max_parts", "1"), ("seed", "1"), ("branching", True), ("refine_contact", "true"),
                         ("temperature", "1.5"), ("exclude_modes", ["1"])):
        r = client.post("/assemble", json={"part_id": query.kept[0], field: value})
        assert r.status_code == 422, (field, r.text)
        assert r.json()["error"]["details"][0]["loc"][:2] == ["body", field]


@pytest.mark.parametrize("radius", [1e-20, 1e-38])
def test_a_tiny_frame_radius_is_answered_with_a_frame_warning(client: TestClient, query: AssemblyQuery,
                                                              radius: float) -> None:
    """Points divided by a tiny radius lie near 1e20-1e38 in float32: the reach check squares them
    in float64 (float32 overflowed: a RuntimeWarning, found by the property test above), and the
    answer says the frame is wrong."""
    body = _suggest_body(query)
    body["frame"]["radius"] = radius
    response = client.post("/suggest", json=body)
    _check(response)
    assert response.status_code == 200
    assert any(w["code"] == "frame" for w in response.json()["warnings"]), response.json()["warnings"]
