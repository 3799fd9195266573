"""Every client error gets its status and a ``{"error": {"code", "message"}}`` body; never a 500.

The session's ``TestClient`` re-raises server exceptions, so an unhandled error fails the test
instead of hiding behind a 500.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from service_testkit import TEST_LIMITS, AssemblyQuery

from service.geometry.inputs import points_to_base64
from service.settings import Settings


def assert_error(response: Any, status: int, code: str) -> dict[str, Any]:
    assert response.status_code == status, response.text
    body = response.json()
    assert set(body) == {"error"}, body
    assert body["error"]["code"] == code, body
    assert isinstance(body["error"]["message"], str) and body["error"]["message"]
    assert response.headers["content-type"].startswith("application/json")
    return body["error"]


def post_raw(client: TestClient, path: str, text: str) -> Any:
    return client.post(path, content=text.encode(), headers={"content-type": "application/json"})


@pytest.fixture(scope="module")
def pts(query: AssemblyQuery) -> list[list[float]]:
    return query.points[:200].tolist()


def _cases(pts: list[list[float]]) -> list[tuple[str, dict[str, Any], int, str]]:
    b64 = points_to_base64(np.array(pts, np.float32))
    too_many = points_to_base64(np.zeros((TEST_LIMITS["max_points"] + 1, 3), np.float32))
    return [
        ("empty list", {"points": []}, 422, "empty_points"),
        ("empty base64", {"points_base64": ""}, 422, "empty_points"),
        ("no points at all", {"k": 3}, 422, "missing_points"),
        ("both encodings", {"points": pts, "points_base64": b64}, 422, "validation_error"),
        ("too few", {"points": pts[:3]}, 422, "too_few_points"),
        ("too many", {"points_base64": too_many}, 422, "too_many_points"),
        ("pairs", {"points": [p[:2] for p in pts]}, 422, "bad_shape"),
        ("ragged", {"points": [*pts, [1.0, 2.0]]}, 422, "bad_shape"),
        ("quads", {"points": [[*p, 1.0] for p in pts]}, 422, "bad_shape"),
        ("non-numeric", {"points": [["a", 1, 2], *pts]}, 422, "validation_error"),
        ("boolean coordinate", {"points": [*pts, [0.5, True, 0.5]]}, 422, "validation_error"),
        ("null coordinate", {"points": [*pts, [0.5, None, 0.5]]}, 422, "validation_error"),
        ("points is a string", {"points": "1 2 3"}, 422, "validation_error"),
        ("bad base64", {"points_base64": "****"}, 422, "invalid_base64"),
        ("base64 of 13 bytes", {"points_base64": "AAAAAAAAAAAAAAAAAA=="}, 422, "bad_shape"),
        ("k zero", {"points": pts, "k": 0}, 422, "k_out_of_range"),
        ("k too large", {"points": pts, "k": TEST_LIMITS["max_k"] + 1}, 422, "k_out_of_range"),
        ("k not a number", {"points": pts, "k": "five"}, 422, "validation_error"),
        ("unknown category", {"points": pts, "category": "spaceship"}, 422, "unknown_category"),
        ("unknown category in list", {"points": pts, "category": ["spaceship"]}, 422, "unknown_category"),
        ("unknown field", {"points": pts, "kk": 3}, 422, "validation_error"),
        ("zero radius", {"points": pts, "frame": {"radius": 0}}, 422, "validation_error"),
        ("bad up axis", {"points": pts, "frame": {"up_axis": "x"}}, 422, "validation_error"),
        ("short centre", {"points": pts, "frame": {"center": [0, 0]}}, 422, "validation_error"),
        ("unknown excluded part", {"points": pts, "exclude_parts": ["no-such/0"]}, 404, "unknown_part"),
        ("unknown excluded shape", {"points": pts, "exclude_shapes": ["no-such"]}, 404, "unknown_shape"),
        ("too many exclusions", {"points": pts, "exclude_shapes": ["s"] * (TEST_LIMITS["max_exclude"] + 1)},
         422, "too_many_exclusions"),
    ]


def test_suggest_refuses_bad_input(client: TestClient, pts: list[list[float]]) -> None:
    for name, body, status, code in _cases(pts):
        err = assert_error(client.post("/suggest", json=body), status, code)
        assert err["message"], name


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity"])
def test_non_finite_values(client: TestClient, pts: list[list[float]], literal: str) -> None:
    marked = [list(p) for p in pts]
    marked[5][1] = 12345.5
    text = json.dumps({"points": marked}).replace("12345.5", literal)
    err = assert_error(post_raw(client, "/suggest", text), 422, "non_finite_points")
    assert "point 5" in err["message"]


def test_non_finite_base64(client: TestClient, pts: list[list[float]]) -> None:
    arr = np.array(pts, np.float32)
    arr[7, 2] = np.nan
    response = client.post("/suggest", json={"points_base64": points_to_base64(arr)})
    assert "point 7" in assert_error(response, 422, "non_finite_points")["message"]


def test_validation_details_name_the_field(client: TestClient, pts: list[list[float]]) -> None:
    err = assert_error(client.post("/suggest", json={"points": pts, "k": "five"}), 422, "validation_error")
    assert err["details"][0]["loc"] == ["body", "k"]
    # Thousands of bad values list a bounded number of details.
    response = client.post("/suggest", json={"points": [["x", "y", "z"]] * 500})
    err = assert_error(response, 422, "validation_error")
    assert len(err["details"]) <= 10 and "1499 more values that are not numbers" in err["message"]


def test_not_json(client: TestClient) -> None:
    assert_error(post_raw(client, "/suggest", "{points: nope"), 400, "invalid_json")
    assert_error(post_raw(client, "/suggest", "[1, 2, 3]"), 422, "validation_error")
    assert_error(post_raw(client, "/suggest", ""), 422, "validation_error")


def test_body_too_large_by_content_length(client: TestClient, settings: Settings) -> None:
    body = b'{"points": [' + b" " * settings.max_body_bytes + b"]}"
    err = assert_error(client.post("/suggest", content=body, headers={"content-type": "application/json"}),
                       413, "payload_too_large")
    assert str(settings.max_body_bytes) in err["message"]


def test_body_too_large_while_reading(client: TestClient, settings: Settings) -> None:
    # A generator body goes out chunked, without Content-Length: the limit holds while reading.
    def chunks():
        yield b'{"points": ['
        for _ in range(settings.max_body_bytes // 65536 + 2):
            yield b" " * 65536
        yield b"]}"

    response = client.post("/suggest", content=chunks(), headers={"content-type": "application/json"})
    assert "content-length" not in {k.lower() for k in response.request.headers}
    assert_error(response, 413, "payload_too_large")


def test_place_errors(client: TestClient, pts: list[list[float]], catalog) -> None:
    pid = catalog.part_ids[0]
    assert_error(client.post("/place", json={"points": pts, "part_ids": ["no-such/1"]}), 404, "unknown_part")
    assert_error(client.post("/place", json={"points": pts, "part_ids": []}), 422, "no_parts")
    many = [pid] * (TEST_LIMITS["max_place_parts"] + 1)
    assert_error(client.post("/place", json={"points": pts, "part_ids": many}), 422, "too_many_parts")
    assert_error(client.post("/place", json={"points": pts}), 422, "validation_error")
    assert_error(client.post("/place", json={"points": pts[:2], "part_ids": [pid]}), 422, "too_few_points")


def test_batch_level_errors(client: TestClient, pts: list[list[float]]) -> None:
    assert_error(client.post("/suggest/batch", json={"items": []}), 422, "empty_batch")
    items = [{"points": pts[:20]}] * (TEST_LIMITS["max_batch_items"] + 1)
    assert_error(client.post("/suggest/batch", json={"items": items}), 422, "too_many_items")
    assert_error(client.post("/suggest/batch", json={"items": "all"}), 422, "validation_error")


def test_catalog_errors(client: TestClient) -> None:
    assert_error(client.get("/parts/no-such/3"), 404, "unknown_part")
    assert_error(client.get("/parts/no-such/3/mesh"), 404, "unknown_part")
    assert_error(client.get("/parts/no-such/3/points"), 404, "unknown_part")
    assert_error(client.get("/parts", params={"category": "spaceship"}), 422, "unknown_category")
    assert_error(client.get("/parts", params={"shape_id": "no-such"}), 404, "unknown_shape")
    too_long = TEST_LIMITS["max_page_size"] + 1
    assert_error(client.get("/parts", params={"limit": too_long}), 422, "limit_out_of_range")
    assert_error(client.get("/parts", params={"offset": -1}), 422, "validation_error")


def test_catalog_format_errors(client: TestClient, catalog) -> None:
    pid = catalog.part_ids[0]
    assert_error(client.get(f"/parts/{pid}/mesh", params={"format": "fbx"}), 422, "validation_error")
    assert_error(client.get(f"/parts/{pid}/points", params={"encoding": "hex"}), 422, "validation_error")


def test_routing_errors(client: TestClient) -> None:
    assert_error(client.get("/no-such-route"), 404, "not_found")
    assert_error(client.get("/suggest"), 405, "method_not_allowed")


def _upload(client: TestClient, name: str, data: bytes, **form: str) -> Any:
    return client.post("/suggest/mesh", files={"file": (name, data)}, data=form)


_BOX_OBJ = b"".join(f"v {x} {y} {z}\n".encode() for x in (0, 1) for y in (0, 1) for z in (0, 1)) + (
    b"f 1 2 4\nf 1 4 3\nf 5 7 8\nf 5 8 6\nf 1 5 6\nf 1 6 2\nf 3 4 8\nf 3 8 7\nf 1 3 7\nf 1 7 5\n"
    b"f 2 6 8\nf 2 8 4\n")


def test_mesh_upload_errors(client: TestClient, settings: Settings) -> None:
    assert _upload(client, "box.obj", _BOX_OBJ).status_code == 200
    assert_error(_upload(client, "box.fbx", _BOX_OBJ), 415, "unsupported_format")
    assert_error(_upload(client, "box", _BOX_OBJ), 415, "unsupported_format")
    assert_error(_upload(client, "box", _BOX_OBJ, format="3ds"), 415, "unsupported_format")
    assert_error(_upload(client, "box.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n"),
                 422, "corrupt_mesh")
    assert_error(_upload(client, "box.stl", b"\x00" * 40), 422, "corrupt_mesh")
    assert_error(_upload(client, "box.obj", b""), 422, "empty_mesh")
    assert_error(_upload(client, "line.obj", b"v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n"), 422, "zero_area")
    assert_error(_upload(client, "nan.obj", b"v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n"), 422, "non_finite")
    gltf = b'{"asset": {"version": "2.0"}, "buffers": [{"uri": "../secret.bin", "byteLength": 4}]}'
    assert_error(_upload(client, "x.gltf", gltf), 422, "external_reference")
    huge = f"ply\nformat ascii 1.0\nelement vertex {settings.max_mesh_vertices + 1}\nend_header\n".encode()
    assert_error(_upload(client, "huge.ply", huge), 413, "too_large")
    big = b"# " + b"x" * settings.max_upload_bytes + b"\n" + _BOX_OBJ
    assert_error(_upload(client, "big.obj", big), 413, "payload_too_large")


def test_mesh_upload_option_errors(client: TestClient) -> None:
    assert_error(_upload(client, "box.obj", _BOX_OBJ, options='{"k": 0}'), 422, "k_out_of_range")
    assert_error(_upload(client, "box.obj", _BOX_OBJ, options="k=3"), 400, "invalid_json")
    err = assert_error(_upload(client, "box.obj", _BOX_OBJ, options='{"kk": 3}'), 422, "validation_error")
    assert err["details"][0]["loc"] == ["body", "options", "kk"]
    # A multipart form without its file part; an urlencoded form cannot carry one at all.
    assert_error(client.post("/suggest/mesh", files={"options": (None, "{}")}), 422, "validation_error")
    assert_error(client.post("/suggest/mesh", data={"options": "{}"}), 415, "unsupported_media_type")
    assert_error(client.post("/suggest/mesh", json={"points": [[0, 0, 0]] * 20}), 422, "validation_error")
