"""ONNX parity of every exported graph, and the exported artifact folder (catalog, index, manifest)."""

from __future__ import annotations

import json
from pathlib import Path

import faiss
import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from service.artifacts.layout import (
    CATALOG_ARRAYS,
    CATALOG_FIELDS,
    CATALOG_JSON,
    GRAPH_FILES,
    GRAPH_INPUTS,
    GRAPH_OUTPUTS,
    INDEX_FILE,
    MANIFEST,
    read_manifest,
)
from training.catalog import find_duplicates, sample_parts
from training.checkpoint import load_trained
from training.export import ExportOptions, export_graphs, export_run, graph_modules
from training.split import load_split


@pytest.fixture(scope="module")
def graphs(tiny_run: Path, tmp_path_factory: pytest.TempPathFactory):
    trained = load_trained(tiny_run)
    folder = tmp_path_factory.mktemp("graphs")
    export_graphs(trained.pair, trained.placement, folder)
    return trained, folder


def _session(path: Path) -> ort.InferenceSession:
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])


def _inputs(graph: str, trained, batch: int, n: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    if graph == "h_head":
        qf = rng.normal(size=(batch, trained.placement.query_dim))
        pf = np.abs(rng.normal(size=(batch, trained.placement.part_dim)))
        return {"query_feature": qf.astype(np.float32), "part_feature": pf.astype(np.float32)}
    return {"points": rng.uniform(-1, 1, size=(batch, n, 3)).astype(np.float32)}


@pytest.mark.parametrize("graph", list(GRAPH_FILES))
@pytest.mark.parametrize(("batch", "n"), [(1, 100), (5, 700)])
def test_onnx_matches_torch(graphs, graph: str, batch: int, n: int):
    trained, folder = graphs
    module = graph_modules(trained.pair, trained.placement)[graph].eval()
    feeds = _inputs(graph, trained, batch, n, np.random.default_rng(batch * 1000 + n))
    got = _session(folder / GRAPH_FILES[graph]).run(GRAPH_OUTPUTS[graph], feeds)
    with torch.no_grad():
        want = module(*(torch.from_numpy(feeds[name]) for name in GRAPH_INPUTS[graph]))
    want = want if isinstance(want, tuple) else (want,)
    assert len(got) == len(want)
    for g, w in zip(got, want, strict=True):
        assert g.shape == tuple(w.shape)
        assert np.abs(g - w.numpy()).max() < 1e-4


def test_graph_names_and_dynamic_axes(graphs):
    _, folder = graphs
    for graph, name in GRAPH_FILES.items():
        model = onnx.load(str(folder / name))
        onnx.checker.check_model(model)
        assert [i.name for i in model.graph.input] == GRAPH_INPUTS[graph]
        assert [o.name for o in model.graph.output] == GRAPH_OUTPUTS[graph]
        for i in model.graph.input:
            assert i.type.tensor_type.shape.dim[0].dim_param == "batch"
        assert not (folder / (name + ".data")).exists(), "each graph must be a single file"


def test_split_placement_graphs_compose_to_h(graphs):
    trained, folder = graphs
    rng = np.random.default_rng(5)
    X = rng.uniform(-1, 1, size=(4, 300, 3)).astype(np.float32)
    Y = rng.uniform(-0.3, 0.3, size=(4, 200, 3)).astype(np.float32)
    qf = _session(folder / GRAPH_FILES["h_query"]).run(None, {"points": X})[0]
    pf = _session(folder / GRAPH_FILES["h_part"]).run(None, {"points": Y})[0]
    got = _session(folder / GRAPH_FILES["h_head"]).run(None, {"query_feature": qf, "part_feature": pf})[0]
    with torch.no_grad():
        want = trained.placement.eval()(torch.from_numpy(X), torch.from_numpy(Y)).numpy()
    assert np.abs(got - want).max() < 1e-4


@pytest.fixture(scope="module")
def exported(tiny_run: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("exported") / "exported"
    export_run(tiny_run, out)
    return out


def test_exported_folder_loads_and_is_consistent(exported: Path, tiny_run: Path, toy_dataset):
    manifest = read_manifest(exported)
    trained = load_trained(tiny_run)
    cfg = trained.config
    P = toy_dataset.n_components
    for key in ("model_version", "n_points", "embedding_dim", "n_modes", "part_count", "query_feature_dim",
                "part_feature_dim", "catalog_points", "index", "model_config", "dataset", "training",
                "created", "familiarity"):
        assert key in manifest, key
    # The familiarity bank: three partial assemblies per training shape, a positive threshold.
    assert 0 < manifest["familiarity"]["queries"] <= 3 * manifest["split"]["train_shapes"]
    assert manifest["familiarity"]["threshold"] > 0 and "familiarity.npz" in manifest["files"]
    assert manifest["part_count"] == P and manifest["n_points"] == cfg.n_points
    assert manifest["embedding_dim"] == cfg.model.embedding_dim and manifest["n_modes"] == cfg.model.n_modes
    assert manifest["training"]["steps"] == 20
    assert manifest["dataset"]["hash"] == toy_dataset.content_hash()
    assert manifest["index"]["type"] == "IndexFlatL2"

    records = json.loads((exported / CATALOG_JSON).read_text())
    assert len(records) == P
    assert all(set(r) == set(CATALOG_FIELDS) for r in records)
    split = load_split(tiny_run, toy_dataset)
    test_ids = {toy_dataset.shapes[s]["shape_id"] for s in split.test.tolist()}
    assert {r["shape_id"] for r in records if r["split"] == "test"} == test_ids
    assert records[3]["part_id"] == f"{toy_dataset.shapes[1]['shape_id']}/0"
    np.testing.assert_allclose(records[3]["translation"], toy_dataset.translation[3], atol=1e-6)

    with np.load(exported / CATALOG_ARRAYS) as npz:
        arrays = {k: npz[k] for k in npz.files}
    assert arrays["embeddings"].shape == (P, cfg.model.embedding_dim)
    assert arrays["embeddings"].dtype == np.float32
    assert arrays["part_features"].shape == (P, manifest["part_feature_dim"])
    # The stored embeddings and features are what the shipped graphs compute (features as float16).
    parts = sample_parts(toy_dataset, manifest["n_points"], seed=0)[:6]
    emb = _session(exported / GRAPH_FILES["f"]).run(None, {"points": parts})[0]
    np.testing.assert_allclose(arrays["embeddings"][:6], emb, atol=1e-5)
    feats = _session(exported / GRAPH_FILES["h_part"]).run(None, {"points": parts})[0]
    np.testing.assert_allclose(arrays["part_features"][:6].astype(np.float32), feats, rtol=2e-3, atol=1e-3)
    assert arrays["mesh_faces"].dtype == np.uint16 and arrays["mesh_vertices"].dtype == np.float16
    assert arrays["points"].shape == (P, 256, 3) and arrays["points"].dtype == np.float16
    assert arrays["vertex_first"][-1] == len(arrays["mesh_vertices"])

    index = faiss.read_index(str(exported / INDEX_FILE))
    assert index.ntotal == P and index.d == cfg.model.embedding_dim
    _, nearest = index.search(arrays["embeddings"][:5], 1)
    assert (nearest[:, 0] == np.arange(5)).all()

    sessions = {g: _session(exported / name) for g, name in GRAPH_FILES.items()}
    pts = np.random.default_rng(0).uniform(-0.5, 0.5, (2, manifest["n_points"], 3)).astype(np.float32)
    w, _, sigma = sessions["g"].run(None, {"points": pts})
    assert w.shape == (2, manifest["n_modes"]) and np.allclose(w.sum(1), 1, atol=1e-5)
    assert (sigma > 0).all() and (sigma <= cfg.model.sigma_max + 1e-6).all()
    qf = sessions["h_query"].run(None, {"points": pts})[0]
    assert qf.shape == (2, manifest["query_feature_dim"])
    pf = arrays["part_features"][:2].astype(np.float32)
    tr = sessions["h_head"].run(None, {"query_feature": qf, "part_feature": pf})[0]
    assert tr.shape == (2, 3) and np.isfinite(tr).all()


def test_export_refuses_to_exceed_the_size_limit(tiny_run: Path, tmp_path: Path):
    out = tmp_path / "exported"
    with pytest.raises(ValueError, match=r"over the limit of 0\.01 MB"):
        export_run(tiny_run, out, options=ExportOptions(max_megabytes=0.01))
    assert not (out / MANIFEST).exists()
    assert not list(tmp_path.glob(".exported.export-*")), "temporary folder left behind"


def test_h_can_take_its_own_point_count(tiny_run: Path, exported: Path, toy_dataset, tmp_path: Path):
    """--placement-points: h's part features from that many samples, f's embeddings as before, and
    the manifest says so; without it the manifest has no such key (the loader reads N)."""
    from service.artifacts.loading import load_artifacts

    out = tmp_path / "exported"
    manifest = export_run(tiny_run, out, options=ExportOptions(placement_points=48))
    n = manifest["n_points"]
    assert manifest["placement_points"] == 48 != n
    assert "placement_points" not in read_manifest(exported)
    with np.load(out / CATALOG_ARRAYS) as npz, np.load(exported / CATALOG_ARRAYS) as base:
        np.testing.assert_array_equal(npz["embeddings"], base["embeddings"])
        parts = sample_parts(toy_dataset, 48, 0)[:6]
        feats = _session(out / GRAPH_FILES["h_part"]).run(None, {"points": parts})[0]
        np.testing.assert_allclose(npz["part_features"][:6].astype(np.float32), feats, rtol=2e-3, atol=1e-3)
        assert not np.allclose(npz["part_features"], base["part_features"])
    loaded = load_artifacts(out)
    assert (loaded.n_points, loaded.placement_points, loaded.query_points) == (n, 48, max(n, 48))
    shipped_like = load_artifacts(exported)
    assert shipped_like.placement_points == shipped_like.query_points == n


def test_a_catalog_past_index_flat_max_gets_a_tuned_index(tiny_run: Path, tmp_path: Path):
    """Above the threshold the export builds IVF, records its search breadth, and the service uses it."""
    from service.artifacts.loading import load_artifacts

    out = tmp_path / "exported"
    manifest = export_run(tiny_run, out, options=ExportOptions(index_flat_max=1, index_recall_k=8))
    entry = manifest["index"]
    assert entry["type"] == "IndexIVFFlat"
    assert entry["params"]["recall_k"] == 8 and entry["params"]["nprobe"] >= 1
    # Tuned on g's means of training queries (the toy catalog has multi-part training shapes).
    assert entry["params"]["tuning_source"] == "given"
    assert entry["params"]["tuning_queries"] > 0
    loaded = load_artifacts(out)
    assert faiss.extract_index_ivf(loaded.index).nprobe == entry["params"]["nprobe"]


def test_duplicates_are_same_geometry_only(toy_dataset_factory):
    ds = toy_dataset_factory(3, seed=4, cached_points=1024, copies_of_first=2)
    n = ds.n_components
    emb = np.zeros((n, 4), np.float32)   # every pair is an embedding candidate: Chamfer decides
    extents = np.stack([np.ptp(ds.component_mesh(c)[0], axis=0) for c in range(n)])
    dup = find_duplicates(emb, ds.points, ds.area, extents, embedding_radius=1.0, chamfer_factor=0.65,
                          size_tolerance=0.02)
    originals = ds.components_of(0).tolist()
    for copy_shape in (ds.n_shapes - 2, ds.n_shapes - 1):
        assert [dup[c] for c in ds.components_of(copy_shape)] == originals
    others = [c for s in range(1, ds.n_shapes - 2) for c in ds.components_of(s)]
    assert all(dup[c] is None for c in others + originals)
    # A far embedding keeps them apart even with identical geometry.
    emb[ds.components_of(ds.n_shapes - 1)] = 100.0
    extents = np.stack([np.ptp(ds.component_mesh(c)[0], axis=0) for c in range(n)])
    dup = find_duplicates(emb, ds.points, ds.area, extents, embedding_radius=1.0, chamfer_factor=0.65,
                          size_tolerance=0.02)
    assert all(dup[c] is None for c in ds.components_of(ds.n_shapes - 1))
