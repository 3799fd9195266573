"""Compressed indexes for millions of parts: codes searched, the shortlist re-ranked exactly, the
file's exact vectors memory-mapped on read, filters passed through the wrappers."""

from __future__ import annotations

from pathlib import Path

import faiss
import numpy as np
import pytest
from service_testkit import clustered_embeddings

from service.artifacts.indexing import (
    build_index,
    configure_search,
    exact_search,
    index_entry,
    read_flags,
)
from service.suggest.neighbours import CatalogSearch


def _clustered(n: int) -> np.ndarray:
    return clustered_embeddings(n, 50)


@pytest.fixture(scope="module")
def x() -> np.ndarray:
    return _clustered(20_000)


@pytest.mark.parametrize("kind", ["ivf_sq8", "ivf_pq"])
def test_compressed_index_reaches_the_recall_target_after_the_rerank(x: np.ndarray, kind: str,
                                                                     tmp_path: Path) -> None:
    index, params = build_index(x, kind=kind, rerank=8, recall_k=32, tuning_queries=200,  # type: ignore[arg-type]
                                target_recall=0.95)
    assert params["type"] == "IndexRefineFlat" and params["rerank"] == 8
    assert params["recall"] >= 0.95 and "nprobe" in params
    if kind == "ivf_sq8":  # zero-padded to a multiple of 16 for FAISS's SIMD scan
        assert params["padded_dim"] == 64
    # Written, read back memory-mapped and configured from the manifest entry: same answers.
    path = tmp_path / "index.faiss"
    faiss.write_index(index, str(path))
    entry = index_entry(params)
    assert read_flags(entry) == faiss.IO_FLAG_MMAP_IFC
    loaded = faiss.read_index(str(path), read_flags(entry))
    configure_search(loaded, entry)
    assert loaded.k_factor == 8 and faiss.extract_index_ivf(loaded).nprobe == params["nprobe"]
    q = x[:40] + 0.1
    np.testing.assert_array_equal(loaded.search(q, 32)[1], index.search(q, 32)[1])
    # The re-rank orders by exact distance: returned distances are the true squared distances.
    d, labels = loaded.search(q[:3], 5)
    np.testing.assert_allclose(d, ((x[labels] - q[:3, None]) ** 2).sum(-1), rtol=1e-4)


def test_auto_picks_a_compressed_index_above_compressed_min(x: np.ndarray) -> None:
    _, small = build_index(x[:5000], flat_max=1000, compressed_min=10_000, recall_k=16, tuning_queries=50)
    _, large = build_index(x, flat_max=1000, compressed_min=10_000, recall_k=16, tuning_queries=50)
    assert small["type"] == "IndexIVFFlat"
    assert large["type"] == "IndexRefineFlat" and large["base"] == "IndexIVFScalarQuantizer"
    assert read_flags(small) == 0


def test_rerank_on_a_plain_index_is_refused(x: np.ndarray) -> None:
    index, _ = build_index(x[:3000], flat_max=1000, recall_k=16, tuning_queries=50)
    with pytest.raises(ValueError, match="rerank"):
        configure_search(index, {"rerank": 4})


def test_filtered_search_through_the_rerank_keeps_allowed_rows_only(x: np.ndarray) -> None:
    index, _ = build_index(x, kind="ivf_sq8", recall_k=32, tuning_queries=100)
    search = CatalogSearch(x, index, brute_force_max_parts=1000, exact_search_max_filtered=100)
    allowed = np.zeros(len(x), bool)
    allowed[::3] = True  # too many rows for the exact subset search: the ID selector is used
    means = x[:16] + 0.05
    found = search.neighbour_union(means, 8, 32, allowed)
    assert len(found) == 2 and all(len(f) > 0 and allowed[f].all() for f in found)
    # The selector reached the base search: its own labels are allowed rows only (an IVF probing
    # few lists may find fewer than k of them), nearest first as exact search over them orders.
    labels = search._faiss_search(means, 32, allowed)
    assert allowed[labels[labels >= 0]].all()
    rows = np.flatnonzero(allowed)
    nearest = rows[exact_search(x[rows], means, 1)[:, 0]]
    assert np.mean(labels[:, 0] == nearest) >= 0.75  # 14 of 16 with the 2 lists it tuned to probe


def test_a_filtered_ivf_search_probes_the_tuned_lists(x: np.ndarray) -> None:
    index, params = build_index(x, kind="ivf", recall_k=32, tuning_queries=100)
    assert params["nprobe"] > 1
    search = CatalogSearch(x, index, brute_force_max_parts=1000, exact_search_max_filtered=100)
    means = x[:16] + 0.05
    # A filter that the nearest parts pass (like the query's own category): the selector search
    # finds the nearest allowed rows among the lists an unfiltered search probes. (Left at
    # FAISS's default search parameters, it probed one list and found fewer.)
    allowed = np.ones(len(x), bool)
    wide = index.search(means, 64)[1]
    allowed[np.unique(wide[:, 40:])] = False
    expected = np.stack([row[allowed[row]][:32] for row in wide])
    assert expected.shape == (16, 32)
    np.testing.assert_array_equal(np.sort(search._faiss_search(means, 32, allowed), axis=1),
                                  np.sort(expected, axis=1))
