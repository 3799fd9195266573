"""Recall against a known answer, replicated embeddings and the replicated catalog."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bench.catalog_bench import recall_at_k, time_calls
from bench.replicate import (
    REPLICA_ARRAYS,
    ReplicatedCatalog,
    open_replica_arrays,
    replicate_embeddings,
    write_replica_arrays,
)
from service.artifacts.catalog import Catalog, load_catalog
from service.artifacts.layout import CATALOG_ARRAYS, CATALOG_JSON, read_manifest
from service.settings import DEFAULT_ARTIFACTS


def test_recall_against_a_known_answer() -> None:
    # Points on a line at 0, 1, ..., 9; the query sits at 0: its exact top 3 are rows 0, 1, 2.
    x = np.arange(10, dtype=np.float32)[:, None] * np.array([[1.0, 0.0]], dtype=np.float32)
    q = np.zeros((2, 2), np.float32)
    exact_dist = np.array([[0.0, 1.0, 4.0]] * 2)
    found = np.array([[0, 1, 2],      # all three: 3 hits
                      [0, 5, -1]])    # one right, one wrong, one missing: 1 hit
    assert recall_at_k(x, q, found, exact_dist) == pytest.approx(4 / 6)
    # A repeated label counts once.
    assert recall_at_k(x, q[:1], np.array([[0, 0, 0]]), exact_dist[:1]) == pytest.approx(1 / 3)
    with pytest.raises(ValueError, match="disagree"):
        recall_at_k(x, q, found[:1], exact_dist)


def test_recall_counts_ties_at_the_kth_distance() -> None:
    # Rows 1 and 2 are both at distance 1: exact search keeps one of them, either is right.
    x = np.array([[0, 0], [1, 0], [-1, 0], [5, 0]], dtype=np.float32)
    q = np.zeros((1, 2), np.float32)
    exact_dist = np.array([[0.0, 1.0]])
    assert recall_at_k(x, q, np.array([[0, 2]]), exact_dist) == 1.0
    assert recall_at_k(x, q, np.array([[0, 3]]), exact_dist) == 0.5


def test_replicated_embeddings_keep_copy_zero_and_are_seeded() -> None:
    rng = np.random.default_rng(0)
    base = rng.normal(size=(100, 8)).astype(np.float32)
    a = replicate_embeddings(base, 250, noise=0.1, seed=3)
    assert a.shape == (250, 8) and a.dtype == np.float32
    np.testing.assert_array_equal(a[:100], base)
    np.testing.assert_array_equal(a, replicate_embeddings(base, 250, noise=0.1, seed=3))
    assert not np.array_equal(a, replicate_embeddings(base, 250, noise=0.1, seed=4))
    jitter = (a[100:] - base[np.arange(100, 250) % 100]) / base.std(axis=0)
    assert 0.07 < jitter.std() < 0.13  # noise of 0.1 std per dimension
    np.testing.assert_array_equal(replicate_embeddings(base, 50, noise=0.1, seed=0), base[:50])
    with pytest.raises(ValueError, match="at least 1"):
        replicate_embeddings(base, 0, noise=0.1, seed=0)


def test_replicated_embeddings_are_the_same_made_in_blocks() -> None:
    # One draw of all the noise (how the rows were first made) against the block-wise rows.
    rng = np.random.default_rng(0)
    base = rng.normal(size=(100, 8)).astype(np.float32)
    one_draw = np.tile(base, (3, 1))[:250]
    one_draw[100:] += (np.random.default_rng(3).standard_normal((150, 8), dtype=np.float32)
                       * (0.1 * base.std(axis=0)).astype(np.float32))
    np.testing.assert_array_equal(replicate_embeddings(base, 250, noise=0.1, seed=3), one_draw)


def test_time_calls_stops_at_the_count_or_the_time_bound() -> None:
    calls: list[int] = []
    assert len(time_calls(lambda: calls.append(1), reps=5, warmup=2, max_seconds=60)) == 5
    assert len(calls) == 7
    assert len(time_calls(lambda: None, reps=10**9, warmup=0, max_seconds=0.05)) < 10**9


@pytest.fixture(scope="module")
def shipped_catalog() -> Catalog:
    folder = Path(DEFAULT_ARTIFACTS)
    if not (folder / "manifest.json").is_file():
        pytest.skip(f"no artifact folder at {folder}")
    m = read_manifest(folder, verify_checksums=False)
    return load_catalog(folder / CATALOG_JSON, folder / CATALOG_ARRAYS, int(m["part_count"]),
                        int(m["embedding_dim"]))


def test_replicated_catalog_rows_are_their_real_parts(shipped_catalog: Catalog) -> None:
    base = shipped_catalog
    P = len(base)
    n = 2 * P + 17
    cat = ReplicatedCatalog(base, replicate_embeddings(base.embeddings, n, noise=0.05, seed=0))
    assert len(cat) == n and len(cat.records) == n
    assert cat.part_features.shape == (n, base.part_features.shape[1])
    i = P + 5  # the second copy of part 5
    assert cat.part_ids[i] == f"{base.part_ids[5]}~1" and cat.lookup(cat.part_ids[i]) == i
    assert cat.records[i]["part_id"] == cat.part_ids[i]
    assert cat.records[i]["shape_id"] == base.records[5]["shape_id"]
    assert cat.records[5] is base.records[5]
    np.testing.assert_array_equal(cat.part_features[i], base.part_features[5])
    np.testing.assert_array_equal(cat.bbox_max[i], base.bbox_max[5])
    assert cat.category_of[i] == base.category_of[5]
    v, f = cat.mesh(i)
    bv, bf = base.mesh(5)
    np.testing.assert_array_equal(v, bv)
    np.testing.assert_array_equal(f, bf)
    np.testing.assert_array_equal(cat.part_points(i), base.part_points(5))
    # Copies share the real part's duplicate group.
    assert cat.group[i] == base.group[5] and cat.group_size[5] >= 2 * base.group_size[5]
    with pytest.raises(IndexError):
        cat.records[n]


def test_engines_are_timed_in_interleaved_rounds_each_with_its_own_catalog(shipped_catalog: Catalog) -> None:
    import dataclasses

    from bench.catalog_bench import CatalogBenchConfig, time_engines
    from bench.engine_bench import load_engine
    from bench.query import load_query
    from service.settings import Settings

    settings = Settings(artifacts=Path(DEFAULT_ARTIFACTS), verify_checksums=False)
    engine = load_engine(settings)
    base = engine.catalog
    bigger = ReplicatedCatalog(base, replicate_embeddings(base.embeddings, 2 * len(base), noise=0.05, seed=0))
    flat = engine.index.__class__(base.embeddings.shape[1])
    flat.add(bigger.embeddings)
    other = type(engine)(dataclasses.replace(engine.artifacts, index=flat, catalog=bigger), settings)
    rows = time_engines([engine, other], load_query().body("json"),
                        CatalogBenchConfig(engine_reps=3, warmup=1))
    assert [r["engine"]["suggest"]["n"] for r in rows] == [3, 3]
    assert "~" not in rows[0]["top_part"]  # the shipped catalog has no copies
    assert rows[1]["top_part"] is not None


def test_mapped_replica_matches_the_in_memory_one(shipped_catalog: Catalog, tmp_path: Path) -> None:
    base = shipped_catalog
    P = len(base)
    n = 3 * P + 11
    folder = tmp_path / "replica"
    with pytest.raises(FileNotFoundError, match=r"replica\.json"):
        open_replica_arrays(folder)
    write_replica_arrays(base, n, noise=0.05, seed=0, folder=folder, block_rows=P // 2 + 7)
    arrays = open_replica_arrays(folder)
    assert set(arrays) == set(REPLICA_ARRAYS)
    assert all(isinstance(a, np.memmap) and not a.flags.writeable for a in arrays.values())
    mapped = ReplicatedCatalog(base, arrays=arrays)
    memory = ReplicatedCatalog(base, replicate_embeddings(base.embeddings, n, noise=0.05, seed=0))
    for name in REPLICA_ARRAYS:
        np.testing.assert_array_equal(getattr(mapped, name), getattr(memory, name), err_msg=name)
    assert mapped.part_features.dtype == np.float16  # stored as catalog.npz stores it
    i = 2 * P + 5
    assert mapped.part_ids[i] == f"{base.part_ids[5]}~2" == memory.part_ids[i]
    assert mapped.lookup(mapped.part_ids[i]) == i and mapped.lookup(base.part_ids[5]) == 5
    for bad in (f"{base.part_ids[5]}~0", f"{base.part_ids[P - 1]}~3", f"{base.part_ids[5]}~x", "nope~1"):
        assert bad not in mapped.index_of
    assert len(mapped.index_of) == n and list(mapped.index_of)[P] == f"{base.part_ids[0]}~1"
    with pytest.raises(ValueError, match="either"):
        ReplicatedCatalog(base)
