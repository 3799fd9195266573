"""Mesh uploads: structure limits checked before a scene is built, repeated form fields, the
upload limit on every mesh route, and memory that uploads leave behind."""

from __future__ import annotations

import os
import resource
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from service_testkit import TRIANGLE, glb, make_settings
from starlette.formparsers import MultiPartParser

from service.api.app import create_app
from service.geometry.mesh import MeshError, load_mesh_bytes
from service.settings import Settings


def triangle_tree(nodes: list[dict[str, Any]], roots: list[int]) -> dict[str, Any]:
    return {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": roots}], "nodes": nodes,
            "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
            "buffers": [{"byteLength": len(TRIANGLE)}],
            "bufferViews": [{"buffer": 0, "byteLength": len(TRIANGLE)}],
            "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                           "min": [0, 0, 0], "max": [0.2, 0.2, 0]}]}


def _bombs() -> dict[str, tuple[str, bytes]]:
    nested = b'{"asset":{"version":"2.0"},"extras":' + b"[" * 2000 + b"]" * 2000 + b"}"
    instanced = glb(triangle_tree([{"mesh": 0}] * 100_000, list(range(100_000))), TRIANGLE)
    chain = glb(triangle_tree([{"children": [i + 1]} for i in range(40_000)] + [{"mesh": 0}], [0]), TRIANGLE)
    cycle = glb(triangle_tree([{"children": [1]}, {"children": [0], "mesh": 0}], [0]), TRIANGLE)
    return {"nested": ("deep.gltf", nested), "instanced": ("many.glb", instanced),
            "chain": ("chain.glb", chain), "cycle": ("cycle.glb", cycle)}


# Each bomb is refused by the structure check made before any geometry is expanded (the
# message names that check), not by running out of vertices or time after expanding it.
BOMB_REFUSALS = {"nested": ("too_large", "nests 2001 deep"),
                 "instanced": ("too_large", "declares 100000 nodes"),
                 "chain": ("too_large", "declares 40001 nodes"),
                 "cycle": ("corrupt_mesh", "its own ancestor")}


@pytest.mark.parametrize("kind", sorted(BOMB_REFUSALS))
def test_gltf_structure_bombs_are_refused_before_expansion(client: TestClient, kind: str) -> None:
    name, data = _bombs()[kind]
    code, says = BOMB_REFUSALS[kind]
    for path in ("/suggest/mesh", "/assemble/mesh"):
        response = client.post(path, files={"file": (name, data)})
        assert response.status_code in (413, 422), response.text
        error = response.json()["error"]
        assert error["code"] == code and says in error["message"], error
    with pytest.raises(MeshError):  # the default limits apply to every caller (POST /parts too)
        load_mesh_bytes(data, name.rsplit(".", 1)[1], max_vertices=1000, max_faces=1000)


def test_a_scene_within_the_structure_limits_still_loads() -> None:
    nodes = [{"children": [i + 1]} for i in range(40)] + [{"mesh": 0, "translation": [1, 0, 0]}]
    mesh = load_mesh_bytes(glb(triangle_tree(nodes, [0]), TRIANGLE), "glb", max_vertices=1000, max_faces=1000)
    assert len(mesh.faces) == 1 and np.allclose(mesh.vertices[:, 0].min(), 1.0)
    shared = glb(triangle_tree([{"children": [1, 2]}, {"mesh": 0}, {"mesh": 0, "translation": [0, 0, 1]}],
                               [0]), TRIANGLE)
    assert len(load_mesh_bytes(shared, "glb", max_vertices=1000, max_faces=1000).faces) == 2


def test_many_obj_groups_are_refused_before_loading() -> None:
    obj = b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"g a\nf 1 2 3\n" * 50
    assert len(load_mesh_bytes(obj, "obj", max_vertices=100, max_faces=100, max_nodes=50).faces) == 50
    with pytest.raises(MeshError) as err:
        load_mesh_bytes(obj, "obj", max_vertices=100, max_faces=100, max_nodes=49)
    assert err.value.code == "too_large" and "groups" in err.value.message


CUBE_OBJ = (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nv 0 0 1\nv 1 0 1\nv 0 1 1\nv 1 1 1\n"
            b"f 1 3 2\nf 2 3 4\nf 5 6 7\nf 6 8 7\nf 1 2 5\nf 2 6 5\nf 3 7 4\nf 4 7 8\nf 1 5 3\nf 3 5 7\n"
            b"f 2 4 6\nf 4 8 6\n")


@pytest.mark.parametrize("path", ["/suggest/mesh", "/assemble/mesh"])
def test_a_repeated_form_field_is_refused(client: TestClient, path: str) -> None:
    files: list[tuple[str, Any]] = [("file", ("a.obj", CUBE_OBJ)), ("file", ("b.obj", CUBE_OBJ))]
    response = client.post(path, files=files)
    assert response.status_code == 422 and response.json()["error"]["code"] == "duplicate_field"
    response = client.post(path, files={"file": ("a.obj", CUBE_OBJ)},
                           data={"options": ['{"k": 1}', '{"k": 2}']})  # type: ignore[dict-item]
    assert response.status_code == 422 and response.json()["error"]["code"] == "duplicate_field"
    assert "'options'" in response.json()["error"]["message"]
    assert client.post(path, files={"file": ("a.obj", CUBE_OBJ)}).status_code == 200


def test_assemble_mesh_is_held_to_the_upload_limit(client: TestClient, settings: Any) -> None:
    # Over the JSON body limit, under the upload limit: read, not refused with 413.
    padding = b"# " + b"x" * (settings.max_body_bytes + 1000) + b"\n"
    assert settings.max_body_bytes < len(padding) < settings.max_upload_bytes
    response = client.post("/assemble/mesh", files={"file": ("a.obj", padding + CUBE_OBJ)},
                           data={"options": '{"max_parts": 1}'})
    assert response.status_code == 200, response.text
    response = client.post("/assemble/mesh", files={"file": ("a.obj", b"#" * settings.max_upload_bytes)})
    assert response.status_code == 413


# 18 MB uploads in the memory test: the acceptance's 200 do not fit the CI budget (see the test).
UPLOADS = int(os.environ.get("COMPLEMENTME_TEST_UPLOADS", "10"))


def _rss_mb() -> float:
    return int(Path("/proc/self/statm").read_text().split()[1]) * resource.getpagesize() / 2**20


def _big_obj(vertices: int = 600_000) -> bytes:
    """A triangle soup OBJ of 600k vertices and 200k faces (about 20 MB), like the issue's."""
    rng = np.random.default_rng(0)
    v = np.round(rng.random((vertices, 3)), 6)
    lines = [b"v %.6f %.6f %.6f" % tuple(row) for row in v.tolist()]
    lines += [b"f %d %d %d" % (i, i + 1, i + 2) for i in range(1, vertices, 3)]
    return b"\n".join(lines) + b"\n"


@pytest.fixture(scope="module")
def big_client(artifacts: Path) -> Iterator[TestClient]:
    settings = make_settings(artifacts, max_upload_bytes=64 * 2**20, max_mesh_vertices=2_000_000,
                             max_mesh_faces=2_000_000, request_timeout=120)
    with TestClient(create_app(settings)) as c:
        yield c


@pytest.mark.slow
def test_large_uploads_leave_memory_behind_no_more_than_150_mb(big_client: TestClient) -> None:
    """``UPLOADS`` uploads of an 18 MB OBJ (the acceptance: 200) keep RSS within 150 MB of where it
    started, after every one of them. Before the fix each left about 60 MB behind.

    Each upload costs about 4 s (the OBJ parse), so the acceptance's 200 take about 13 minutes:
    more than half of the suite's CI budget. CI runs 10, which would have grown RSS by 600 MB before the
    fix; ``COMPLEMENTME_TEST_UPLOADS=200`` runs the acceptance's count (docs/performance.md,
    "Memory under repeated uploads", has that run's figures).
    """
    obj = _big_obj()
    assert len(obj) > 18e6
    assert big_client.post("/suggest/mesh", files={"file": ("big.obj", obj)}).status_code == 200
    start = _rss_mb()
    after: list[float] = []
    for i in range(UPLOADS):
        t = time.monotonic()
        response = big_client.post("/suggest/mesh", files={"file": ("big.obj", obj)})
        assert response.status_code == 200, response.text
        after.append(_rss_mb())
        print(f"upload {i + 1}/{UPLOADS}: {time.monotonic() - t:.1f} s, RSS {after[-1]:.0f} MB", flush=True)
    print(f"RSS: {start:.0f} MB after the first upload, at most {max(after):.0f} MB over {UPLOADS} more, "
          f"{after[-1]:.0f} MB at the end")
    assert max(after) - start < 150, f"RSS grew from {start:.0f} MB to {max(after):.0f} MB"
    assert "process_resident_memory_bytes" in big_client.get("/metrics").text


def test_an_upload_spilled_to_disk_is_answered_as_one_kept_in_memory(artifacts: Path) -> None:
    """``upload_memory_bytes`` only decides where a form's file waits while it is received: the
    example upload gets the same answer spilled to a temporary file (a bound of 1 byte; Python's
    spooled file never spills at 0) and kept in memory."""
    obj = (Path(__file__).resolve().parents[2] / "examples" / "chair-without-legs.obj").read_bytes()
    answers = {}
    try:
        for bound in (1, len(obj) + 4096):
            with TestClient(create_app(make_settings(artifacts, upload_memory_bytes=bound))) as c:
                assert MultiPartParser.spool_max_size == bound
                response = c.post("/suggest/mesh", files={"file": ("chair.obj", obj)},
                                  data={"options": '{"k": 5, "fit_frame": false}'})
                assert response.status_code == 200, response.text
                answers[bound] = [(s["part_id"], s["translation"]) for s in response.json()["suggestions"]]
    finally:
        MultiPartParser.spool_max_size = Settings().upload_memory_bytes
    first, second = answers.values()
    assert first == second and len(first) == 5


def test_catalog_uploads_take_the_structure_limits_from_the_settings(artifacts: Path, tmp_path: Path) -> None:
    """POST /parts is held to max_mesh_nodes as configured, not only to the built-in default."""
    from catalog_testkit import AUTH, writable_settings

    chain = glb(triangle_tree([{"children": [i + 1]} for i in range(30)] + [{"mesh": 0}], [0]), TRIANGLE)
    for limit, refused in ((8, True), (10_000, False)):
        settings = writable_settings(artifacts, tmp_path / f"data-{limit}", max_mesh_nodes=limit)
        with TestClient(create_app(settings)) as c:
            r = c.post("/parts", files={"file": ("chain.glb", chain)}, data={"category": "chair"},
                       headers=AUTH)
        if refused:
            assert r.status_code == 413 and r.json()["error"]["code"] == "too_large", r.text
        else:
            assert r.json().get("error", {}).get("code") != "too_large", r.text
