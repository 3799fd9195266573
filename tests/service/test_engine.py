"""The engine without HTTP: retrieval against brute force, batching, filters, placement."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from service_testkit import AssemblyQuery, assembly_query, multi_part_shapes

from service.errors import InputError, NotFoundError, ServiceError
from service.geometry.frames import Frame
from service.settings import Settings
from service.suggest.engine import SuggestionEngine, SuggestOptions
from service.suggest.mixture import mixture_log_likelihood


@pytest.fixture(scope="module")
def exhaustive(engine: SuggestionEngine, settings: Settings) -> SuggestionEngine:
    """The same artifacts with FAISS asked for every part: candidates = the whole catalog, ranked
    by likelihood alone (no complement check, no inferred category, no slots dealt to modes and
    no fit penalties, which brute force does not model)."""
    update = {"neighbours_per_mode": len(engine.catalog), "max_k": len(engine.catalog),
              "suggest_complement_check": False, "infer_category": False, "suggest_order": "likelihood",
              "rank_scale_weight": 0.0, "rank_move_weight": 0.0}
    return SuggestionEngine(engine.artifacts, settings.model_copy(update=update))


def brute_force(engine: SuggestionEngine, points: np.ndarray, k: int, allowed: np.ndarray | None = None,
                collapse: bool = True) -> list[str]:
    """Rank every catalog part by the exact mixture log-likelihood, then collapse duplicates."""
    canonical = engine.prepare(points, Frame())
    mix = engine.networks.mixture(canonical[None])
    ll, _ = mixture_log_likelihood(engine.catalog.embeddings, mix.weights[0], mix.means[0], mix.sigmas[0])
    order = np.argsort(-ll, kind="stable")
    if allowed is not None:
        order = order[allowed[order]]
    out: list[str] = []
    seen: set[int] = set()
    for i in order:
        g = int(engine.catalog.group[i])
        if collapse and g in seen:
            continue
        seen.add(g)
        out.append(engine.catalog.part_ids[i])
        if len(out) == k:
            break
    return out


def ids(result) -> list[str]:
    return [s.part_id for s in result.suggestions]


def test_exhaustive_search_equals_brute_force(exhaustive: SuggestionEngine, query: AssemblyQuery) -> None:
    for collapse in (True, False):
        result = exhaustive.suggest(query.points, SuggestOptions(k=25, collapse_duplicates=collapse))
        assert ids(result) == brute_force(exhaustive, query.points, 25, collapse=collapse)
        assert result.candidates == len(exhaustive.catalog)


def test_filters_equal_brute_force(exhaustive: SuggestionEngine, query: AssemblyQuery) -> None:
    cat = exhaustive.catalog
    category = cat.categories[-1]
    allowed = cat.category_of == cat.categories.index(category)
    result = exhaustive.suggest(query.points, SuggestOptions(k=10, categories=(category,)))
    assert ids(result) == brute_force(exhaustive, query.points, 10, allowed)
    shape = query.shape_id
    excluded = ids(result)[0]
    allowed = (cat.shape_of != cat.shape_code(shape)) & (cat.group != cat.group[cat.lookup(excluded)])
    result = exhaustive.suggest(query.points, SuggestOptions(k=10, exclude_shapes=(shape,),
                                                            exclude_parts=(excluded,)))
    assert ids(result) == brute_force(exhaustive, query.points, 10, allowed)


def test_faiss_candidates_are_a_subset_ranked_the_same(engine: SuggestionEngine, exhaustive: SuggestionEngine,
                                                       query: AssemblyQuery) -> None:
    result = engine.suggest(query.points, SuggestOptions(k=10))
    K, nn = engine.artifacts.n_modes, min(engine.config.neighbours_per_mode, len(engine.catalog))
    assert 0 < result.candidates <= K * nn
    # Scores are exact: a part's score does not depend on how it became a candidate.
    everything = SuggestOptions(k=len(engine.catalog), collapse_duplicates=False)
    full = {s.part_id: s.score for s in exhaustive.suggest(query.points, everything).suggestions}
    for s in result.suggestions:
        assert s.score == pytest.approx(full[s.part_id], rel=1e-12)


def test_batch_equals_single_queries(engine: SuggestionEngine, catalog) -> None:
    n = engine.artifacts.n_points
    shapes = multi_part_shapes(catalog, 4)
    queries = []
    for s in shapes:
        last = [r["part_id"] for r in catalog.records if r["shape_id"] == s][-1]
        queries.append(assembly_query(catalog, s, last, n, seed=3))
    options = [SuggestOptions(k=5), SuggestOptions(k=3, categories=(catalog.categories[0],)),
               SuggestOptions(k=5), SuggestOptions(k=4, frame=Frame(np.array([1.0, 0, 0]), 2.0, "z"))]
    points = [q.points if o.frame.is_canonical else o.frame.from_canonical(q.points)
              for q, o in zip(queries, options, strict=True)]
    batch = engine.suggest_batch(list(zip(points, options, strict=True)))
    for p, o, b in zip(points, options, batch, strict=True):
        assert not isinstance(b, ServiceError)
        single = engine.suggest(p, o)
        assert ids(b) == ids(single)
        for x, y in zip(b.suggestions, single.suggestions, strict=True):
            np.testing.assert_allclose(x.translation, y.translation, atol=1e-5)
            assert x.score == pytest.approx(y.score, rel=1e-6)


def test_batch_isolates_bad_items(engine: SuggestionEngine, query: AssemblyQuery) -> None:
    out = engine.suggest_batch([(query.points, SuggestOptions(k=2)),
                                (query.points[:3], SuggestOptions()),
                                (query.points, SuggestOptions(categories=("spaceship",))),
                                (query.points, SuggestOptions(exclude_parts=("no-such/0",)))])
    assert not isinstance(out[0], ServiceError) and len(out[0].suggestions) == 2
    assert isinstance(out[1], InputError) and out[1].code == "too_few_points"
    assert isinstance(out[2], InputError) and out[2].code == "unknown_category"
    assert isinstance(out[3], NotFoundError) and out[3].code == "unknown_part"


def test_a_filter_that_leaves_nothing(engine: SuggestionEngine, settings: Settings,
                                      query: AssemblyQuery) -> None:
    cat = engine.catalog
    first = cat.categories[0]
    shapes = tuple(sorted({r["shape_id"] for r in cat.records if r["category"] == first}))
    # A real catalog has more shapes per category than the test limit on exclusions.
    roomy = SuggestionEngine(engine.artifacts,
                             settings.model_copy(update={"max_exclude": max(len(shapes), 1)}))
    result = roomy.suggest(query.points, SuggestOptions(categories=(first,), exclude_shapes=shapes))
    assert result.suggestions == [] and result.candidates == 0


def test_place_agrees_with_suggest(engine: SuggestionEngine, query: AssemblyQuery) -> None:
    for refine in (False, True):
        result = engine.suggest(query.points, SuggestOptions(k=6, refine_contact=refine))
        placed = engine.place(query.points, ids(result), refine_contact=refine)
        for p, s in zip(placed.placements, result.suggestions, strict=True):
            np.testing.assert_allclose(p.translation, s.translation, atol=1e-6)
    with pytest.raises(NotFoundError):
        engine.place(query.points, ["no-such/0"])


def test_warmup_suggests_and_places(engine: SuggestionEngine) -> None:
    result = engine.warmup()
    assert result.suggestions, "warm-up made no suggestion from a whole catalog shape"
    assert all(np.isfinite(s.translation).all() for s in result.suggestions)


def test_chunked_runs_equal_one_run(engine: SuggestionEngine, query: AssemblyQuery) -> None:
    n = engine.artifacts.n_points
    batch = np.stack([engine.prepare(query.points * s, Frame()) for s in (1.0, 0.9, 0.8, 0.7, 0.6)])
    whole = dataclasses.replace(engine.networks, max_points_per_run=10**9)
    chunked = dataclasses.replace(engine.networks, max_points_per_run=2 * n)  # rows of 2, 2, 1
    a, b = whole.mixture(batch), chunked.mixture(batch)
    for x, y in ((a.weights, b.weights), (a.means, b.means), (a.sigmas, b.sigmas),
                 (whole.query_features(batch), chunked.query_features(batch))):
        assert x.shape == y.shape
        np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-6)


def test_a_large_k_is_not_starved(engine: SuggestionEngine, settings: Settings, query: AssemblyQuery) -> None:
    narrow = SuggestionEngine(engine.artifacts, settings.model_copy(update={"neighbours_per_mode": 2}))
    k = min(20, len(engine.catalog))
    result = narrow.suggest(query.points, SuggestOptions(k=k, collapse_duplicates=False))
    assert len(result.suggestions) == k


def test_h_query_beside_g_gives_the_same_answer(engine: SuggestionEngine, settings: Settings,
                                                query: AssemblyQuery) -> None:
    inline = SuggestionEngine(engine.artifacts, settings.model_copy(update={"overlap_max_batch": 0}))
    beside = SuggestionEngine(engine.artifacts, settings.model_copy(update={"overlap_max_batch": 2}))
    items = [(query.points, SuggestOptions(k=6)), (query.points[::2], SuggestOptions(k=4))]
    for a, b in zip(inline.suggest_batch(items), beside.suggest_batch(items), strict=True):
        assert not isinstance(a, ServiceError) and not isinstance(b, ServiceError)
        assert ids(a) == ids(b)
        np.testing.assert_array_equal([s.translation for s in a.suggestions],
                                      [s.translation for s in b.suggestions])
        assert a.timings["h_query"] > 0 and b.timings["h_query"] > 0
