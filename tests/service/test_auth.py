"""Catalog writes need the API key: no key, wrong key, right key, and servers that accept none."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from catalog_testkit import AUTH, KEY, add_part, part_mesh, writable_settings
from fastapi.testclient import TestClient
from pydantic import ValidationError

from service.api.app import create_app
from service.settings import Settings


@pytest.fixture(scope="module")
def keyed(artifacts: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    with TestClient(create_app(writable_settings(artifacts, tmp_path_factory.mktemp("data")))) as c:
        yield c


def _upload(client: TestClient, headers: dict[str, Any]) -> Any:
    return client.post("/parts", files={"file": ("p.ply", part_mesh(0))}, data={"category": "auth"},
                       headers=headers)


@pytest.mark.parametrize(("headers", "code"), [
    ({}, "missing_credentials"),
    ({"Authorization": "Bearer"}, "missing_credentials"),
    ({"Authorization": f"Basic {KEY}"}, "missing_credentials"),
    ({"Authorization": "Bearer not-the-key-at-all-000"}, "invalid_credentials"),
    ({"Authorization": f"Bearer {KEY}x"}, "invalid_credentials"),
    ({"Authorization": f"Bearer {KEY[:-1]}"}, "invalid_credentials"),
    ({"Authorization": "Bearer k\u00e9y-with-\u00fcnicode-000000".encode("latin-1")}, "invalid_credentials"),
])
def test_missing_or_wrong_key_gets_401(keyed: TestClient, headers: dict[str, Any], code: str) -> None:
    for response in (_upload(keyed, headers), keyed.delete("/parts/any/0", headers=headers)):
        assert response.status_code == 401, response.text
        assert response.json()["error"]["code"] == code
        assert response.headers["www-authenticate"].startswith("Bearer realm=")
    assert keyed.get("/catalog").json()["added_parts"] == 0


def test_right_key_writes(keyed: TestClient) -> None:
    response = add_part(keyed, 3, category="auth")
    assert response.status_code == 201, response.text
    assert keyed.delete(f"/parts/{response.json()['part_id']}", headers=AUTH).status_code == 204


def test_the_body_is_not_read_before_the_key_is_checked(keyed: TestClient, settings: Settings) -> None:
    # Over the upload limit: with the key this is a 413; without it the body is never read.
    huge = {"file": ("p.ply", b"x" * (settings.max_upload_bytes + 1))}
    assert keyed.post("/parts", files=huge, data={"category": "a"}).status_code == 401
    assert keyed.post("/parts", files=huge, data={"category": "a"}, headers=AUTH).status_code == 413


def test_reads_need_no_key(keyed: TestClient, catalog) -> None:
    for path in ("/catalog", "/categories", f"/parts/{catalog.part_ids[0]}", "/healthz"):
        assert keyed.get(path).status_code == 200


def test_no_key_configured_means_no_writes(artifacts: Path, tmp_path: Path) -> None:
    with TestClient(create_app(writable_settings(artifacts, tmp_path / "d", api_key=None))) as c:
        for headers in ({}, AUTH):
            response = _upload(c, headers)
            assert response.status_code == 403
            assert response.json()["error"]["code"] == "writes_disabled"
        assert c.delete("/parts/a/0", headers=AUTH).status_code == 403


def test_a_default_server_accepts_no_writes(client: TestClient) -> None:
    """The session's app is configured like a default server: no key and no data folder."""
    settings = client.app.state.settings  # type: ignore[attr-defined]
    assert settings.data_dir is None and settings.api_key is None
    response = client.post("/parts", files={"file": ("p.ply", part_mesh(0))}, data={"category": "a"},
                           headers=AUTH)
    assert response.status_code == 403 and response.json()["error"]["code"] == "writes_disabled"
    status = client.get("/catalog").json()
    assert status["writable"] is False and status["added_parts"] == 0


def test_key_but_no_data_folder(artifacts: Path) -> None:
    with TestClient(create_app(writable_settings(artifacts, None))) as c:
        response = _upload(c, AUTH)
        assert response.status_code == 403
        assert response.json()["error"]["code"] == "read_only"
        assert "COMPLEMENTME_DATA_DIR" in response.json()["error"]["message"]


def test_short_or_empty_keys(artifacts: Path) -> None:
    with pytest.raises(ValidationError, match="at least 16 characters"):
        Settings.model_validate({"artifacts": artifacts, "api_key": "short"})
    assert Settings.model_validate({"artifacts": artifacts, "api_key": ""}).api_key is None
    assert KEY not in repr(Settings.model_validate({"artifacts": artifacts, "api_key": KEY}))


def test_openapi_declares_the_bearer_scheme(keyed: TestClient) -> None:
    doc = keyed.get("/openapi.json").json()
    assert doc["components"]["securitySchemes"]["ApiKey"] == {
        "type": "http", "scheme": "bearer", "description": "Catalog writes: `Authorization: Bearer "
        "<COMPLEMENTME_API_KEY>`."}
    assert doc["paths"]["/parts"]["post"]["security"] == [{"ApiKey": []}]
    assert "security" not in doc["paths"]["/parts"]["get"]


def test_cors_only_when_configured(artifacts: Path, keyed: TestClient) -> None:
    preflight = {"Origin": "https://app.example", "Access-Control-Request-Method": "POST"}
    assert "access-control-allow-origin" not in keyed.options("/suggest", headers=preflight).headers
    settings = writable_settings(artifacts, None, cors_origins=["https://app.example"])
    with TestClient(create_app(settings)) as c:
        answer = c.options("/suggest", headers=preflight)
        assert answer.headers["access-control-allow-origin"] == "https://app.example"
        other = c.options("/suggest", headers={**preflight, "Origin": "https://evil.example"})
        assert "access-control-allow-origin" not in other.headers
        # A refused preflight gets the service's JSON error body, not Starlette's plain text.
        assert other.status_code == 400
        error = other.json()["error"]
        assert error["code"] == "cors_refused" and "origin" in error["message"]
