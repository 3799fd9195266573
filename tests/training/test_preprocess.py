"""Tests of the Section 4 preprocessing: each merge rule, the contact graph, limits and outputs."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

from service.geometry.mesh import points_to_mesh_distance, sample_surface
from training.data.preprocess import (
    Kept,
    Merges,
    PreprocessConfig,
    Rejected,
    preprocess_folder,
    preprocess_shape,
)
from training.data.processed import ProcessedDataset, load_npz, save_npz_deterministic
from training.data.shapes import RawPiece, RawShape
from training.data.stats import HISTOGRAM_PNG, TABLE_TXT, write_stats

CONFIG = PreprocessConfig(points_per_component=256)
# Cached points are float16: coordinates below 1 round by at most 2.4e-4 each.
FLOAT16_TOL = 1e-3


def box(extents: tuple[float, float, float], centre: tuple[float, float, float], name: str,
        key: str | None = None, label: str | None = None) -> RawPiece:
    m = trimesh.creation.box(extents=extents)
    m.apply_translation(centre)
    return RawPiece(name, np.array(m.vertices), np.array(m.faces), key or name, label)


def seat() -> RawPiece:
    return box((1.0, 0.1, 1.0), (0, 0.5, 0), "seat", label="seat")


def back() -> RawPiece:
    return box((0.8, 0.8, 0.1), (0, 0.95, -0.45), "back", label="back")


def legs(keys: bool = True) -> list[RawPiece]:
    return [box((0.1, 0.45, 0.1), (x, 0.225, z), f"leg{i}", key="leg" if keys else None, label="leg")
            for i, (x, z) in enumerate([(-0.45, -0.45), (0.45, -0.45), (-0.45, 0.45), (0.45, 0.45)])]


def as_kept(result: Kept | Rejected) -> Kept:
    assert isinstance(result, Kept), result
    return result


def as_rejected(result: Kept | Rejected) -> Rejected:
    assert isinstance(result, Rejected), result
    return result


def vertices_by_label(result: Kept) -> dict[str, int]:
    return {str(label): len(v) for label, (v, _) in zip(result.labels, result.meshes, strict=True)}


def edges_by_label(result: Kept) -> set[tuple[str, ...]]:
    return {tuple(sorted((str(result.labels[i]), str(result.labels[j])))) for i, j in result.edges.tolist()}


def test_small_piece_merges_into_its_largest_neighbour() -> None:
    # A bolt at the seat/back joint touches both; the seat has the larger area.
    bolt = box((0.04, 0.04, 0.04), (0, 0.57, -0.42), "bolt", label="bolt")
    result = as_kept(preprocess_shape(RawShape("s", "chair", [seat(), back(), bolt]), CONFIG))
    assert result.merges == Merges(size=1, overlap=0, identical=0)
    assert vertices_by_label(result) == {"seat": 16, "back": 8}  # the bolt went to the seat
    assert edges_by_label(result) == {("back", "seat")}


@pytest.mark.parametrize("keys", [True, False])
def test_identical_legs_become_one_component(keys: bool) -> None:
    # Legs do not touch each other; with or without shared geometry keys they are one component.
    result = as_kept(preprocess_shape(RawShape("s", "chair", [seat(), back(), *legs(keys)]), CONFIG))
    assert result.merges.identical == 3
    assert vertices_by_label(result) == {"seat": 8, "back": 8, "leg": 32}
    # The legs' component touches the seat only, through the union of its members' edges.
    assert edges_by_label(result) == {("back", "seat"), ("leg", "seat")}


def test_different_pieces_are_not_grouped_as_identical() -> None:
    short_leg = box((0.1, 0.3, 0.1), (0.45, 0.3, 0.45), "short")
    result = as_kept(preprocess_shape(RawShape("s", "chair", [seat(), back(), legs()[0], short_leg]), CONFIG))
    assert result.merges.identical == 0
    assert result.n_components == 4


def test_overlapping_pieces_are_grouped() -> None:
    # A thin cushion lying on the seat: every cushion point is within tau_hausdorff of the seat.
    cushion = box((0.9, 0.03, 0.9), (0, 0.565, 0.02), "cushion", label="cushion")
    result = as_kept(preprocess_shape(RawShape("s", "chair", [seat(), back(), cushion]), CONFIG))
    assert result.merges == Merges(size=0, overlap=1, identical=0)
    # The majority label by area: the seat has more area than the cushion.
    assert vertices_by_label(result) == {"seat": 16, "back": 8}


def _pair_with_gap(gap: float) -> RawShape:
    a = box((1.0, 1.0, 1.0), (0, 0, 0), "a")
    b = box((0.6, 0.8, 0.7), (0.5 + 0.3 + gap, 0, 0), "b")
    return RawShape("pair", "thing", [a, b])


def test_contact_edges_follow_tau_proximity() -> None:
    whole = np.concatenate([p.vertices for p in _pair_with_gap(0.0).pieces])
    centre = (whole.min(axis=0) + whole.max(axis=0)) / 2
    radius = np.linalg.norm(whole - centre, axis=1).max()
    tau = CONFIG.tau_proximity
    near = as_kept(preprocess_shape(_pair_with_gap(0.7 * tau * radius), CONFIG))
    assert near.edges.tolist() == [[0, 1]]
    far = as_rejected(preprocess_shape(_pair_with_gap(1.5 * tau * radius), CONFIG))
    assert far.code == "disconnected" and far.n_components == 2


def test_distant_pieces_are_not_connected() -> None:
    shape = RawShape("s", "chair", [seat(), box((0.5, 0.5, 0.5), (3, 3, 3), "floating")])
    result = as_rejected(preprocess_shape(shape, CONFIG))
    assert result.code == "disconnected"
    assert "not connected" in result.reason


def test_component_count_limits() -> None:
    one = as_rejected(preprocess_shape(RawShape("s", "x", [seat()]), CONFIG))
    assert one.code == "too_few_components"
    # A row of touching boxes of distinct sizes: none is small, none identical, none overlapping.
    row = [box((0.5, 0.5 + 0.05 * i, 0.5), (0.5 * i, 0, 0), f"b{i}") for i in range(10)]
    many = as_rejected(preprocess_shape(RawShape("s", "x", row), CONFIG))
    assert many.code == "too_many_components" and many.n_components == 10


def test_piece_order_does_not_matter() -> None:
    pieces = [seat(), back(), *legs()]
    a = as_kept(preprocess_shape(RawShape("s", "chair", pieces), CONFIG))
    b = as_kept(preprocess_shape(RawShape("s", "chair", pieces[::-1]), CONFIG))
    assert np.array_equal(a.points, b.points) and np.array_equal(a.edges, b.edges)


def test_outputs_are_centred_meshes_with_surface_samples() -> None:
    result = as_kept(preprocess_shape(RawShape("s", "chair", [seat(), back(), *legs()]), CONFIG))
    assert result.points.shape == (3, 256, 3) and result.points.dtype == np.float16
    for k, (v, f) in enumerate(result.meshes):
        assert np.allclose((v.min(axis=0) + v.max(axis=0)) / 2, 0, atol=1e-6)
        dist = points_to_mesh_distance(result.points[k].astype(np.float64), v, f)
        assert dist.max() < FLOAT16_TOL
        assert result.area[k] == pytest.approx(trimesh.Trimesh(v, f, process=False).area, rel=1e-5)
    # Translations put the components back where they were in the unit-radius frame.
    meshes, translation = result.meshes, result.translation
    placed = np.concatenate([v + t for (v, _), t in zip(meshes, translation, strict=True)])
    assert np.linalg.norm(placed - (placed.min(axis=0) + placed.max(axis=0)) / 2, axis=1).max() == \
        pytest.approx(1.0, abs=1e-5)


def test_point_only_components_use_their_points() -> None:
    # A segmented point cloud: a seat slab and a back slab, no triangles.
    s, b = seat(), back()
    pieces = [RawPiece(p.name, sample_surface(p.vertices, p.faces, 600, seed=i).astype(np.float64),
                       np.zeros((0, 3), np.int64), p.name, p.name) for i, p in enumerate((s, b))]
    result = as_kept(preprocess_shape(RawShape("pc", "chair", pieces), CONFIG))
    assert result.edges.tolist() == [[0, 1]]
    assert result.points.shape == (2, 256, 3)
    assert result.area.tolist() == pytest.approx([0.5, 0.5])
    # The cached points are input points (in the normalised, centred frame).
    v, f = result.meshes[0]
    assert len(f) == 0 and len(v) == 600
    cached = result.points[0].astype(np.float64)
    assert np.linalg.norm(cached[:, None] - v[None], axis=-1).min(axis=1).max() < FLOAT16_TOL


# ---- folder runs ---------------------------------------------------------------------------


def write_obj(path: Path, pieces: list[RawPiece]) -> None:
    lines, offset = [], 1
    for p in pieces:
        lines.append(f"o {p.name}")
        lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in p.vertices.tolist()]
        lines += [f"f {a + offset} {b + offset} {c + offset}" for a, b, c in p.faces.tolist()]
        offset += len(p.vertices)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def make_raw_folder(root: Path) -> Path:
    rng = np.random.default_rng(0)
    for i in range(3):
        w = rng.uniform(0.8, 1.2)
        pieces = [box((w, 0.1, 1.0), (0, 0.5, 0), "seat"), box((w, 0.8, 0.1), (0, 0.95, -0.45), "back"),
                  *[box((0.1, 0.45, 0.1), (x * (w / 2 - 0.05), 0.225, z), f"leg{k}")
                    for k, (x, z) in enumerate([(-1, -0.45), (1, -0.45), (-1, 0.45), (1, 0.45)])]]
        write_obj(root / "chair" / f"c{i}.obj", pieces)
    write_obj(root / "table" / "t0.obj", [box((1.5, 0.05, 1), (0, 0.7, 0), "top"),
                                          box((0.1, 0.7, 0.1), (0, 0.35, 0), "stem")])
    write_obj(root / "table" / "single.obj", [box((1, 1, 1), (0, 0, 0), "block")])
    (root / "table" / "broken.obj").write_text("v 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    return root


@pytest.fixture(scope="module")
def raw_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_raw_folder(tmp_path_factory.mktemp("raw"))


def test_folder_output_is_byte_identical_across_runs_and_workers(raw_folder: Path, tmp_path: Path) -> None:
    ds = preprocess_folder(raw_folder, tmp_path / "a", CONFIG, workers=1)
    preprocess_folder(raw_folder, tmp_path / "b", CONFIG, workers=1)
    preprocess_folder(raw_folder, tmp_path / "c", CONFIG, workers=2)
    for name in ("arrays.npz", "dataset.json"):
        a = (tmp_path / "a" / name).read_bytes()
        assert a == (tmp_path / "b" / name).read_bytes()
        assert a == (tmp_path / "c" / name).read_bytes()
    loaded = ProcessedDataset.load(tmp_path / "a")
    assert loaded.content_hash() == ds.content_hash()
    # Sorted by category then id; the one-block and the NaN shapes are rejected with reasons.
    assert [(s["category"], s["shape_id"]) for s in loaded.shapes] == \
        [("chair", "c0"), ("chair", "c1"), ("chair", "c2"), ("table", "t0")]
    rejected = {r["shape_id"]: r for r in loaded.info["rejected"]}
    assert rejected["single"]["code"] == "too_few_components"
    assert rejected["broken"]["code"] == "unreadable" and "broken.obj" in rejected["broken"]["reason"]
    assert loaded.info["merge_counts"]["identical"] == 9  # three legs joined per chair
    assert loaded.info["counts"] == {"shapes_in": 6, "kept": 4, "rejected": 2, "pieces_in": 21,
                                     "components": 11}
    assert loaded.info["components_histogram"] == {"chair": {"3": 3}, "table": {"1": 1, "2": 1}}
    assert loaded.info["components_histogram_kept"] == {"chair": {"3": 3}, "table": {"2": 1}}


def test_seed_changes_samples_but_not_structure(raw_folder: Path, tmp_path: Path) -> None:
    a = preprocess_folder(raw_folder, tmp_path / "a", CONFIG, workers=1)
    b = preprocess_folder(raw_folder, tmp_path / "b", PreprocessConfig(points_per_component=256, seed=1),
                          workers=1)
    assert np.array_equal(a.edges, b.edges) and np.array_equal(a.first_comp, b.first_comp)
    assert not np.array_equal(a.points, b.points)


def test_stats_of_a_processed_folder(raw_folder: Path, tmp_path: Path) -> None:
    preprocess_folder(raw_folder, tmp_path / "processed", CONFIG, workers=1)
    summary = write_stats(tmp_path / "processed", tmp_path / "stats")
    assert (tmp_path / "stats" / HISTOGRAM_PNG).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = {r["category"]: r for r in summary["categories"]}
    assert rows["table"]["shapes"] == 3 and rows["table"]["kept"] == 1
    assert rows["table"]["discarded_by_reason"] == {"too_few_components": 1, "unreadable": 1}
    table = (tmp_path / "stats" / TABLE_TXT).read_text()
    assert "chair" in table and "too_few_components 1" in table and "identical 9" in table


def test_npz_files_are_byte_identical_and_lzma_members_read_back(tmp_path: Path) -> None:
    """A seeded pipeline rewrites its .npz files byte for byte; members written with LZMA (the
    export's mesh arrays) load with numpy like the deflated ones."""
    arrays = {"faces": np.arange(3000, dtype=np.uint16).reshape(-1, 3) % 7,
              "points": np.linspace(0, 1, 600, dtype=np.float32).reshape(-1, 3)}
    a, b = tmp_path / "a.npz", tmp_path / "b.npz"
    save_npz_deterministic(a, arrays, lzma=("faces",))
    save_npz_deterministic(b, arrays, lzma=("faces",))
    assert a.read_bytes() == b.read_bytes()
    with zipfile.ZipFile(a) as zf:
        kinds = {i.filename: i.compress_type for i in zf.infolist()}
    assert kinds == {"faces.npy": zipfile.ZIP_LZMA, "points.npy": zipfile.ZIP_DEFLATED}
    back = load_npz(a)
    for name, value in arrays.items():
        np.testing.assert_array_equal(back[name], value)
        assert back[name].dtype == value.dtype
