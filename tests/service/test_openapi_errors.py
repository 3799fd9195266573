"""The error bodies /openapi.json documents are the ones the service sends."""

from __future__ import annotations

import json
from typing import Any

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.artifacts.catalog import Catalog

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


def _error_responses(schema: dict[str, Any]) -> list[tuple[str, str, str, dict[str, Any]]]:
    return [(path, method, status, response)
            for path, ops in schema["paths"].items() for method, op in ops.items()
            for status, response in op["responses"].items() if status[0] in "45"]


def test_every_documented_error_is_the_error_envelope(client: TestClient) -> None:
    schema = client.get("/openapi.json").json()
    wrong = [(path, method, status) for path, method, status, response in _error_responses(schema)
             if response.get("content", {}).get("application/json", {}).get("schema")
             != {"$ref": "#/components/schemas/ErrorResponse"}]
    assert not wrong, wrong
    assert "HTTPValidationError" not in json.dumps(schema)


def _matches(body: Any, schema: dict[str, Any], components: dict[str, Any]) -> bool:
    """A small structural check: required keys present and typed as the schema says."""
    if "$ref" in schema:
        return _matches(body, components[schema["$ref"].rsplit("/", 1)[1]], components)
    if "anyOf" in schema:
        return any(_matches(body, s, components) for s in schema["anyOf"])
    kind = schema.get("type")
    if kind == "object":
        return (isinstance(body, dict) and all(k in body for k in schema.get("required", []))
                and all(_matches(body[k], s, components) for k, s in schema.get("properties", {}).items()
                        if k in body))
    if kind == "array":
        return isinstance(body, list) and all(_matches(b, schema.get("items", {}), components) for b in body)
    types = {"string": str, "integer": int, "number": (int, float), "boolean": bool, "null": type(None)}
    return kind is None or isinstance(body, types[kind])


@pytest.mark.parametrize(("method", "template", "query", "status"), [
    ("GET", "/parts/{part_id}/mesh", "?format=nope", 422),
    ("GET", "/parts/{part_id}/points", "?encoding=nope", 422),
    ("GET", "/parts/{part_id}", "", 200),  # the control: a good request answers
    ("DELETE", "/parts/{part_id}", "", 403),
    ("POST", "/suggest", "", 422),
])
def test_sent_errors_match_the_documented_body(client: TestClient, catalog: Catalog, method: str,
                                               template: str, query: str, status: int) -> None:
    schema = client.get("/openapi.json").json()
    path = template.replace("{part_id}", catalog.records[0]["part_id"]) + query
    answer = client.request(method, path, json={} if method == "POST" else None)
    assert answer.status_code == status, answer.text
    if status < 400:
        return
    documented = schema["paths"][template][method.lower()]["responses"]
    assert str(status) in documented, (template, method, status, sorted(documented))
    assert _matches(answer.json(), documented[str(status)]["content"]["application/json"]["schema"],
                    schema["components"]["schemas"]), answer.json()
    # and not merely because the check is loose: FastAPI's own body would not pass it
    assert not _matches({"detail": [{"loc": ["query"], "msg": "x", "type": "y"}]},
                        documented[str(status)]["content"]["application/json"]["schema"],
                        schema["components"]["schemas"])


def test_the_document_carries_this_servers_limits_and_the_server_enforces_them(settings: Any,
                                                                              query: Any) -> None:
    """A client generated from /openapi.json sees the limits of the server it came from."""
    small = settings.model_copy(update={"max_k": 7, "default_k": 5, "max_batch_items": 2, "min_points": 20})
    with TestClient(create_app(small)) as c:
        schema = c.get("/openapi.json").json()
        assert schema["info"]["x-limits"]["max_k"] == 7
        models = schema["components"]["schemas"]
        k = next(b for b in models["SuggestRequest"]["properties"]["k"]["anyOf"]
                 if b.get("type") == "integer")
        assert (k["minimum"], k["maximum"], k["default"]) == (1, 7, 5)
        items = models["BatchRequest"]["properties"]["items"]
        assert (items["minItems"], items["maxItems"]) == (1, 2)
        cloud = next(b for b in models["SuggestRequest"]["properties"]["points"]["anyOf"]
                     if b.get("type") == "array")
        assert (cloud["minItems"], cloud["maxItems"]) == (20, small.max_points)
        # ... and the bounds are the ones the server enforces.
        points = query.points.tolist()
        assert c.post("/suggest", json={"points": points, "k": 7}).status_code == 200
        over = c.post("/suggest", json={"points": points, "k": 8})
        assert over.status_code == 422 and over.json()["error"]["code"] == "k_out_of_range"
        batch = c.post("/suggest/batch", json={"items": [{"points": points}] * 3})
        assert batch.status_code == 422 and batch.json()["error"]["code"] == "too_many_items"
        few = c.post("/suggest", json={"points": points[:19]})
        assert few.status_code == 422 and few.json()["error"]["code"] == "too_few_points"




def test_the_answers_of_the_layers_and_of_mesh_reading_are_documented_once(client: TestClient) -> None:
    """400 (not JSON, not a valid form) comes from the parsers, not from a route, and a mesh upload's
    413 and 415 from reading the file: every operation documents each in the same words (one owner:
    service.api.openapi_extras and service.api.mesh_upload.MESH_UPLOAD_ERRORS). A 413 names the
    limits that apply, and the suggestion routes' also their request budget (413 over_budget)."""
    from service.api.mesh_upload import MESH_UPLOAD_ERRORS
    from service.api.openapi_extras import BODY_TOO_LARGE

    schema = client.get("/openapi.json").json()
    with_body = {(path, m): op for path, ops in schema["paths"].items() for m, op in ops.items()
                 if "requestBody" in op}
    meshes = {key for key, op in with_body.items() if "Not OBJ" in op["responses"].get("415", {}).get(
        "description", "")}
    assert {path for path, _m in meshes} >= {"/suggest/mesh", "/assemble/mesh", "/parts"}
    for status, keys in (("400", set(with_body)), ("415", meshes)):
        said = {with_body[key]["responses"][status]["description"] for key in keys}
        assert len(said) == 1, f"{status} is documented {len(said)} ways: {sorted(said)}"
    for key, op in with_body.items():
        said = op["responses"]["413"]["description"]
        shared = MESH_UPLOAD_ERRORS[413]["description"] if key in meshes else BODY_TOO_LARGE
        assert said.startswith(shared), (key, said)
        budgeted = key[0] in ("/suggest", "/suggest/batch", "/suggest/mesh")
        assert ("over_budget" in said and "COMPLEMENTME_MAX_REQUEST_COST_MS" in said) == budgeted, (key, said)
