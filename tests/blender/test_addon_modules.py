"""The add-on's bpy-free modules, outside Blender, checked against the service's own code.

The add-on cannot import the service (Python's standard library only), so these tests pin that
its GLB is what the service's mesh loader reads, its placement is the service's frame formula,
its OBJ reader reads the service's OBJ export, and its error text carries the service's message.
"""

from __future__ import annotations

import json
import sys
import threading
import urllib.parse
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, HTTPServer
from pathlib import Path

import numpy as np
import pytest
import trimesh

from service.geometry.frames import Frame
from service.geometry.mesh import load_mesh_bytes
from service.modeling.export_mesh import ExportItem, placed_meshes

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "clients" / "blender"))

from complementme_blender import geometry, service_client


def test_glb_is_read_by_the_service_loader_unchanged() -> None:
    rng = np.random.default_rng(0)
    vertices = rng.normal(size=(50, 3)).astype(np.float32)
    faces = rng.integers(0, 50, size=(80, 3))
    faces = faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])]
    glb = geometry.glb_bytes(vertices.ravel().tolist(), faces.ravel().tolist())

    mesh = load_mesh_bytes(glb, "glb", max_vertices=1000, max_faces=1000)

    # glTF is y up by convention, but the loader takes coordinates as they are: the request's
    # frame (up_axis "z") is what says Blender's z is up.
    np.testing.assert_allclose(mesh.vertices, vertices, atol=1e-6)
    np.testing.assert_array_equal(mesh.faces, faces)


class _OnePart:
    """Stands in for the catalog in ``placed_meshes``: one part with the given vertices."""

    def __init__(self, vertices: np.ndarray) -> None:
        self.vertices = vertices

    def lookup(self, part_id: str) -> int:
        return 0

    def mesh(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices, np.array([[0, 1, 0]])


@pytest.mark.parametrize("up_axis", ["y", "z"])
def test_placement_matrix_is_the_service_frame_formula(up_axis: str) -> None:
    frame = Frame(center=np.array([0.1, -2.0, 3.0]), radius=0.7, up_axis=up_axis)  # type: ignore[arg-type]
    answer_frame = {"scale": frame.radius, "rotation": frame.part_rotation.tolist()}
    v = np.array([[0.1, 0.2, 0.3], [-0.4, 0.5, -0.6]])
    t = [1.0, 2.0, 3.0]

    m = np.array(geometry.placement_matrix(answer_frame, t, (1.0, 1.0, 1.0)))
    placed = v @ m[:3, :3].T + m[:3, 3]

    np.testing.assert_allclose(placed, frame.radius * v @ frame.part_rotation.T + t)
    # A part's fitting scale is along the caller's axes, about its centre: what /export applies.
    m = np.array(geometry.placement_matrix(answer_frame, t, (2.0, 1.0, 0.5)))
    (_, mesh), = placed_meshes(_OnePart(v), [ExportItem("p", (1.0, 2.0, 3.0), (2.0, 1.0, 0.5))],
                               frame)
    np.testing.assert_allclose(v @ m[:3, :3].T + m[:3, 3], mesh.vertices)


def test_request_frame_modes() -> None:
    lo, hi = (-1.0, -2.0, 1.0), (1.0, 2.0, 3.0)
    ground = geometry.request_frame("GROUND", lo, hi)
    assert ground == {"center": [0.0, 0.0, 1.5], "radius": pytest.approx(np.sqrt(1 + 4 + 1.5 ** 2)),
                      "up_axis": "z"}
    whole = geometry.request_frame("SELECTION", lo, hi)
    assert whole["center"] == [0.0, 0.0, 2.0] and whole["radius"] == pytest.approx(np.sqrt(1 + 4 + 1))
    manual = geometry.request_frame("MANUAL", lo, hi, (1.0, 2.0, 3.0), 4.0)
    assert manual == {"center": [1.0, 2.0, 3.0], "radius": 4.0, "up_axis": "z"}
    with pytest.raises(ValueError, match="no extent"):
        geometry.request_frame("SELECTION", (1.0, 1.0, 1.0), (1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match="frame mode"):
        geometry.request_frame("AUTO", lo, hi)
    # FIT: only the up axis, and the request asks the service to fit the rest.
    assert geometry.frame_request("FIT", lo, hi) == {"frame": {"up_axis": "z"}, "fit_frame": True}
    assert geometry.frame_request("GROUND", lo, hi) == {"frame": ground}


def test_parse_obj_reads_the_service_obj_export() -> None:
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    text = box.export(file_type="obj")

    vertices, faces = geometry.parse_obj(text)

    np.testing.assert_allclose(vertices, box.vertices, atol=1e-6)
    np.testing.assert_array_equal(faces, box.faces)
    with pytest.raises(ValueError, match="out of range"):
        geometry.parse_obj("v 0 0 0\nv 1 0 0\nf 1 2 3\n")


def test_part_scale_defaults_to_one() -> None:
    assert geometry.part_scale({}) == (1.0, 1.0, 1.0)
    assert geometry.part_scale({"scale": [1.0, 2.0, 3.0]}) == (1.0, 2.0, 3.0)
    assert geometry.part_scale({"scale": 2}) == (2.0, 2.0, 2.0)


class _Handler(BaseHTTPRequestHandler):
    """Answers every POST with the service's error body for a 422, and keeps what it was sent."""

    def do_POST(self) -> None:
        body = self.rfile.read(int(self.headers["Content-Length"]))
        self.server.seen = (self.path, self.headers["Content-Type"], body)  # type: ignore[attr-defined]
        error = {"error": {"code": "validation_error", "message": "invalid request",
                           "details": [{"loc": ["body", "options", "k"], "message": "too big", "type": "x"}]}}
        data = json.dumps(error).encode()
        self.send_response(422)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def log_message(self, *args: object) -> None:
        pass


@pytest.fixture()
def error_server() -> Iterator[HTTPServer]:
    server = HTTPServer(("127.0.0.1", 0), _Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield server
    server.shutdown()
    server.server_close()


def test_client_sends_the_glb_as_the_body_and_reports_the_service_message(error_server: HTTPServer) -> None:
    client = service_client.Client(f"http://127.0.0.1:{error_server.server_address[1]}/", timeout=5)

    with pytest.raises(service_client.ServiceError) as err:
        client.suggest_mesh(b"GLBDATA", {"k": 500})

    assert str(err.value).endswith("422 validation_error: invalid request (body.options.k: too big)")
    path, content_type, body = error_server.seen  # type: ignore[attr-defined]
    route, _, query = path.partition("?")
    assert route == "/suggest/mesh" and content_type == "model/gltf-binary" and body == b"GLBDATA"
    assert urllib.parse.parse_qs(query) == {"options": ['{"k": 500}']}


def test_client_errors_are_one_line() -> None:
    with pytest.raises(service_client.ServiceError, match="must look like http://host:port"):
        service_client.Client("localhost:8000")
    text = service_client.http_error_message(502, b"<html>Bad gateway</html>")
    assert text == "HTTP 502: <html>Bad gateway</html>"
