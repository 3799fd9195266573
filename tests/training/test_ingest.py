"""Tests of ingest: each accepted format, sidecars, refusals, and a folder run with bad files."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from service.geometry.mesh import mesh_area
from training.data.ingest import IngestConfig, ShapeFileError, ingest_folder, load_shape_file
from training.data.preprocess import PreprocessConfig, preprocess_folder


def _box(extents: tuple[float, float, float], centre: tuple[float, float, float]) -> trimesh.Trimesh:
    m = trimesh.creation.box(extents=extents)
    m.apply_translation(centre)
    return m


def _parts() -> dict[str, trimesh.Trimesh]:
    return {"seat": _box((1, 0.1, 1), (0, 0.5, 0)), "back": _box((0.9, 0.8, 0.1), (0, 0.95, -0.4)),
            "leg": _box((0.1, 0.45, 0.1), (0, 0.225, 0))}


def _scene() -> trimesh.Scene:
    scene = trimesh.Scene()
    for name, mesh in _parts().items():
        centre = mesh.bounds.mean(axis=0)
        local = mesh.copy()
        local.apply_translation(-centre)
        scene.add_geometry(local, node_name=name, geom_name=f"{name}_mesh",
                           transform=trimesh.transformations.translation_matrix(centre))
    return scene


def _joined() -> trimesh.Trimesh:
    return trimesh.util.concatenate(list(_parts().values()))


def _write(path: Path, data: bytes | str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    return path


def _obj_with_groups() -> str:
    lines, offset = [], 1
    for name, mesh in _parts().items():
        lines.append(f"g {name}")
        lines += [f"v {x} {y} {z}" for x, y, z in mesh.vertices.tolist()]
        lines += [f"f {a + offset} {b + offset} {c + offset}" for a, b, c in mesh.faces.tolist()]
        offset += len(mesh.vertices)
    return "\n".join(lines) + "\n"


def _areas(shape) -> list[float]:
    return sorted(round(mesh_area(p.vertices, p.faces), 6) for p in shape.pieces)


EXPECTED_AREAS = sorted(round(m.area, 6) for m in _parts().values())


def test_obj_groups_are_pieces(tmp_path: Path) -> None:
    shape = load_shape_file(_write(tmp_path / "chair" / "a.obj", _obj_with_groups()))
    assert shape.shape_id == "a" and shape.category == "chair"
    assert _areas(shape) == EXPECTED_AREAS
    assert len({p.name for p in shape.pieces}) == 3


@pytest.mark.parametrize("suffix", ["glb", "gltf"])
def test_gltf_scene_leaves_are_pieces_in_world_frame(tmp_path: Path, suffix: str) -> None:
    if suffix == "glb":
        data = _scene().export(file_type="glb")
    else:
        data = trimesh.exchange.gltf.export_gltf(_scene(), embed_buffers=True)["model.gltf"]
    shape = load_shape_file(_write(tmp_path / "chair" / f"b.{suffix}", data), category="seating")
    assert shape.category == "seating"  # an explicit category wins
    by_name = {p.name: p for p in shape.pieces}
    assert set(by_name) == {"seat", "back", "leg"}
    assert np.allclose(by_name["back"].vertices.mean(axis=0), (0, 0.95, -0.4))
    assert _areas(shape) == EXPECTED_AREAS


def test_sidecar_supplies_metadata(tmp_path: Path) -> None:
    glb = _write(tmp_path / "raw" / "x.glb", _scene().export(file_type="glb"))
    _write(glb.with_suffix(".json"), json.dumps({
        "shape_id": "chair-0007", "category": "chair", "style": "armless",
        "labels": {"seat": "seat", "leg": "leg"}, "geometry_keys": {"leg": "leg-geom"}}))
    shape = load_shape_file(glb)
    assert (shape.shape_id, shape.category, shape.style) == ("chair-0007", "chair", "armless")
    by_name = {p.name: p for p in shape.pieces}
    assert by_name["seat"].label == "seat" and by_name["back"].label is None
    assert by_name["leg"].geometry_key == "leg-geom"


def test_bad_sidecar_is_named(tmp_path: Path) -> None:
    glb = _write(tmp_path / "x.glb", _scene().export(file_type="glb"))
    _write(glb.with_suffix(".json"), '{"labels": [1, 2]}')
    with pytest.raises(ShapeFileError, match=r"x\.json.*labels"):
        load_shape_file(glb)


@pytest.mark.parametrize("suffix", ["ply", "off", "stl"])
def test_single_meshes_split_into_connected_components(tmp_path: Path, suffix: str) -> None:
    data = _joined().export(file_type=suffix)
    shape = load_shape_file(_write(tmp_path / "table" / f"m.{suffix}", data))
    assert shape.category == "table"
    assert _areas(shape) == EXPECTED_AREAS


def _pts_and_seg(folder: Path, stem: str, seg_folder: Path | None = None) -> Path:
    rng = np.random.default_rng(0)
    rows, seg = [], []
    for sid, mesh in enumerate(_parts().values(), start=1):
        pts, _ = trimesh.sample.sample_surface(mesh, 200, seed=int(rng.integers(1000)))
        rows += pts.tolist()
        seg += [sid] * len(pts)
    path = _write(folder / f"{stem}.pts", "".join(f"{x} {y} {z}\n" for x, y, z in rows))
    _write((seg_folder or folder) / f"{stem}.seg", "".join(f"{s}\n" for s in seg))
    return path


def test_segmented_point_cloud_pieces(tmp_path: Path) -> None:
    shape = load_shape_file(_pts_and_seg(tmp_path / "chair", "p1"))
    assert [p.name for p in shape.pieces] == ["segment_1", "segment_2", "segment_3"]
    assert [p.label for p in shape.pieces] == ["1", "2", "3"]
    assert all(p.faces.shape == (0, 3) and p.vertices.shape == (200, 3) for p in shape.pieces)


def test_part_benchmark_layout(tmp_path: Path) -> None:
    # <category>/points/<id>.pts with <category>/points_label/<id>.seg
    cat = tmp_path / "03001627"
    shape = load_shape_file(_pts_and_seg(cat / "points", "abc", seg_folder=cat / "points_label"))
    assert shape.category == "03001627" and len(shape.pieces) == 3


def test_point_cloud_without_segments_is_refused(tmp_path: Path) -> None:
    path = _write(tmp_path / "lone.pts", "0 0 0\n1 0 0\n")
    with pytest.raises(ShapeFileError, match=r"lone\.pts.*lone\.seg"):
        load_shape_file(path)


def test_segment_count_must_match(tmp_path: Path) -> None:
    path = _write(tmp_path / "p.pts", "0 0 0\n1 0 0\n0 1 0\n")
    _write(tmp_path / "p.seg", "1\n2\n")
    with pytest.raises(ShapeFileError, match=r"p\.seg.*2 segment ids for 3 points"):
        load_shape_file(path)


def test_gltf_referring_to_a_local_file_is_refused_without_reading_it(tmp_path: Path) -> None:
    secret = _write(tmp_path / "secret.bin", b"\0" * 36)
    gltf = {
        "asset": {"version": "2.0"},
        "buffers": [{"uri": "secret.bin", "byteLength": 36}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                       "min": [0, 0, 0], "max": [0, 0, 0]}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}], "scene": 0,
    }
    path = _write(tmp_path / "evil.gltf", json.dumps(gltf))
    # The file exists and holds valid data, so only the refusal (not a failed read) stops the load.
    assert secret.is_file()
    with pytest.raises(ShapeFileError) as err:
        load_shape_file(path)
    assert err.value.code == "external_reference"
    assert "evil.gltf" in str(err.value) and "secret.bin" in str(err.value)


def test_obj_material_library_is_refused_unless_ignored(tmp_path: Path) -> None:
    path = _write(tmp_path / "c" / "m.obj", "mtllib model.mtl\n" + _obj_with_groups())
    with pytest.raises(ShapeFileError, match=r"m\.obj.*mtllib model\.mtl"):
        load_shape_file(path)
    shape = load_shape_file(path, config=IngestConfig(ignore_obj_materials=True))
    assert len(shape.pieces) == 3


@pytest.mark.parametrize("name,data,words", [
    ("empty.obj", "", "empty"),
    ("nan.obj", "v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n", "NaN"),
    ("noise.glb", b"\x89PNG\r\n\x1a\n not a mesh", "not a GLB"),
    ("noise.stl", b"hello, I am a text file", "not an STL"),
    ("notes.fbx", b"whatever", "unsupported file type"),
])
def test_bad_files_get_clear_messages(tmp_path: Path, name: str, data: bytes | str, words: str) -> None:
    path = _write(tmp_path / name, data)
    with pytest.raises(ShapeFileError) as err:
        load_shape_file(path)
    assert str(path) in str(err.value) and words in str(err.value)


def test_file_size_limit(tmp_path: Path) -> None:
    path = _write(tmp_path / "a.obj", _obj_with_groups())
    with pytest.raises(ShapeFileError, match="more than the limit of 100"):
        load_shape_file(path, config=IngestConfig(max_file_bytes=100))


# ---- folder ingest -------------------------------------------------------------------------


@pytest.fixture
def src_folder(tmp_path: Path) -> Path:
    src = tmp_path / "src"
    _write(src / "chair" / "a.obj", _obj_with_groups())
    _write(src / "chair" / "b.glb", _scene().export(file_type="glb"))
    _write(src / "chair" / "deep" / "c.ply", _joined().export(file_type="ply"))
    _pts_and_seg(src / "chair", "pc")
    _write(src / "table" / "one.stl", _box((1, 1, 1), (0, 0, 0)).export(file_type="stl"))
    _write(src / "table" / "nan.obj", "v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    _write(src / "table" / "junk.off", "this is not an OFF file\n")
    _write(src / "table" / "empty.ply", b"")
    return src


def test_ingest_folder_writes_the_builtin_format_and_reports_skips(src_folder: Path, tmp_path: Path) -> None:
    out = tmp_path / "raw"
    report = ingest_folder(src_folder, out)
    written = {(w["category"], w["shape_id"]) for w in report.written}
    assert written == {("chair", "a"), ("chair", "b"), ("chair", "c"), ("chair", "pc")}
    skipped = {Path(s["file"]).name: s for s in report.skipped}
    assert set(skipped) == {"one.stl", "nan.obj", "junk.off", "empty.ply"}
    assert skipped["one.stl"]["code"] == "too_few_components"
    assert "1 component" in skipped["one.stl"]["reason"]
    assert skipped["nan.obj"]["code"] == "non_finite"
    assert skipped["junk.off"]["code"] == "corrupt_mesh"
    assert skipped["empty.ply"]["code"] == "empty_mesh"
    # Every written shape reads back with its pieces; meshes as GLB + sidecar.
    assert (out / "chair" / "a.glb").is_file() and (out / "chair" / "a.json").is_file()
    for w in report.written:
        back = load_shape_file(Path(w["path"]))
        assert back.category == "chair" and len(back.pieces) == w["pieces"] == 3
    saved = json.loads((out / "ingest_report.json").read_text())
    assert len(saved["written"]) == 4 and len(saved["skipped"]) == 4
    table = report.table()
    assert "4 written, 4 skipped" in table and "nan.obj" in table and "chair" in table


def test_ingested_folder_preprocesses(src_folder: Path, tmp_path: Path) -> None:
    ingest_folder(src_folder, tmp_path / "raw", category="seating")
    config = PreprocessConfig(points_per_component=64)
    ds = preprocess_folder(tmp_path / "raw", tmp_path / "processed", config, workers=1)
    assert ds.info["counts"]["shapes_in"] == 4
    assert {s["category"] for s in ds.shapes} == {"seating"}
    # The point cloud's segments keep their labels through ingest and preprocessing.
    pc = next(s for s in ds.shapes if s["shape_id"] == "pc")
    assert sorted(pc["labels"]) == ["1", "2", "3"]


def test_duplicate_stems_get_distinct_ids(tmp_path: Path) -> None:
    src = tmp_path / "src"
    for model in ("m1", "m2"):
        _write(src / "chair" / model / "models" / "model_normalized.obj", _obj_with_groups())
    report = ingest_folder(src, tmp_path / "raw")
    assert sorted(w["shape_id"] for w in report.written) == ["chair-m1-models-model_normalized",
                                                           "chair-m2-models-model_normalized"]
