"""JSON bodies: UTF-8 JSON only (415 otherwise), and too many points refused before parsing."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import orjson
import pytest
from fastapi.testclient import TestClient
from service_testkit import AssemblyQuery, make_settings

from service.api import create_app


def test_a_non_json_media_type_gets_415(client: TestClient, query: AssemblyQuery) -> None:
    body = orjson.dumps({"points": query.points.tolist()})
    for content_type in ("text/plain", "application/x-www-form-urlencoded", "multipart/form-data; boundary=x",
                         "application/json; charset=utf-16"):
        response = client.post("/suggest", content=body, headers={"content-type": content_type})
        assert response.status_code == 415, (content_type, response.text)
        assert response.json()["error"]["code"] == "unsupported_media_type"
    for content_type in ("application/json", "application/json; charset=UTF-8", "application/vnd.x+json"):
        response = client.post("/suggest", content=body, headers={"content-type": content_type})
        assert response.status_code == 200, (content_type, response.text)
    assert client.post("/place", content=b"{}", headers={"content-type": "text/plain"}).status_code == 415


def test_a_utf16_body_is_refused(client: TestClient, query: AssemblyQuery) -> None:
    text = orjson.dumps({"points": query.points.tolist()}).decode()
    for encoding in ("utf-16", "utf-16-le", "utf-16-be", "utf-32"):
        response = client.post("/suggest", content=text.encode(encoding),
                               headers={"content-type": "application/json"})
        assert response.status_code == 415, (encoding, response.text)
        assert "UTF-8" in response.json()["error"]["message"]


def test_a_batch_with_too_many_points_in_all_is_refused_before_parsing(client: TestClient,
                                                                        settings: object) -> None:
    limit = client.app.state.settings.max_body_points  # type: ignore[attr-defined]
    row = [0, 0, 1]
    items = [{"points": [row] * (limit // 4 + 300)} for _ in range(4)]  # past the 1024 spare brackets
    big = orjson.dumps({"items": items})
    assert len(big) < client.app.state.settings.max_body_bytes  # type: ignore[attr-defined]
    response = client.post("/suggest/batch", content=big,
                           headers={"content-type": "application/json"})
    assert response.status_code == 422 and response.json()["error"]["code"] == "too_many_points"
    assert str(limit) in response.json()["error"]["message"]


@pytest.fixture(scope="module")
def roomy_client(artifacts: Path) -> Iterator[TestClient]:
    """A body limit large enough for the issue's 8.3 MB body of 1.04M points."""
    with TestClient(create_app(make_settings(artifacts, max_body_bytes=16 * 2**20))) as c:
        yield c


def _worst_healthz(client: TestClient, probes: int) -> float:
    worst = 0.0
    for _ in range(probes):
        start = time.perf_counter()
        assert client.get("/healthz").status_code == 200
        worst = max(worst, time.perf_counter() - start)
        time.sleep(0.005)
    return worst


def test_a_million_point_body_never_stalls_healthz(roomy_client: TestClient) -> None:
    """Before the count, the parse held the event loop 1.4-1.7 s. The bound is 50 ms beyond the
    worst of as many probes of an idle server (the in-process client's own delays on a loaded
    2-core machine reached 20-50 ms there)."""
    body = orjson.dumps({"points": np.random.default_rng(0).integers(0, 10, (1_040_000, 3)).tolist()})
    assert len(body) > 8e6
    idle = _worst_healthz(roomy_client, 20)
    answer: list[object] = []
    sender = threading.Thread(target=lambda: answer.append(roomy_client.post(
        "/suggest", content=body, headers={"content-type": "application/json"})))
    worst, probes = 0.0, 0
    sender.start()
    while sender.is_alive() or probes < 20:
        start = time.perf_counter()
        assert roomy_client.get("/healthz").status_code == 200
        worst = max(worst, time.perf_counter() - start)
        probes += 1
        time.sleep(0.005)
    sender.join()
    response = answer[0]
    assert response.status_code == 422 and response.json()["error"]["code"] == "too_many_points"  # type: ignore[attr-defined]
    assert worst < 0.05 + idle, f"/healthz took {worst * 1000:.0f} ms (idle: {idle * 1000:.0f} ms)"
