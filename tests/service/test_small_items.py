"""The smaller findings of the reliability issue: HEAD, secrets kept out of errors and logs, a
repeated upload field on POST /parts."""

from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import pytest
from catalog_testkit import AUTH, writable_settings
from fastapi.testclient import TestClient
from pydantic import ValidationError

from service.api.access_log import RedactSecrets, redact_query
from service.api.app import create_app
from service.settings import Settings


@pytest.mark.parametrize("path", ["/healthz", "/readyz", "/model", "/parts?limit=2", "/metrics",
                                  "/categories"])
def test_head_answers_like_get_without_a_body(client: TestClient, path: str) -> None:
    got, head = client.get(path), client.head(path)
    assert head.status_code == got.status_code == 200
    assert head.content == b""
    assert head.headers["content-type"] == got.headers["content-type"]
    if "content-length" in got.headers and path != "/metrics":  # metrics change between the calls
        assert head.headers["content-length"] == got.headers["content-length"]


def test_head_on_a_post_route_is_still_405(client: TestClient) -> None:
    response = client.head("/suggest")
    assert response.status_code == 405


def test_a_short_api_key_is_not_echoed_in_the_start_up_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COMPLEMENTME_API_KEY", "short-secret1")
    with pytest.raises(ValidationError) as err:
        Settings()
    assert "short-secret1" not in str(err.value)
    assert "api_key" in str(err.value) and "16 characters" in str(err.value)


def test_a_key_in_the_query_string_is_redacted_from_the_access_log() -> None:
    assert redact_query("/parts?api_key=abc123&limit=5") == "/parts?api_key=REDACTED&limit=5"
    assert redact_query("/parts?limit=5&access_token=abc") == "/parts?limit=5&access_token=REDACTED"
    assert redact_query("/parts?offset=5&limit=5") == "/parts?offset=5&limit=5"
    record = logging.LogRecord("uvicorn.access", logging.INFO, __file__, 1, '%s - "%s %s HTTP/%s" %d',
                               ("127.0.0.1:5", "POST", "/parts?key=s3cret", "1.1", 401), None)
    assert RedactSecrets().filter(record)
    assert "s3cret" not in record.getMessage() and "key=REDACTED" in record.getMessage()
    create_app(Settings(artifacts=Path("unused")))  # the app factory installs the filter
    assert any(isinstance(f, RedactSecrets) for f in logging.getLogger("uvicorn.access").filters)


@pytest.fixture(scope="module")
def writable_client(artifacts: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    with TestClient(create_app(writable_settings(artifacts, tmp_path_factory.mktemp("data")))) as c:
        yield c


def test_a_repeated_file_on_post_parts_is_422_duplicate_field(writable_client: TestClient) -> None:
    obj = b"v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
    response = writable_client.post("/parts", headers=AUTH, data={"category": "chair"},
                                    files=[("file", ("a.obj", obj)), ("file", ("b.obj", obj))])
    assert response.status_code == 422, response.text
    assert response.json()["error"]["code"] == "duplicate_field"
    response = writable_client.post("/parts", headers=AUTH, data={"category": "chair"},
                                    files=[("file", ("a.obj", obj)), ("extra", ("b.obj", obj))])
    assert response.status_code == 422 and response.json()["error"]["code"] == "unexpected_file"
