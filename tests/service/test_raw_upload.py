"""Mesh uploads sent as the request body (``service.api.mesh_upload``): the same answers as the
multipart form, the format from the media type or the query, and clear refusals."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import orjson
import pytest
import trimesh
from fastapi.testclient import TestClient
from service_testkit import make_settings

from service.api.app import create_app
from service.geometry.mesh import load_mesh_bytes

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "chair-without-legs.obj"
OPTIONS = {"/suggest/mesh": {"k": 4}, "/assemble/mesh": {"max_parts": 3}}


def _without_timings(answer: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in answer.items() if k != "timings"}


@pytest.mark.parametrize("path", sorted(OPTIONS))
def test_the_body_and_the_form_give_the_same_answer(client: TestClient, path: str) -> None:
    data = EXAMPLE.read_bytes()
    options = orjson.dumps(OPTIONS[path]).decode()
    form = client.post(path, files={"file": ("chair.obj", data)}, data={"options": options})
    raw = client.post(path, content=data, params={"options": options}, headers={"content-type": "model/obj"})
    assert form.status_code == raw.status_code == 200, raw.text
    assert _without_timings(raw.json()) == _without_timings(form.json())
    octets = client.post(path, content=data, params={"options": options, "format": "obj"},
                         headers={"content-type": "application/octet-stream"})
    assert _without_timings(octets.json()) == _without_timings(form.json()), "the format from the query"


def test_a_glb_body_is_read_by_its_media_type(client: TestClient) -> None:
    mesh = load_mesh_bytes(EXAMPLE.read_bytes(), "obj", max_vertices=10**6, max_faces=10**6)
    glb = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).export(file_type="glb")
    raw = client.post("/suggest/mesh", content=glb, headers={"content-type": "model/gltf-binary"},
                      params={"options": '{"k": 3}'})
    form = client.post("/suggest/mesh", files={"file": ("chair.glb", glb)}, data={"options": '{"k": 3}'})
    assert raw.status_code == 200 and _without_timings(raw.json()) == _without_timings(form.json())


_OBJ = {"content-type": "model/obj"}


@pytest.mark.parametrize(("request_args", "status", "code", "says"), [
    ({"headers": {"content-type": "application/octet-stream"}}, 415, "unsupported_format", "format query"),
    ({"headers": {"content-type": "text/plain"}, "params": {"format": "dwg"}}, 415, "unsupported_format",
     "dwg"),
    ({"headers": _OBJ, "params": {"options": '{"k": 0}'}}, 422, "k_out_of_range", ""),
    ({"headers": _OBJ, "params": {"options": '{"k": "x"}'}}, 422, "validation_error", "query.options.k"),
    ({"headers": _OBJ, "params": [("format", "obj"), ("format", "ply")]}, 422, "duplicate_field", "'format'"),
    ({"headers": {"content-type": "model/gltf-binary"}}, 422, "corrupt_mesh", "glTF"),
    ({"headers": {"content-type": "application/x-www-form-urlencoded"}}, 415, "unsupported_media_type",
     "Content-Type: model/obj"),
])
def test_a_bad_body_upload_is_refused_clearly(client: TestClient, request_args: dict[str, Any], status: int,
                                              code: str, says: str) -> None:
    response = client.post("/suggest/mesh", content=EXAMPLE.read_bytes(), **request_args)
    assert response.status_code == status, response.text
    error = response.json()["error"]
    assert error["code"] == code and says in error["message"], error


def test_an_empty_body_and_a_json_body_are_not_meshes(client: TestClient) -> None:
    empty = client.post("/suggest/mesh", content=b"", headers={"content-type": "model/obj"})
    assert empty.status_code == 422 and empty.json()["error"]["code"] == "empty_mesh"
    points = client.post("/suggest/mesh", json={"points": [[0, 0, 0]] * 20})
    assert points.status_code == 422
    assert "request body with its media type" in points.json()["error"]["message"]


def test_a_form_upload_takes_no_options_from_the_query(client: TestClient) -> None:
    response = client.post("/suggest/mesh", files={"file": ("chair.obj", EXAMPLE.read_bytes())},
                           params={"options": '{"k": 1}'})
    assert response.status_code == 422 and response.json()["error"]["code"] == "conflicting_fields"


def test_a_body_upload_is_held_to_the_upload_limit(artifacts: Path) -> None:
    data = EXAMPLE.read_bytes()
    with TestClient(create_app(make_settings(artifacts, max_upload_bytes=len(data) - 1))) as c:
        response = c.post("/suggest/mesh", content=data, headers={"content-type": "model/obj"})
        assert response.status_code == 413 and response.json()["error"]["code"] == "payload_too_large"
