"""The index chosen by catalog size: flat below the threshold, tuned IVF / HNSW above it."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import faiss
import numpy as np
import pytest

from service.indexing import (
    build_index,
    configure_search,
    exact_search,
    index_entry,
    jittered_queries,
    params_from_entry,
    recall_at_k,
)


def _clustered(n: int, d: int = 16, seed: int = 0) -> np.ndarray:
    """Embeddings that cluster like real part embeddings do: jittered copies of a few centres."""
    rng = np.random.default_rng(seed)
    centres = rng.standard_normal((max(1, n // 50), d))
    x = centres[rng.integers(len(centres), size=n)] + 0.3 * rng.standard_normal((n, d))
    return x.astype(np.float32)


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
