"""numpy brute force gives the parts a FAISS flat index gives (service/suggest/neighbours.py)."""

from __future__ import annotations

import faiss
import numpy as np
import pytest
from service_testkit import AssemblyQuery

from service.settings import Settings
from service.suggest.engine import SuggestionEngine, SuggestOptions
from service.suggest.neighbours import BruteForceNeighbours


def _faiss_union(emb: np.ndarray, means: np.ndarray, modes: int, nn: int, metric: int,
                 allowed: np.ndarray | None = None) -> list[set[int]]:
    rows = np.arange(len(emb)) if allowed is None else np.flatnonzero(allowed)
    index = faiss.IndexFlat(emb.shape[1], metric)
    index.add(emb[rows])
    _, labels = index.search(means, min(nn, len(rows)))
    return [set(rows[labels[q * modes:(q + 1) * modes].ravel()].tolist()) for q in range(len(means) // modes)]


@pytest.mark.parametrize("metric", [faiss.METRIC_L2, faiss.METRIC_INNER_PRODUCT])
def test_same_parts_as_a_flat_faiss_index(metric: int) -> None:
    rng = np.random.default_rng(1)
    emb = rng.normal(size=(3000, 50)).astype(np.float32)
    means = rng.normal(size=(5 * 8, 50)).astype(np.float32)
    got = BruteForceNeighbours(emb, inner_product=metric == faiss.METRIC_INNER_PRODUCT).neighbour_union(
        means, 8, 64)
    want = _faiss_union(emb, means, 8, 64, metric)
    assert [set(g.tolist()) for g in got] == want
    assert all(np.all(np.diff(g) > 0) for g in got)  # sorted, distinct


def test_a_filter_is_respected_and_matches_faiss_on_the_allowed_rows() -> None:
    rng = np.random.default_rng(2)
    emb = rng.normal(size=(2000, 16)).astype(np.float32)
    means = rng.normal(size=(3 * 4, 16)).astype(np.float32)
    allowed = rng.random(2000) < 0.3
    got = BruteForceNeighbours(emb).neighbour_union(means, 4, 32, allowed)
    assert [set(g.tolist()) for g in got] == _faiss_union(emb, means, 4, 32, faiss.METRIC_L2, allowed)
    assert all(allowed[g].all() for g in got)


def test_fewer_allowed_parts_than_asked_gives_all_of_them() -> None:
    rng = np.random.default_rng(3)
    emb = rng.normal(size=(500, 8)).astype(np.float32)
    allowed = np.zeros(500, bool)
    allowed[[3, 70, 444]] = True
    means = rng.normal(size=(2, 8)).astype(np.float32)
    got = BruteForceNeighbours(emb).neighbour_union(means, 2, 64, allowed)
    assert [g.tolist() for g in got] == [[3, 70, 444]]
    none = BruteForceNeighbours(emb).neighbour_union(np.zeros((4, 8), np.float32), 2, 64, np.zeros(500, bool))
    assert [g.tolist() for g in none] == [[], []]


def test_parts_tied_with_the_last_neighbour_are_all_kept() -> None:
    emb = np.zeros((10, 3), np.float32)
    emb[:, 0] = [0, 1, 1, 1, 2, 3, 4, 5, 6, 7]  # three parts at distance 1 from the origin
    got = BruteForceNeighbours(emb).neighbour_union(np.zeros((1, 3), np.float32), 1, 2)
    assert got[0].tolist() == [0, 1, 2, 3]


def test_the_engine_suggests_the_same_parts_with_either_search(
        engine: SuggestionEngine, settings: Settings, query: AssemblyQuery) -> None:
    assert engine.brute_force is not None, "the shipped catalog is small enough for brute force"
    with_faiss = SuggestionEngine(engine.artifacts, settings.model_copy(update={"brute_force_max_parts": 0}))
    assert with_faiss.brute_force is None
    for options in (SuggestOptions(k=20), SuggestOptions(k=10, categories=("chair", "table")),
                    SuggestOptions(k=10, exclude_shapes=(query.shape_id,))):
        a, b = (e.suggest_batch([(query.points, options)])[0] for e in (engine, with_faiss))
        assert [s.part_id for s in a.suggestions] == [s.part_id for s in b.suggestions]
        assert a.candidates == b.candidates


def test_a_kept_category_mask_gives_the_search_what_a_fresh_one_gives() -> None:
    """A category's mask is made once per snapshot, read-only, and the FAISS search keeps its
    bitmap: the same parts as the same filter made afresh, and the mask cannot be changed."""
    from service.suggest.neighbours import CatalogSearch

    rng = np.random.default_rng(3)
    emb = rng.normal(size=(3000, 16)).astype(np.float32)
    means = rng.normal(size=(2 * 4, 16)).astype(np.float32)
    index = faiss.IndexFlatL2(16)
    index.add(emb)
    search = CatalogSearch(emb, index, brute_force_max_parts=0, exact_search_max_filtered=0)
    kept = rng.random(3000) < 0.6
    kept.setflags(write=False)
    for _ in range(2):  # the second search reads the kept bitmap
        got = search.neighbour_union(means, 4, 32, kept)
        assert [set(g.tolist()) for g in got] == _faiss_union(emb, means, 4, 32, faiss.METRIC_L2, kept)
    other = ~kept  # a different mask of the same size: its own bitmap
    got = search.neighbour_union(means, 4, 32, other)
    assert [set(g.tolist()) for g in got] == _faiss_union(emb, means, 4, 32, faiss.METRIC_L2, other)


def test_the_snapshot_keeps_one_read_only_mask_per_category(engine: SuggestionEngine) -> None:
    snap = engine.shipped
    cat = snap.catalog
    chair = snap.category_mask(cat.category_codes(["chair"]))
    assert chair is snap.category_mask(cat.category_codes(["chair"]))
    assert not chair.flags.writeable
    np.testing.assert_array_equal(chair, cat.category_of == cat.category_codes(["chair"])[0])
    both = snap.category_mask(cat.category_codes(["chair", "table"]))
    assert both.flags.writeable and int(both.sum()) == int(chair.sum()) + int(
        (cat.category_of == cat.category_codes(["table"])[0]).sum())


@pytest.mark.parametrize("share", [0.1, 0.6, 0.002])
def test_brute_force_over_a_kept_mask_searches_its_rows_alone_with_the_same_answer(share: float) -> None:
    """A read-only (kept) mask is searched over its own columns, made once; the answer is the
    masked search's, ties included, and a writeable mask is still masked per call."""
    rng = np.random.default_rng(4)
    emb = np.round(rng.normal(size=(3000, 16)), 1).astype(np.float32)  # coarse values: ties happen
    means = np.round(rng.normal(size=(3 * 4, 16)), 1).astype(np.float32)
    allowed = rng.random(3000) < share
    fresh = BruteForceNeighbours(emb).neighbour_union(means, 4, 32, allowed.copy())
    kept = allowed.copy()
    kept.setflags(write=False)
    search = BruteForceNeighbours(emb)
    for _ in range(2):  # the second call reads the kept columns
        got = search.neighbour_union(means, 4, 32, kept)
        assert [g.tolist() for g in got] == [f.tolist() for f in fresh]
        assert all(g.dtype == np.int64 and allowed[g].all() for g in got)
    assert len(search._subsets) == 1
    assert [set(g.tolist()) for g in got] == _faiss_union(emb, means, 4, 32, faiss.METRIC_L2, allowed)
