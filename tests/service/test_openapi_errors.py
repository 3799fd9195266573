"""The error bodies /openapi.json documents are the ones the service sends."""

from __future__ import annotations

import json
from typing import Any

import pytest
from fastapi.testclient import TestClient

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
