"""Tests of service.geometry.mesh: safe loading of each format, refusals, sampling and frames."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest
import trimesh

from service.geometry.mesh import (
    MeshError,
    _prepare_obj,
    connected_components,
    load_mesh_bytes,
    load_scene_pieces,
    mesh_area,
    normalize_frame,
    points_to_mesh_distance,
    resample_points,
    sample_surface,
    triangle_areas,
)

LIMITS = {"max_vertices": 10_000, "max_faces": 20_000}


def _two_box_scene() -> trimesh.Scene:
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.creation.box(extents=(1, 1, 1)), node_name="seat",
                       geom_name="seat_mesh", transform=trimesh.transformations.translation_matrix((0, 0, 0)))
    scene.add_geometry(trimesh.creation.box(extents=(0.2, 0.2, 2)), node_name="post",
                       geom_name="post_mesh", transform=trimesh.transformations.translation_matrix((3, 0, 0)))
    return scene


def _two_box_mesh() -> trimesh.Trimesh:
    a = trimesh.creation.box(extents=(1, 1, 1))
    b = trimesh.creation.box(extents=(0.2, 0.2, 2))
    b.apply_translation((3, 0, 0))
    return trimesh.util.concatenate([a, b])


def _export(mesh_or_scene: trimesh.Trimesh | trimesh.Scene, file_type: str) -> bytes:
    if file_type == "gltf":
        scene = mesh_or_scene if isinstance(mesh_or_scene, trimesh.Scene) else trimesh.Scene(mesh_or_scene)
        files = trimesh.exchange.gltf.export_gltf(scene, embed_buffers=True)
        return files["model.gltf"]
    out = mesh_or_scene.export(file_type=file_type)
    return out.encode() if isinstance(out, str) else out


# ---- loading every format ------------------------------------------------------------------


@pytest.mark.parametrize("file_type", ["obj", "ply", "stl", "off", "glb", "gltf"])
def test_each_format_loads_with_the_right_area(file_type: str) -> None:
    source = _two_box_mesh()
    mesh = load_mesh_bytes(_export(source, file_type), file_type, name="two.x", **LIMITS)
    assert mesh.area == pytest.approx(source.area, rel=1e-5)
    assert np.allclose(mesh.bounds, source.bounds, atol=1e-5)


@pytest.mark.parametrize("file_type", ["ply", "stl", "off", "obj"])
def test_single_mesh_pieces_are_connected_components(file_type: str) -> None:
    pieces = load_scene_pieces(_export(_two_box_mesh(), file_type), file_type, **LIMITS)
    assert len(pieces) == 2
    areas = sorted(mesh_area(v, f) for _, v, f in pieces)
    assert areas == pytest.approx(sorted([6.0, 4 * 0.2 * 2 + 2 * 0.04]), rel=1e-5)


@pytest.mark.parametrize("file_type", ["glb", "gltf"])
def test_scene_pieces_are_leaves_in_world_frame(file_type: str) -> None:
    pieces = load_scene_pieces(_export(_two_box_scene(), file_type), file_type, **LIMITS)
    by_name = {name: v for name, v, _ in pieces}
    assert set(by_name) == {"seat", "post"}
    assert np.allclose(by_name["post"].mean(axis=0), (3, 0, 0), atol=1e-6)
    assert np.allclose(by_name["seat"].mean(axis=0), (0, 0, 0), atol=1e-6)


def test_scene_concatenates_in_world_frame() -> None:
    mesh = load_mesh_bytes(_export(_two_box_scene(), "glb"), "glb", **LIMITS)
    assert mesh.bounds[1, 0] == pytest.approx(3.1)


def test_connected_components_welds_split_corners() -> None:
    box = trimesh.creation.box()
    # STL-style: every triangle with its own three corners.
    v = box.vertices[box.faces].reshape(-1, 3)
    f = np.arange(len(v)).reshape(-1, 3)
    assert len(connected_components(v, f)) == 1


# ---- refusals ------------------------------------------------------------------------------


def test_gltf_with_local_file_buffer_is_refused(tmp_path) -> None:
    secret = tmp_path / "secret.bin"
    secret.write_bytes(b"\0" * 36)
    gltf = {
        "asset": {"version": "2.0"},
        "buffers": [{"uri": str(secret), "byteLength": 36}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                       "min": [0, 0, 0], "max": [0, 0, 0]}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}], "scene": 0,
    }
    with pytest.raises(MeshError) as err:
        load_mesh_bytes(json.dumps(gltf).encode(), "gltf", name="evil.gltf", **LIMITS)
    assert err.value.code == "external_reference"
    assert "evil.gltf" in str(err.value) and str(secret) in str(err.value)


def test_glb_with_external_image_is_refused() -> None:
    data = _export(_two_box_scene(), "glb")
    # Re-pack the JSON chunk with an image that points at a URL.
    (json_len,) = struct.unpack("<I", data[12:16])
    tree = json.loads(data[20:20 + json_len])
    tree["images"] = [{"uri": "http://example.invalid/texture.png"}]
    chunk = json.dumps(tree).encode()
    chunk += b" " * (-len(chunk) % 4)
    rest = data[20 + json_len:]
    body = struct.pack("<II", len(chunk), 0x4E4F534A) + chunk + rest
    glb = b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body
    with pytest.raises(MeshError) as err:
        load_mesh_bytes(glb, "glb", name="tex.glb", **LIMITS)
    assert err.value.code == "external_reference"
    assert "texture.png" in str(err.value)


def test_obj_material_library_is_refused_or_dropped() -> None:
    obj = b"mtllib ../../etc/passwd\nv 0 0 0\nv 1 0 0\nv 0 1 0\nusemtl red\nf 1 2 3\n"
    with pytest.raises(MeshError) as err:
        load_mesh_bytes(obj, "obj", name="m.obj", **LIMITS)
    assert err.value.code == "external_reference" and "etc/passwd" in str(err.value)
    mesh = load_mesh_bytes(obj, "obj", name="m.obj", ignore_obj_materials=True, **LIMITS)
    assert mesh.area == pytest.approx(0.5)


def test_ply_texture_file_is_refused() -> None:
    ply = _export(trimesh.creation.box(), "ply")
    ply = ply.replace(b"format", b"comment TextureFile ../secret.png\nformat", 1)
    with pytest.raises(MeshError) as err:
        load_mesh_bytes(ply, "ply", name="t.ply", **LIMITS)
    assert err.value.code == "external_reference" and "secret.png" in str(err.value)


@pytest.mark.parametrize("file_type,data", [
    ("ply", b"ply\nformat ascii 1.0\nelement vertex 999999999\nproperty float x\nend_header\n"),
    ("off", b"OFF\n999999999 1 0\n"),
    ("stl", b"\0" * 80 + struct.pack("<I", 10**9)),
    ("obj", b"v 0 0 0\n" * 10_001),
])
def test_declared_counts_over_the_limit_are_refused(file_type: str, data: bytes) -> None:
    with pytest.raises(MeshError) as err:
        load_mesh_bytes(data, file_type, name="big", **LIMITS)
    assert err.value.code == "too_large"
    assert "big" in str(err.value)


def test_binary_stl_over_face_limit_is_refused() -> None:
    mesh = trimesh.creation.icosphere(subdivisions=3)  # 1280 faces
    with pytest.raises(MeshError) as err:
        load_mesh_bytes(_export(mesh, "stl"), "stl", name="ico.stl", max_vertices=10**6, max_faces=1000)
    assert err.value.code == "too_large" and "1280" in str(err.value)


def test_gltf_accessor_counts_over_the_limit_are_refused() -> None:
    data = _export(trimesh.creation.icosphere(subdivisions=3), "glb")
    with pytest.raises(MeshError) as err:
        load_mesh_bytes(data, "glb", name="ico.glb", max_vertices=100, max_faces=10**6)
    assert err.value.code == "too_large"


def test_instancing_cannot_exceed_the_limits() -> None:
    scene = trimesh.Scene()
    box = trimesh.creation.box()
    for i in range(10):
        scene.add_geometry(box, geom_name="box", node_name=f"n{i}",
                           transform=trimesh.transformations.translation_matrix((i, 0, 0)))
    with pytest.raises(MeshError) as err:
        load_mesh_bytes(_export(scene, "glb"), "glb", max_vertices=50, max_faces=10**6)
    assert err.value.code == "too_large"


@pytest.mark.parametrize("file_type,data,code", [
    ("obj", b"", "empty_mesh"),
    ("obj", b"# nothing here\n", "empty_mesh"),
    ("glb", b"this is not a mesh at all", "corrupt_mesh"),
    ("gltf", b"{not json", "corrupt_mesh"),
    ("ply", b"\x00\x01garbage", "corrupt_mesh"),
    ("stl", b"hello world", "corrupt_mesh"),
    ("obj", b"v nan 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "non_finite"),
    ("obj", b"v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", "zero_area"),
    ("obj", b"v 0 0 0\nv 1 0 0\nv 0 1\nf 1 2 3\n", "corrupt_mesh"),  # a vertex of two numbers: was a 500
    ("ply", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
            b"property float z\nend_header\n0 0 0\n1 1 1\n", "empty_mesh"),
    ("fbx", b"whatever", "unsupported_format"),
])
def test_bad_input_gets_a_code_and_names_the_file(file_type: str, data: bytes, code: str) -> None:
    with pytest.raises(MeshError) as err:
        load_mesh_bytes(data, file_type, name="bad-file.x", **LIMITS)
    assert err.value.code == code
    assert "bad-file.x" in str(err.value)


# ---- sampling and frames -------------------------------------------------------------------


def test_samples_lie_on_the_surface_and_are_seeded() -> None:
    mesh = trimesh.creation.cylinder(radius=0.3, height=1.5, sections=24)
    pts = sample_surface(mesh.vertices, mesh.faces, 2000, seed=7)
    assert pts.shape == (2000, 3) and pts.dtype == np.float32
    assert points_to_mesh_distance(pts, mesh.vertices, mesh.faces).max() < 1e-4
    assert np.array_equal(pts, sample_surface(mesh.vertices, mesh.faces, 2000, seed=7))
    assert not np.array_equal(pts, sample_surface(mesh.vertices, mesh.faces, 2000, seed=8))


def test_samples_are_area_weighted() -> None:
    # Two disjoint triangles, the second with three times the area of the first.
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 0, 0], [8, 0, 0], [5, 1, 0]], float)
    f = np.array([[0, 1, 2], [3, 4, 5]])
    pts = sample_surface(v, f, 20_000, seed=0)
    assert (pts[:, 0] < 2).mean() == pytest.approx(0.25, abs=0.015)


def test_sampling_refuses_bad_meshes() -> None:
    with pytest.raises(MeshError) as err:
        sample_surface(np.zeros((3, 3)), np.array([[0, 1, 2]]), 10, seed=0)
    assert err.value.code == "zero_area"
    with pytest.raises(MeshError) as err:
        sample_surface(np.zeros((0, 3)), np.zeros((0, 3), int), 10, seed=0)
    assert err.value.code == "empty_mesh"


def test_normalize_frame_centres_the_box_and_scales_to_unit_radius() -> None:
    pts = np.array([[1, 2, 3], [3, 2, 3], [1, 6, 3], [2, 2, 5]], float)
    out, center, radius = normalize_frame(pts)
    assert np.allclose(center, (2, 4, 4))
    assert np.linalg.norm(out, axis=1).max() == pytest.approx(1.0)
    assert np.allclose(out * radius + center, pts)
    with pytest.raises(MeshError) as err:
        normalize_frame(np.ones((5, 3)))
    assert err.value.code == "degenerate"
    with pytest.raises(MeshError) as err:
        normalize_frame(np.array([[0, 0, np.inf]]))
    assert err.value.code == "non_finite"


def test_resample_points_gives_exactly_n_from_the_input() -> None:
    pts = np.random.default_rng(0).normal(size=(100, 3)).astype(np.float32)
    down = resample_points(pts, 30, seed=1)
    up = resample_points(pts, 250, seed=1)
    assert down.shape == (30, 3) and up.shape == (250, 3) and up.dtype == np.float32
    assert len(np.unique(down, axis=0)) == 30  # without replacement
    assert len(np.unique(up, axis=0)) == 100  # every input point kept
    rows = {tuple(p) for p in pts.tolist()}
    assert all(tuple(p) in rows for p in up.tolist())
    assert np.array_equal(down, resample_points(pts, 30, seed=1))


def test_point_to_mesh_distance_matches_the_box_distance() -> None:
    box = trimesh.creation.box(extents=(2, 2, 2))
    p = np.random.default_rng(0).normal(size=(400, 3)) * 2
    q = np.abs(p) - 1
    exact = np.where(q.max(axis=1) > 0, np.linalg.norm(np.maximum(q, 0), axis=1), -q.max(axis=1))
    assert np.allclose(points_to_mesh_distance(p, box.vertices, box.faces), exact, atol=1e-12)


def test_point_to_mesh_distance_is_below_any_sampled_distance() -> None:
    rng = np.random.default_rng(1)
    v = rng.normal(size=(3, 3))
    f = np.array([[0, 1, 2]])
    p = rng.normal(size=(50, 3)) * 3
    dense = sample_surface(v, f, 20_000, seed=2).astype(np.float64)
    sampled = np.linalg.norm(p[:, None] - dense[None], axis=-1).min(axis=1)
    exact = points_to_mesh_distance(p, v, f)
    assert (exact <= sampled + 1e-6).all()
    assert np.allclose(exact, sampled, atol=0.03)


@pytest.mark.parametrize(("text", "vertices", "faces", "groups"), [
    (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", 3, 1, 0),
    (b"v 0 0 0\r\nv 1 0 0\r\n  v 0 1 0\r\nf 1 2 3 4 5\r\n", 3, 3, 0),   # CRLF, indented, a pentagon
    (b"v 0 0 0\rv 1 0 0\rvt 0 0\rvn 0 0 1\r\tf\t1/1\x0b2/1 3/1\rg a\ro b", 2, 1, 2),  # CR, tabs, \x0b
    (b"vv 1\nf1 2 3\nv\nf\n# v 1 2 3\n\n   \n", 1, 1, 0),  # 'v' and 'f' alone count; 'vv', 'f1' do not
])
def test_obj_prescan_counts_lines_as_the_loader_splits_them(text: bytes, vertices: int, faces: int,
                                                            groups: int) -> None:
    """The OBJ pre-scan (numpy over the bytes) counts keywords per line as bytes.splitlines() and
    bytes.split() see them: every line ending, leading whitespace, polygons as k - 2 triangles."""
    _prepare_obj(text, "m.obj", vertices, faces, False, groups)
    for over in ({"max_vertices": vertices - 1}, {"max_faces": faces - 1}, {"max_nodes": groups - 1}):
        limits = {"max_vertices": vertices, "max_faces": faces, "max_nodes": groups, **over}
        if min(limits.values()) < 0:
            continue
        with pytest.raises(MeshError) as err:
            _prepare_obj(text, "m.obj", limits["max_vertices"], limits["max_faces"], False,
                         limits["max_nodes"])
        assert err.value.code == "too_large"


def test_obj_prescan_drops_only_material_lines() -> None:
    text = b"v 0 0 0\r\nusemtl red\r\nv 1 0 0\n mtllib a.mtl\nv 0 1 0\nf 1 2 3\nusemap x"
    kept = _prepare_obj(text, "m.obj", 3, 1, True)
    assert kept.splitlines() == [b"v 0 0 0", b"v 1 0 0", b"v 0 1 0", b"f 1 2 3"]
    with pytest.raises(MeshError, match=r"'csh x\.sh' refers to an external file"):
        _prepare_obj(b"v 0 0 0\n\tcsh\x0bx.sh \nmtllib b.mtl\n", "m.obj", 10, 10, True)


def test_box_iou_of_one_box_with_many() -> None:
    from service.geometry.boxes import box_iou

    lo, hi = np.zeros(3), np.ones(3)
    los = np.array([[0, 0, 0], [0.5, 0, 0], [2, 2, 2], [0, 0, 0]], dtype=np.float64)
    his = np.array([[1, 1, 1], [1.5, 1, 1], [3, 3, 3], [0.5, 1, 1]], dtype=np.float64)
    iou = box_iou(lo, hi, los, his)
    # The same box, half shifted (0.5 / 1.5), apart, half inside (0.5 / 1).
    assert np.allclose(iou, [1.0, 1 / 3, 0.0, 0.5])
    flat = box_iou(np.zeros(3), np.array([1.0, 1.0, 0.0]), np.zeros((1, 3)), np.array([[1.0, 1.0, 0.0]]))
    assert np.isnan(flat[0]) and not flat[0] > 0.25   # no volume: nothing to measure, never "stacked"


def test_triangle_areas_compiled_are_numpys_to_the_bit() -> None:
    """The compiled areas (every index in range) against the same sums in numpy (np.cross and
    np.linalg.norm), to the last bit; indices out of range keep numpy's error."""
    rng = np.random.default_rng(3)
    vertices = rng.normal(size=(500, 3)) * rng.uniform(1e-3, 1e3)
    faces = rng.integers(0, 500, size=(2000, 3))
    want = 0.5 * np.linalg.norm(np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                                          vertices[faces[:, 2]] - vertices[faces[:, 0]]), axis=1)
    assert np.array_equal(triangle_areas(vertices, faces), want)
    assert triangle_areas(vertices, np.zeros((0, 3), dtype=np.int64)).shape == (0,)
    with pytest.raises(IndexError):
        triangle_areas(vertices, np.array([[0, 1, 500]]))


def test_scaled_area_is_exact_for_a_uniform_scale_and_brackets_a_stretched_box() -> None:
    from service.geometry.scaling import scaled_area

    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    assert scaled_area(box.area, None) == pytest.approx(box.area)
    doubled = trimesh.creation.box(extents=(2.0, 2.0, 2.0)).area
    assert scaled_area(box.area, np.full(3, 2.0)) == pytest.approx(doubled)
    # A per-axis scale: the estimate keeps the volume change's uniform equivalent; a surface
    # stretched along one axis lies between the areas of the boxes scaled by the smallest and by
    # the largest factor.
    stretched = trimesh.creation.box(extents=(2.0, 1.0, 1.0)).area
    estimate = scaled_area(box.area, np.array([2.0, 1.0, 1.0]))
    assert box.area < estimate < doubled
    assert abs(estimate - stretched) / stretched < 0.1
