"""The procedural shape generator and the GLB + sidecar writer.

Small counts only: every style is built a couple of times, a dataset of a few shapes is written.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from training.data.generator import CATEGORIES, generate_dataset, generate_shape, shape_id, style_of
from training.data.generator.mesh import Mesh
from training.data.generator.outlines import ccw, signed_area, triangulate
from training.data.generator.primitives import capsule, extrude, lathe, loft, sweep, torus
from training.data.shape_io import save_shape
from training.data.shapes import RawShape

REQUIRED_CATEGORIES = {"chair", "table", "sofa", "lamp", "airplane", "car", "guitar", "watercraft", "rifle"}
# ShapeNet part benchmark names where the category has them.
BENCHMARK_LABELS = {
    "airplane": {"body", "wing", "tail", "engine"},
    "car": {"body", "wheel", "hood", "roof"},
    "chair": {"back", "seat", "leg", "arm"},
    "guitar": {"head", "neck", "body"},
    "lamp": {"base", "shade", "bulb", "tube"},
    "table": {"top", "leg", "support"},
}
# (label, axis, label): mean coordinate of the first label's vertices is larger along the axis
# (0 = x, front; 1 = y, up). "*" stands for every label but the other one.
ORIENTATION = {
    "chair": [("seat", 1, "leg")],
    "table": [("top", 1, "leg")],
    "sofa": [("back", 1, "leg"), ("seat", 0, "back")],
    "lamp": [("shade", 1, "base")],
    "airplane": [("wing", 0, "tail"), ("body", 0, "tail")],
    "car": [("roof", 1, "wheel"), ("hood", 0, "roof")],
    "guitar": [("head", 1, "body"), ("neck", 0, "body")],
    "watercraft": [("*", 1, "hull")],
    "rifle": [("barrel", 0, "body"), ("barrel", 0, "stock"), ("body", 1, "trigger")],
}
STYLE_ORIENTATION = {
    ("lamp", "pendant"): [("base", 1, "shade")],
    ("chair", "straight"): [("seat", 1, "leg"), ("seat", 0, "back")],
    ("chair", "armchair"): [("seat", 1, "leg"), ("seat", 0, "back")],
    ("chair", "swivel"): [("seat", 1, "leg"), ("seat", 0, "back")],
    ("chair", "cantilever"): [("seat", 1, "leg"), ("seat", 0, "back")],
}
ALL_STYLES = [(c, s) for c, cat in CATEGORIES.items() for s in cat.styles]


def _index_of(category: str, style: str, k: int) -> int:
    """The k-th index whose shape has this style (styles cycle with the index)."""
    styles = list(CATEGORIES[category].styles)
    return k * len(styles) + styles.index(style)


def _closed(faces: np.ndarray) -> bool:
    """Every directed edge used once and its reverse once: closed and consistently oriented."""
    edges = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)
    directed = {tuple(e) for e in edges.tolist()}
    return len(directed) == len(edges) and all((b, a) in directed for a, b in directed)


def _mean(shape: RawShape, label: str, other: str) -> np.ndarray:
    pieces = [p for p in shape.pieces if (p.label == label if label != "*" else p.label != other)]
    assert pieces, f"{shape.shape_id}: no piece labelled {label!r}"
    return np.concatenate([p.vertices for p in pieces]).mean(axis=0)


def test_categories_and_styles_cover_the_spec():
    assert set(CATEGORIES) >= REQUIRED_CATEGORIES
    for name, cat in CATEGORIES.items():
        assert len(cat.styles) >= 3, name
        if name in BENCHMARK_LABELS:
            assert set(cat.labels) == BENCHMARK_LABELS[name]


@pytest.mark.parametrize(("category", "style"), ALL_STYLES)
def test_every_style_gives_valid_labelled_shapes_in_the_canonical_frame(category: str, style: str):
    for k in range(2):
        index = _index_of(category, style, k)
        shape = generate_shape(category, index, seed=3)
        assert shape.style == style == style_of(category, index)
        assert shape.shape_id == shape_id(category, index) == f"{category}-{index:04d}"
        assert shape.category == category
        names = [p.name for p in shape.pieces]
        assert len(set(names)) == len(names) >= 3
        allv = np.concatenate([p.vertices for p in shape.pieces])
        np.testing.assert_allclose((allv.min(axis=0) + allv.max(axis=0)) / 2, 0.0, atol=1e-9)
        assert abs(np.linalg.norm(allv, axis=1).max() - 1.0) < 1e-6
        labels = {p.label for p in shape.pieces}
        assert labels <= set(CATEGORIES[category].labels), labels
        assert sum(len(p.faces) for p in shape.pieces) < 6000
        for p in shape.pieces:
            assert p.vertices.dtype == np.float64 and p.faces.dtype == np.int64
            assert p.faces.min() >= 0 and p.faces.max() < len(p.vertices)
            tri = p.vertices[p.faces]
            area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
            assert area.min() > 1e-12, (shape.shape_id, p.name, p.label)
            assert _closed(p.faces), (shape.shape_id, p.name, p.label)
            assert Mesh(p.vertices, p.faces).signed_volume() > 0, (shape.shape_id, p.name)
        for a, axis, b in STYLE_ORIENTATION.get((category, style), ORIENTATION[category]):
            assert _mean(shape, a, b)[axis] > _mean(shape, b, a)[axis], (shape.shape_id, a, axis, b)


@pytest.mark.parametrize(("category", "style"), ALL_STYLES)
def test_repeated_pieces_are_rigid_copies_of_one_geometry(category: str, style: str):
    shape = generate_shape(category, _index_of(category, style, 0), seed=0)
    by_key: dict[str, list[np.ndarray]] = {}
    for p in shape.pieces:
        by_key.setdefault(p.geometry_key, []).append(p.vertices)
    for key, copies in by_key.items():
        ref = copies[0] - copies[0].mean(axis=0)
        for v in copies[1:]:
            # Same vertex count and pairwise distances: a rigid motion of the first copy.
            assert v.shape == copies[0].shape, key
            w = v - v.mean(axis=0)
            np.testing.assert_allclose(np.linalg.norm(w, axis=1), np.linalg.norm(ref, axis=1), atol=1e-9)
    assert any(len(c) > 1 for c in by_key.values()), f"{shape.shape_id} has no repeated piece"


def test_generation_is_deterministic_and_depends_on_the_seed():
    a, b = generate_shape("chair", 5, seed=11), generate_shape("chair", 5, seed=11)
    assert [p.name for p in a.pieces] == [p.name for p in b.pieces]
    for p, q in zip(a.pieces, b.pieces, strict=True):
        assert np.array_equal(p.vertices, q.vertices) and np.array_equal(p.faces, q.faces)
        assert (p.label, p.geometry_key) == (q.label, q.geometry_key)
    c = generate_shape("chair", 5, seed=12)
    d = generate_shape("chair", 6 + len(CATEGORIES["chair"].styles) - 1, seed=11)  # same style, next shape
    for other in (c, d):
        assert other.style == a.style
        differs = len(other.pieces) != len(a.pieces) or any(
            p.vertices.shape != q.vertices.shape or not np.allclose(p.vertices, q.vertices)
            for p, q in zip(a.pieces, other.pieces, strict=True))
        assert differs


def test_saved_files_are_byte_identical_for_the_same_seed(tmp_path: Path):
    for run in ("one", "two"):
        save_shape(generate_shape("car", 2, seed=4), tmp_path / run)
    save_shape(generate_shape("car", 2, seed=5), tmp_path / "other")
    for suffix in (".glb", ".json"):
        one = (tmp_path / "one" / f"car-0002{suffix}").read_bytes()
        assert one == (tmp_path / "two" / f"car-0002{suffix}").read_bytes()
    other = (tmp_path / "other" / "car-0002.glb").read_bytes()
    assert (tmp_path / "one" / "car-0002.glb").read_bytes() != other


def test_glb_and_sidecar_round_trip(tmp_path: Path):
    shape = generate_shape("airplane", 0, seed=0)
    path = save_shape(shape, tmp_path)
    assert path == tmp_path / "airplane-0000.glb"
    scene = trimesh.load(path, force="scene")
    assert isinstance(scene, trimesh.Scene)
    nodes = scene.graph.nodes_geometry
    assert sorted(nodes) == sorted(p.name for p in shape.pieces)
    for p in shape.pieces:
        transform, geom_name = scene.graph[p.name]
        mesh = scene.geometry[geom_name]
        assert np.array_equal(np.asarray(mesh.faces), p.faces)
        v = np.asarray(mesh.vertices) @ transform[:3, :3].T + transform[:3, 3]
        np.testing.assert_allclose(v, p.vertices, atol=1e-5)  # GLB stores float32 positions
    # Instances share one glTF mesh: fewer meshes than nodes when geometry repeats.
    keys = {p.geometry_key for p in shape.pieces}
    assert len(scene.geometry) == len(keys) < len(shape.pieces)
    meta = json.loads(path.with_suffix(".json").read_text())
    assert meta == {
        "shape_id": "airplane-0000", "category": "airplane", "style": shape.style,
        "labels": {p.name: p.label for p in shape.pieces},
        "geometry_keys": {p.name: p.geometry_key for p in shape.pieces},
    }


def test_save_shape_rejects_duplicate_piece_names(tmp_path: Path):
    shape = generate_shape("table", 1, seed=0)
    shape.pieces[1].name = shape.pieces[0].name
    with pytest.raises(ValueError, match="unique"):
        save_shape(shape, tmp_path)


def test_generate_dataset_layout_and_worker_independence(tmp_path: Path):
    cats = ["lamp", "guitar"]
    one = generate_dataset(tmp_path / "w1", seed=2, shapes_per_category=2, categories=cats, workers=1)
    two = generate_dataset(tmp_path / "w2", seed=2, shapes_per_category=2, categories=cats, workers=2)
    assert [p.relative_to(tmp_path / "w1") for p in one] == [
        Path("lamp/lamp-0000.glb"), Path("lamp/lamp-0001.glb"), Path("guitar/guitar-0000.glb"),
        Path("guitar/guitar-0001.glb")]
    for a, b in zip(one, two, strict=True):
        assert a.read_bytes() == b.read_bytes()
        assert a.with_suffix(".json").read_bytes() == b.with_suffix(".json").read_bytes()


def test_unknown_category_and_bad_arguments_are_refused(tmp_path: Path):
    with pytest.raises(ValueError, match="unknown category 'boat'"):
        generate_shape("boat", 0, seed=0)
    with pytest.raises(ValueError, match="unknown category 'boat'"):
        generate_dataset(tmp_path, categories=["chair", "boat"])
    with pytest.raises(ValueError, match="shapes_per_category"):
        generate_dataset(tmp_path, shapes_per_category=0)
    with pytest.raises(ValueError, match="seed"):
        generate_shape("chair", 0, seed=-1)


def test_cli_generate(tmp_path: Path):
    from training.cli import app

    runner = CliRunner()
    result = runner.invoke(app, ["data", "generate", "--out", str(tmp_path), "--seed", "1",
                                 "--shapes-per-category", "1", "--category", "sofa", "--workers", "1"])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (tmp_path / "sofa").iterdir()) == ["sofa-0000.glb", "sofa-0000.json"]
    bad = runner.invoke(app, ["data", "generate", "--out", str(tmp_path), "--category", "boat"])
    assert bad.exit_code == 2 and "unknown category boat" in bad.output


# ---- primitives -----------------------------------------------------------------------------

@pytest.mark.parametrize("mesh", [
    lathe(np.array([[0.3, 0.0], [0.2, 0.5], [0.25, 1.0]]), 12),
    capsule(1.0, 0.2),
    torus(1.0, 0.2),
    extrude(np.array([[0, 0], [2, 0], [2, 2], [1, 0.5], [0, 2]], float), 0.3, bevel=0.05),
    loft(np.array([[1, 0.1], [0, 0.1], [0, -0.1], [1, -0.1]], float)[::-1], np.linspace(-1, 1, 4),
         np.zeros((4, 2)), np.ones((4, 2)), axis="z"),  # a clockwise section
    sweep(np.array([[0.05, 0], [0, 0.05], [-0.05, 0], [0, -0.05]], float),
          np.array([[0, 0, 0], [0, 1, 0], [1, 1.2, 0], [1, 1.2, 1]], float)),
], ids=["lathe", "capsule", "torus", "extrude", "loft", "sweep"])
def test_primitives_are_closed_and_outward(mesh: Mesh):
    assert _closed(mesh.faces)
    assert mesh.signed_volume() > 0
    t = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    assert t.is_watertight and t.is_winding_consistent
    assert abs(t.volume - mesh.signed_volume()) < 1e-9


def test_triangulate_covers_a_non_convex_polygon_exactly():
    poly = ccw(np.array([[0, 0], [4, 0], [4, 3], [3, 3], [3, 1], [1, 1], [1, 3], [0, 3]], float))
    tris = triangulate(poly)
    p = poly[tris]
    area = 0.5 * ((p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1])
                  - (p[:, 1, 1] - p[:, 0, 1]) * (p[:, 2, 0] - p[:, 0, 0]))
    assert len(tris) == len(poly) - 2 and area.min() > 0
    assert area.sum() == pytest.approx(signed_area(poly))


def test_every_style_survives_preprocessing_with_3_to_8_connected_components():
    """The contract with Section 4's preprocessing: bolts and overlays merge away, repeated parts
    group, and what is left is a connected contact graph of 3..8 components."""
    from training.data.preprocess import Kept, PreprocessConfig, preprocess_shape

    config = PreprocessConfig(points_per_component=32)
    for category, style in ALL_STYLES:
        shape = generate_shape(category, _index_of(category, style, 0), seed=0)
        result = preprocess_shape(shape, config)
        assert isinstance(result, Kept), (shape.shape_id, style, result)
        assert 3 <= result.n_components <= 8, (shape.shape_id, style, result.n_components)
        assert None not in result.labels
