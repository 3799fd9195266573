"""Hostile uploads get clean 4xx answers, read nothing outside the upload, and stay small in memory.

Every case goes to both mesh endpoints: ``POST /parts`` (refuses external references) and
``POST /suggest/mesh`` (drops OBJ material lines, refuses the rest). A canary file sits where a
followed reference would land; every ``open`` of the process is watched for it.
"""

from __future__ import annotations

import base64
import builtins
import contextlib
import gzip
import io
import json
import os
import resource
import tracemalloc
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from catalog_testkit import AUTH, writable_settings
from fastapi.testclient import TestClient
from service_testkit import TRIANGLE, glb

from service.api.app import create_app

CANARY_TEXT = b"CANARY-7f3a9c-never-to-be-read"


def triangle_tree(buffer: dict[str, Any] | None = None, **extra: Any) -> dict[str, Any]:
    tree: dict[str, Any] = {
        "asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "buffers": [buffer or {"byteLength": len(TRIANGLE)}],
        "bufferViews": [{"buffer": 0, "byteLength": len(TRIANGLE)}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                       "min": [0, 0, 0], "max": [0.2, 0.2, 0]}]}
    tree.update(extra)
    return tree


@pytest.fixture(scope="module")
def app_client(artifacts: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    with TestClient(create_app(writable_settings(artifacts, tmp_path_factory.mktemp("data")))) as c:
        yield c


@pytest.fixture()
def canary(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[dict[str, Any]]:
    """A canary file beside the working directory, and a record of every attempt to open it."""
    path = tmp_path / "canary.bin"
    path.write_bytes(CANARY_TEXT)
    (tmp_path / "canary.mtl").write_bytes(b"newmtl x\nmap_Kd canary.bin\n" + CANARY_TEXT)
    monkeypatch.chdir(tmp_path)
    opened: list[str] = []
    real_open, real_os_open = builtins.open, os.open

    def spy_open(file: Any, *args: Any, **kwargs: Any) -> Any:
        if "canary" in str(file):
            opened.append(str(file))
        return real_open(file, *args, **kwargs)

    def spy_os_open(file: Any, *args: Any, **kwargs: Any) -> Any:
        if "canary" in str(file):
            opened.append(str(file))
        return real_os_open(file, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", spy_open)
    monkeypatch.setattr(io, "open", spy_open)
    monkeypatch.setattr(os, "open", spy_os_open)
    yield {"path": path, "opened": opened}
    assert not opened, f"a hostile file made the service open {opened}"


def _both(client: TestClient, name: str, data: bytes) -> list[Any]:
    """The upload sent to POST /parts and to POST /suggest/mesh."""
    return [client.post("/parts", files={"file": (name, data)}, data={"category": "hostile"}, headers=AUTH),
            client.post("/suggest/mesh", files={"file": (name, data)})]


def _gzip_bomb(expanded: int) -> bytes:
    """A gzip stream of ``expanded`` zero bytes, from repeated members (cheap to make)."""
    member = gzip.compress(b"\0" * (1 << 24), compresslevel=9)
    return member * (expanded >> 24)


def _hostile_files(canary_path: Path) -> list[tuple[str, bytes, set[int], str]]:
    """(file name, bytes, statuses accepted from /parts, error code from /parts)."""
    abs_uri, rel_uri, file_uri = str(canary_path), "canary.bin", canary_path.as_uri()
    rng = np.random.default_rng(0)
    cases: list[tuple[str, bytes, set[int], str]] = []
    for uri in (abs_uri, rel_uri, file_uri, "http://127.0.0.1:9/canary.bin", "../canary.bin"):
        tree = triangle_tree({"byteLength": len(TRIANGLE), "uri": uri})
        cases.append(("ref.gltf", json.dumps(tree).encode(), {422}, "external_reference"))
    image = triangle_tree(images=[{"uri": rel_uri}], textures=[{"source": 0}])
    cases.append(("image.glb", glb(image, TRIANGLE), {422}, "external_reference"))
    obj = b"mtllib ../canary.mtl\nusemtl x\nv 0 0 0\nv 0.2 0 0\nv 0 0.2 0\nf 1 2 3\n"
    cases.append(("material.obj", obj, {422}, "external_reference"))
    obj_abs = f"mtllib {canary_path.with_suffix('.mtl')}\nv 0 0 0\nv 0.2 0 0\nv 0 0.2 0\nf 1 2 3\n".encode()
    cases.append(("material_abs.obj", obj_abs, {422}, "external_reference"))
    ply_texture = (b"ply\nformat ascii 1.0\ncomment TextureFile canary.bin\nelement vertex 3\n"
                   b"property float x\nproperty float y\nproperty float z\nelement face 1\n"
                   b"property list uchar int vertex_indices\nend_header\n0 0 0\n0.2 0 0\n0 0.2 0\n3 0 1 2\n")
    cases.append(("texture.ply", ply_texture, {422}, "external_reference"))
    ply_huge = (b"ply\nformat binary_little_endian 1.0\nelement vertex 1000000000000\nproperty float x\n"
                b"property float y\nproperty float z\nend_header\n" + TRIANGLE)
    cases.append(("huge.ply", ply_huge, {413}, "too_large"))
    ply_edges = (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
                 b"property float y\nproperty float z\nelement edge 1000000000000\nproperty int a\n"
                 b"property int b\nend_header\n" + TRIANGLE)
    cases.append(("edges.ply", ply_edges, {422}, "corrupt_mesh"))
    cases.append(("huge.off", b"OFF\n1000000000000 1 0\n0 0 0\n", {413}, "too_large"))
    zero_filled = triangle_tree()
    zero_filled["accessors"].append({"componentType": 5126, "count": 10**9, "type": "MAT4"})
    zero_filled["meshes"][0]["primitives"][0]["attributes"]["NORMAL"] = 1
    cases.append(("zeros.glb", glb(zero_filled, TRIANGLE), {413}, "too_large"))
    shared = triangle_tree()  # many accessors over one view: each within the limit, 1 GB together
    big_view = 12 * 90_000
    shared["bufferViews"] = [{"buffer": 0, "byteLength": big_view}]
    shared["buffers"] = [{"byteLength": big_view}]
    shared["accessors"] = [{"bufferView": 0, "componentType": 5126, "count": 90_000, "type": "VEC3"}] * 1000
    cases.append(("shared.glb", glb(shared, bytes(big_view)), {413}, "too_large"))
    cases.append(("buffer.glb", glb(triangle_tree({"byteLength": 10**12}), TRIANGLE), {422}, "corrupt_mesh"))
    draco = triangle_tree(extensionsUsed=["KHR_draco_mesh_compression"],
                          extensionsRequired=["KHR_draco_mesh_compression"])
    # 10^8 positions: 1.2 GB once decoded, from a file of a few hundred bytes.
    draco["accessors"][0] = {"componentType": 5126, "count": 100_000_000, "type": "VEC3"}
    draco["meshes"][0]["primitives"][0]["extensions"] = {
        "KHR_draco_mesh_compression": {"bufferView": 0, "attributes": {"POSITION": 0}}}
    cases.append(("draco.glb", glb(draco, TRIANGLE), {415}, "unsupported_format"))
    meshopt = triangle_tree(extensionsRequired=["EXT_meshopt_compression"])
    cases.append(("meshopt.glb", glb(meshopt, TRIANGLE), {415}, "unsupported_format"))
    bomb = _gzip_bomb(1 << 30)
    cases.append(("bomb.glb", bomb, {422}, "corrupt_mesh"))
    for ext in ("obj", "ply", "stl", "off", "glb", "gltf"):
        noise = rng.integers(0, 256, size=4096, dtype=np.uint8).tobytes()
        cases.append((f"noise.{ext}", noise, {413, 422}, ""))
    return cases


def test_hostile_files_get_clean_4xx(app_client: TestClient, canary: dict[str, Any]) -> None:
    cases = _hostile_files(canary["path"])
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    tracemalloc.start()
    try:
        for name, data, statuses, code in cases:
            parts, suggest = _both(app_client, name, data)
            assert parts.status_code in statuses, (name, parts.text)
            assert set(parts.json()) == {"error"}, name
            assert not code or parts.json()["error"]["code"] == code, (name, parts.text)
            if code == "external_reference":
                assert "canary" in parts.json()["error"]["message"], "the error names the reference"
            if name.startswith("material"):  # /suggest/mesh drops material lines instead
                assert suggest.status_code == 200, (name, suggest.text)
            else:
                assert 400 <= suggest.status_code < 500, (name, suggest.text)
            for response in (parts, suggest):
                assert CANARY_TEXT not in response.content
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    rss_growth_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss_before) / 1024
    # Loose bounds: the largest legitimate allocation here is a few MB per request.
    assert peak < 200 * 2**20, f"peak traced allocation {peak / 2**20:.0f} MB"
    assert rss_growth_mb < 400, f"peak RSS grew by {rss_growth_mb:.0f} MB"
    assert app_client.get("/catalog").json()["added_parts"] == 0


def test_a_compressed_request_body_is_not_inflated(app_client: TestClient) -> None:
    """Content-Encoding is not honoured for requests: a 1 GB gzip body stays 1 MB of noise."""
    bomb = _gzip_bomb(1 << 30)
    headers = {**AUTH, "Content-Encoding": "gzip", "Content-Type": "multipart/form-data; boundary=x"}
    response = app_client.post("/parts", content=bomb, headers=headers)
    assert 400 <= response.status_code < 500 and set(response.json()) == {"error"}
    response = app_client.post("/suggest", content=bomb, headers={"Content-Encoding": "gzip",
                                                                 "Content-Type": "application/json"})
    assert response.status_code in (400, 413)


def test_self_contained_gltf_is_accepted(app_client: TestClient, canary: dict[str, Any]) -> None:
    """The positive control: embedded data: URIs are fine, and materials are simply dropped."""
    data_uri = "data:application/octet-stream;base64," + base64.b64encode(TRIANGLE).decode()
    tree = triangle_tree({"byteLength": len(TRIANGLE), "uri": data_uri},
                         materials=[{"pbrMetallicRoughness": {"baseColorFactor": [1, 0, 0, 1]}}])
    tree["meshes"][0]["primitives"][0]["material"] = 0
    response = app_client.post("/parts", files={"file": ("ok.gltf", json.dumps(tree).encode())},
                               data={"category": "hostile-control"}, headers=AUTH)
    assert response.status_code == 201, response.text
    assert response.json()["n_faces"] == 1
    assert app_client.delete(f"/parts/{response.json()['part_id']}", headers=AUTH).status_code == 204


def test_the_canary_watch_sees_a_followed_reference(canary: dict[str, Any]) -> None:
    """Proof that the watch works: trimesh left to itself does read the canary."""
    import trimesh

    tree = triangle_tree({"byteLength": len(TRIANGLE), "uri": "canary.bin"})
    (canary["path"].parent / "ref.gltf").write_text(json.dumps(tree))
    with contextlib.suppress(Exception):  # the canary is no valid buffer; it was opened all the same
        trimesh.load_scene(str(canary["path"].parent / "ref.gltf"))
    assert any("canary.bin" in p for p in canary["opened"])
    canary["opened"].clear()
