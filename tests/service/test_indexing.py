"""The index chosen by catalog size: flat below the threshold, tuned IVF / HNSW above it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import faiss
import numpy as np
import pytest
from service_testkit import clustered_embeddings, make_settings

from service.artifacts.indexing import (
    build_index,
    configure_search,
    exact_search,
    index_entry,
    jittered_queries,
    params_from_entry,
    recall_at_k,
)
from service.artifacts.layout import ArtifactError, read_manifest, write_manifest
from service.artifacts.loading import load_artifacts
from service.suggest.engine import SuggestionEngine, SuggestOptions


def _clustered(n: int) -> np.ndarray:
    return clustered_embeddings(n, 16)


def test_small_catalog_gets_an_exact_flat_index() -> None:
    x = _clustered(500)
    index, params = build_index(x, flat_max=1000)
    assert params == {"type": "IndexFlatL2", "metric": "l2", "dim": 16}
    assert isinstance(index, faiss.IndexFlat) and index.ntotal == 500
    q = jittered_queries(x, 20, 0.5, seed=1)
    np.testing.assert_array_equal(index.search(q, 10)[1], exact_search(x, q, 10))


@pytest.mark.parametrize("kind", ["ivf", "hnsw"])
def test_large_catalog_index_reaches_the_recall_target(kind: Literal["ivf", "hnsw"], tmp_path: Path) -> None:
    x = _clustered(6000)
    index, params = build_index(x, flat_max=1000, kind="auto" if kind == "ivf" else kind,
                                target_recall=0.95, recall_k=32, tuning_queries=300)
    assert params["type"] == {"ivf": "IndexIVFFlat", "hnsw": "IndexHNSWFlat"}[kind]
    assert params["recall"] >= 0.95 and params["recall_k"] == 32
    assert index.ntotal == len(x)
    json.dumps(params)  # the manifest records it
    # Written and read back, the index searches with the recorded breadth once configured.
    path = tmp_path / "index.faiss"
    faiss.write_index(index, str(path))
    loaded = faiss.read_index(str(path))
    configure_search(loaded, index_entry(params))
    q = jittered_queries(x, 300, 0.5, seed=0)  # the tuning queries themselves
    assert recall_at_k(loaded.search(q, 32)[1], exact_search(x, q, 32)) == pytest.approx(
        params["recall"], abs=1e-4)
    # Other queries from the same distribution do about as well.
    q2 = jittered_queries(x, 300, 0.5, seed=7)
    assert recall_at_k(loaded.search(q2, 32)[1], exact_search(x, q2, 32)) > 0.9


def test_given_tuning_queries_set_the_breadth_that_they_need() -> None:
    x = _clustered(4000)
    # Queries far from the catalog (between its clusters) need a wider search than jittered parts.
    far = jittered_queries(x, 400, 2.0, seed=3)
    _, near_params = build_index(x, kind="ivf", nlist=64, target_recall=0.95, recall_k=16, tuning_queries=200)
    index, params = build_index(x, kind="ivf", nlist=64, target_recall=0.95, recall_k=16, queries=far,
                                tuning_queries=200)
    assert near_params["tuning_source"] == "jittered_embeddings" and params["tuning_source"] == "given"
    assert params["tuning_queries"] == 200  # a sample of the 400 given
    assert params["nprobe"] > near_params["nprobe"]
    held_out = jittered_queries(x, 200, 2.0, seed=4)
    assert recall_at_k(index.search(held_out, 16)[1], exact_search(x, held_out, 16)) > 0.9
    with pytest.raises(ValueError, match="tuning queries"):
        build_index(x, kind="ivf", nlist=64, queries=far[:, :3])


def test_ivf_breadth_is_the_smallest_that_passes() -> None:
    x = _clustered(4000)
    index, params = build_index(x, kind="ivf", nlist=64, target_recall=0.9, recall_k=16, tuning_queries=200)
    q = jittered_queries(x, 200, 0.5, seed=0)
    exact = exact_search(x, q, 16)
    nprobe = params["nprobe"]
    assert 1 <= nprobe <= 64
    if nprobe > 1:  # one list fewer misses the target (within the refinement's granularity)
        configure_search(index, {"nprobe": max(1, nprobe - max(1, nprobe // 8) - 1)})
        assert recall_at_k(index.search(q, 16)[1], exact) < 0.9


def test_manifest_entry_round_trip_and_old_entries() -> None:
    params = {"type": "IndexIVFFlat", "metric": "l2", "dim": 8, "nlist": 4, "nprobe": 2}
    entry = index_entry(params)
    assert entry == {"type": "IndexIVFFlat", "params": {"metric": "l2", "dim": 8, "nlist": 4, "nprobe": 2}}
    assert params_from_entry(entry) == params
    # The shipped manifest's entry (flat, no search parameters) configures a flat index to nothing.
    old = {"type": "IndexFlatL2", "params": {"metric": "l2", "dim": 8}}
    flat = faiss.IndexFlatL2(8)
    configure_search(flat, old)


def test_search_parameters_must_fit_the_index() -> None:
    with pytest.raises(ValueError, match=r"nprobe.*IndexFlatL2"):
        configure_search(faiss.IndexFlatL2(8), {"type": "IndexIVFFlat", "nprobe": 4})
    with pytest.raises(ValueError, match=r"efSearch.*IndexFlatL2"):
        configure_search(faiss.IndexFlatL2(8), {"type": "IndexHNSWFlat", "efSearch": 64})


def test_bad_embeddings_are_refused() -> None:
    with pytest.raises(ValueError, match="non-empty"):
        build_index(np.zeros((0, 4), np.float32))
    with pytest.raises(ValueError, match="NaN"):
        build_index(np.full((3, 4), np.nan, np.float32))
    with pytest.raises(ValueError, match="metric"):
        build_index(np.zeros((3, 4), np.float32), metric="cosine")
    with pytest.raises(ValueError, match="kind"):
        build_index(np.zeros((3, 4), np.float32), kind="lsh")  # type: ignore[arg-type]


def test_recall_counts_missing_labels_as_misses() -> None:
    exact = np.array([[0, 1, 2, 3]])
    assert recall_at_k(np.array([[3, 2, -1, -1]]), exact) == 0.5


# ------------------------------------------------------------------ loading an exported index


def _copy_with_index(src: Path, dst: Path, index: faiss.Index, entry: dict[str, object]) -> Path:
    """The artifact folder with another index file and manifest ``"index"`` entry."""
    dst.mkdir()
    for f in src.iterdir():
        if f.name not in ("index.faiss", "manifest.json"):
            (dst / f.name).symlink_to(f.resolve())
    faiss.write_index(index, str(dst / "index.faiss"))
    manifest = read_manifest(src, verify_checksums=False)
    manifest = {k: v for k, v in manifest.items() if k not in ("files", "format_version")}
    write_manifest(dst, {**manifest, "index": entry})
    return dst


def test_an_ivf_index_loads_with_its_recorded_search_breadth(artifacts: Path, tmp_path: Path) -> None:
    emb = np.load(artifacts / "catalog.npz")["embeddings"]
    index, params = build_index(emb, flat_max=1000, recall_k=64, tuning_queries=300)
    assert params["type"] == "IndexIVFFlat" and params["recall"] >= 0.95
    folder = _copy_with_index(artifacts, tmp_path / "ivf", index, index_entry(params))
    loaded = load_artifacts(folder)
    assert faiss.extract_index_ivf(loaded.index).nprobe == params["nprobe"]
    settings = make_settings(folder, verify_checksums=False)
    engine = SuggestionEngine(loaded, settings)
    exact = SuggestionEngine(load_artifacts(artifacts, verify_checksums=False), settings)
    cat = engine.catalog
    parts = np.flatnonzero(cat.shape_of == cat.shape_of[0])
    points = np.concatenate([cat.part_points(int(i)) + cat.translations[i] for i in parts])
    # Likelihood order: the complement check would reorder each engine's shortlist on its own.
    a = engine.suggest(points, SuggestOptions(k=10, complement_check=False))
    b = exact.suggest(points, SuggestOptions(k=10, complement_check=False))
    shared = {s.part_id for s in a.suggestions} & {s.part_id for s in b.suggestions}
    assert len(shared) >= 8, "an approximate index at recall 0.95 keeps most of the exact top 10"
    # A filter still returns only allowed parts (exact search over the few that pass it).
    category = cat.categories[-1]
    filtered = engine.suggest(points, SuggestOptions(k=10, categories=(category,)))
    assert filtered.suggestions and all(s.category == category for s in filtered.suggestions)


def test_a_manifest_naming_another_index_type_is_refused(artifacts: Path, tmp_path: Path) -> None:
    emb = np.load(artifacts / "catalog.npz")["embeddings"]
    index, _ = build_index(emb, kind="flat")
    folder = _copy_with_index(artifacts, tmp_path / "wrong", index,
                              {"type": "IndexIVFFlat", "params": {"nlist": 64, "nprobe": 8}})
    with pytest.raises(ArtifactError, match=r"IndexFlatL2.*IndexIVFFlat") as info:
        load_artifacts(folder)
    assert str(folder / "index.faiss") in str(info.value)
