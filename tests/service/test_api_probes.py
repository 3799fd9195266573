"""Probes, metrics, the model header and the OpenAPI document."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families
from service_testkit import AssemblyQuery

from service.api.app import create_app
from service.api.schemas import ModelInfo
from service.settings import Settings
from service.suggest.engine import SuggestionEngine


def test_healthz_and_readyz(client: TestClient, engine: SuggestionEngine) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz")
    assert ready.status_code == 200
    assert ready.json() == {"status": "ready", "model_version": engine.model_version}


def test_not_ready_before_the_lifespan(settings: Settings) -> None:
    # Without entering the TestClient context the lifespan has not run: nothing is loaded.
    bare = TestClient(create_app(settings))
    assert bare.get("/healthz").status_code == 200
    not_ready = bare.get("/readyz")
    assert not_ready.status_code == 503 and not_ready.json()["error"]["code"] == "not_ready"
    assert bare.post("/suggest", json={"points": [[0, 0, 0]] * 20}).status_code == 503
    assert "x-model-version" not in bare.get("/healthz").headers


def test_every_response_names_the_model(client: TestClient, engine: SuggestionEngine) -> None:
    for response in (client.get("/healthz"), client.get("/parts"), client.get("/no-such"),
                     client.post("/suggest", json={})):
        assert response.headers["x-model-version"] == engine.model_version


def test_model_info(client: TestClient, engine: SuggestionEngine, settings: Settings) -> None:
    info = ModelInfo.model_validate(client.get("/model").json())
    assert info.model_version == engine.model_version and info.part_count == len(engine.catalog)
    assert info.limits["max_k"] == settings.max_k and info.limits["max_points"] == settings.max_points


def _samples(client: TestClient) -> dict[str, list]:
    text = client.get("/metrics").text
    out: dict[str, list] = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out.setdefault(s.name, []).append(s)
    return out


def test_metrics(client: TestClient, query: AssemblyQuery, engine: SuggestionEngine) -> None:
    before = _samples(client)

    def count(samples: dict[str, list], route: str, status: str) -> float:
        return sum(s.value for s in samples.get("complementme_http_requests_total", [])
                   if s.labels["route"] == route and s.labels["status"] == status)

    client.post("/suggest", json={"points": query.points.tolist(), "k": 3})
    client.post("/suggest", json={"points": []})
    client.get(f"/parts/{engine.catalog.part_ids[0]}")
    after = _samples(client)
    assert count(after, "/suggest", "200") == count(before, "/suggest", "200") + 1
    assert count(after, "/suggest", "422") == count(before, "/suggest", "422") + 1
    # Part ids do not become labels: the route template does.
    assert count(after, "/parts/{part_id:path}", "200") >= 1
    assert all("/parts/" + engine.catalog.part_ids[0] != s.labels["route"]
               for s in after["complementme_http_requests_total"])
    buckets = after["complementme_http_request_duration_seconds_bucket"]
    assert any(s.labels["route"] == "/suggest" for s in buckets)
    graphs = {s.labels["graph"] for s in after["complementme_inference_duration_seconds_count"]}
    assert {"g", "h_query", "h_head"} <= graphs
    assert after["complementme_search_duration_seconds_count"][0].value >= 1
    assert after["complementme_batch_size_count"][0].value >= 1
    assert after["complementme_catalog_parts"][0].value == len(engine.catalog)
    assert after["complementme_model_info"][0].labels["model_version"] == engine.model_version


def test_openapi_has_examples_for_every_endpoint(client: TestClient) -> None:
    doc = client.get("/openapi.json").json()
    schemas = doc["components"]["schemas"]

    def has_examples(node: dict) -> bool:
        if "example" in node or "examples" in node:
            return True
        schema = node.get("schema", node)
        ref = schema.get("$ref") or schema.get("items", {}).get("$ref")
        return bool(ref) and "examples" in schemas[ref.rsplit("/", 1)[1]]

    missing = []
    for path, ops in doc["paths"].items():
        for method, op in ops.items():
            responses = op.get("responses", {})
            success = next((responses[c] for c in ("200", "201") if c in responses), None)
            ok = [has_examples(c) for c in (success or {}).get("content", {}).values()]
            no_content = success is None and "204" in responses  # e.g. DELETE: nothing to show
            body = op.get("requestBody", {}).get("content", {})
            ok_body = all(has_examples(c) for c in body.values())
            params_ok = all(has_examples(p) or has_examples(p["schema"]) for p in op.get("parameters", []))
            if not ((no_content or (ok and all(ok))) and ok_body and params_ok):
                missing.append(f"{method.upper()} {path}")
    assert not missing, f"operations without examples: {missing}"
    assert client.get("/docs").status_code == 200


def test_the_warm_up_builds_every_route_before_the_first_request(
        settings: Settings, query: AssemblyQuery, monkeypatch: pytest.MonkeyPatch) -> None:
    """FastAPI builds an included router's routes on their first request unless the warm-up did
    (``service.api.app.build_routes``): after a warmed start no request builds one; without the
    warm-up the first request does (so the count can tell)."""
    import fastapi.routing

    built: list[str] = []
    original = fastapi.routing._EffectiveRouteContext.from_api_route

    def counting(*args: object, **kwargs: object) -> object:
        built.append("route")
        return original(*args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(fastapi.routing._EffectiveRouteContext, "from_api_route", counting)
    body = {"points": query.points.tolist(), "k": 3}
    for warmup, expect_built in ((True, False), (False, True)):
        with TestClient(create_app(settings.model_copy(update={"warmup": warmup}))) as c:
            built.clear()
            assert c.post("/suggest", json=body).status_code == 200
            assert c.get("/parts", params={"limit": 1}).status_code == 200
            assert bool(built) is expect_built, (warmup, len(built))
