"""The complement check: parts lying on the query's own surface go behind the parts it lacks."""

from __future__ import annotations

import numpy as np
import pytest
from service_testkit import AssemblyQuery, assembly_query, multi_part_shapes

from service.geometry.frames import Frame
from service.settings import Settings
from service.suggest.complement import covered_share, demote_covered
from service.suggest.engine import SuggestionEngine, SuggestOptions
from service.suggest.fit_rank import fit_keys


def _square(n: int = 40, y: float = 0.0) -> np.ndarray:
    """A grid of n x n points on a unit square at height y (spacing 1 / (n - 1))."""
    u = np.linspace(-0.5, 0.5, n)
    x, z = np.meshgrid(u, u)
    return np.stack([x.ravel(), np.full(x.size, y), z.ravel()], axis=1).astype(np.float32)


def test_covered_share_counts_samples_near_the_query() -> None:
    query = _square()
    part = _square(10)[None] * np.float32(0.5)  # a smaller square, centred
    on = covered_share(query, part, np.zeros((1, 3), np.float32), distance=0.05)
    away = covered_share(query, part, np.array([[0, 1.0, 0]], np.float32), distance=0.05)
    # Shifted by half its width past the query's edge: the half still over the query is covered
    # (distance 0.05 reaches beyond the edge by one row of the 10-point grid).
    half = covered_share(query, part, np.array([[0.5, 0.01, 0]], np.float32), distance=0.05)
    assert on[0] == 1.0 and away[0] == 0.0
    assert 0.5 <= half[0] <= 0.6


def test_covered_share_of_nothing() -> None:
    assert covered_share(_square(), np.zeros((0, 8, 3), np.float32), np.zeros((0, 3)), 0.1).shape == (0,)
    assert covered_share(np.zeros((0, 3)), np.zeros((2, 8, 3)), np.zeros((2, 3)), 0.1).tolist() == [0, 0]


def test_demote_covered_keeps_order_within_each_side() -> None:
    share = np.array([0.9, 0.1, 0.5, 0.0, 0.49, 1.0])
    assert demote_covered(share, 0.5).tolist() == [1, 3, 4, 0, 2, 5]
    assert demote_covered(share, 1.01).tolist() == list(range(6))


def _canonical_share(engine: SuggestionEngine, query: AssemblyQuery, result) -> np.ndarray:
    s, cat = engine.config, engine.catalog
    pts = engine.prepare(query.points, Frame())
    idx = np.array([x.part_index for x in result.suggestions])
    # Canonical frame; h's placement, before any contact refinement (what the check measures).
    tr = np.stack([x.translation - x.contact_offset for x in result.suggestions]).astype(np.float32)
    return covered_share(pts, cat.part_samples(idx, s.complement_part_samples), tr,
                         s.complement_cover_distance)


def test_engine_puts_uncovered_parts_first(engine: SuggestionEngine, settings: Settings, query: AssemblyQuery
                                           ) -> None:
    k = 20
    # A shortlist within max_k, so that the plain ranking below can hold all of it; in likelihood
    # order (the default share order deals each list to the modes on its own).
    engine = SuggestionEngine(engine.artifacts, settings.model_copy(
        update={"complement_candidates": min(40, settings.max_k), "suggest_order": "likelihood"}))
    checked = engine.suggest(query.points, SuggestOptions(k=k, complement_check=True))
    plain = engine.suggest(query.points, SuggestOptions(k=engine.config.complement_candidates,
                                                        complement_check=False))
    share = _canonical_share(engine, query, checked)
    covered = share >= engine.config.complement_cover_share
    # Each suggestion carries the check's measure and verdict; without the check, neither.
    np.testing.assert_allclose([x.covered_share for x in checked.suggestions], share, atol=1e-6)
    assert [x.covered for x in checked.suggestions] == covered.tolist()
    assert all(x.covered is None and x.covered_share is None for x in plain.suggestions)
    # No covered part ahead of an uncovered one, and the checked list is drawn from the plain
    # top candidates in their likelihood order on each side.
    assert not np.any(covered[:-1] & ~covered[1:])
    plain_ids = [x.part_id for x in plain.suggestions]
    checked_ids = [x.part_id for x in checked.suggestions]
    assert len(checked_ids) == k and set(checked_ids) <= set(plain_ids)
    for side in (covered, ~covered):
        ranks = [plain_ids.index(p) for p, c in zip(checked_ids, side, strict=True) if c]
        assert ranks == sorted(ranks)
    # Without the check the order is the fit key's (the log-likelihood less the fit penalties).
    s = plain.suggestions
    keys = fit_keys(np.array([x.score for x in s]), np.stack([x.scale for x in s]),
                    np.stack([x.translation - x.contact_offset for x in s]),
                    engine.catalog.translations[[x.part_index for x in s]],
                    engine.config.rank_scale_weight, engine.config.rank_move_weight)
    assert np.all(np.diff(keys) <= 1e-6 * np.maximum(1.0, np.abs(keys[1:])))


def test_complement_check_off_is_likelihood_order(engine: SuggestionEngine, settings: Settings,
                                                  query: AssemblyQuery) -> None:
    """With the check off and no fit penalties nothing reorders the ranked list: a shorter answer
    is the head of a longer one."""
    engine = SuggestionEngine(engine.artifacts, settings.model_copy(
        update={"rank_scale_weight": 0.0, "rank_move_weight": 0.0}))
    off = engine.suggest(query.points, SuggestOptions(k=10, complement_check=False))
    longer = engine.suggest(query.points, SuggestOptions(k=30, complement_check=False))
    assert [x.part_id for x in off.suggestions] == [x.part_id for x in longer.suggestions][:10]


def test_api_option_reaches_the_engine(client, engine: SuggestionEngine) -> None:
    """A request's ``complement_check`` is the engine's: the API answers as the engine does with and
    without it, on a query where the two differ (the default order is not the likelihood order, so
    the answer's order alone cannot say whether the check ran)."""
    cat = engine.catalog
    for shape in multi_part_shapes(cat, 8):
        last = [r["part_id"] for r in cat.records if r["shape_id"] == shape][-1]
        q = assembly_query(cat, shape, last, engine.artifacts.n_points)
        want = {flag: [x.part_id for x in engine.suggest(q.points, SuggestOptions(
            k=10, complement_check=flag)).suggestions] for flag in (True, False)}
        if want[True] != want[False]:
            break
    else:
        pytest.fail("the check changed the top 10 of none of 8 shapes' queries")
    body = {"points": q.points.tolist(), "k": 10}
    for flag in (True, False):
        got = client.post("/suggest", json={**body, "complement_check": flag}).json()["suggestions"]
        assert [s["part_id"] for s in got] == want[flag], flag
    bad = client.post("/suggest", json={**body, "complement_check": "yes"})
    assert bad.status_code == 422 and "error" in bad.json()


def test_check_changes_some_rankings(engine: SuggestionEngine) -> None:
    """On real held-out-style queries the check is not a no-op: some query has a part it already has
    among its plain top 10, and the check moves it back."""
    cat = engine.catalog
    changed = 0
    for shape in multi_part_shapes(cat, 8):
        last = [r["part_id"] for r in cat.records if r["shape_id"] == shape][-1]
        q = assembly_query(cat, shape, last, engine.artifacts.n_points)
        on = engine.suggest(q.points, SuggestOptions(k=10, complement_check=True))
        off = engine.suggest(q.points, SuggestOptions(k=10, complement_check=False))
        changed += [x.part_id for x in on.suggestions] != [x.part_id for x in off.suggestions]
    assert changed > 0


def test_complement_order_deals_each_group_again_from_its_likelihood_order() -> None:
    from service.suggest.complement import complement_order
    from service.suggest.preferences import share_order

    share = np.array([0.0, 0.9, 0.0, 0.0, 0.9, 0.0])           # parts 1 and 4 are covered
    scores = np.array([-1.0, -2.0, -3.0, -4.0, -5.0, -6.0])    # likelihood order
    modes = np.array([0, 0, 0, 1, 1, 1])
    weights = np.array([0.5, 0.5])
    assert complement_order(share, 0.5, scores).tolist() == [0, 2, 3, 5, 1, 4]
    dealt = complement_order(share, 0.5, scores, lambda g: share_order(modes[g], weights, 0.05))
    # Uncovered 0, 2, 3, 5 dealt to modes 0 and 1 in turn, then the covered 1 and 4 the same way.
    assert dealt.tolist() == [0, 3, 2, 5, 1, 4]
    # With only the first k answered, a group that starts past them is not dealt at all.
    calls: list[int] = []

    def counted(g: np.ndarray) -> np.ndarray:
        calls.append(len(g))
        return share_order(modes[g], weights, 0.05)

    assert complement_order(share, 0.5, scores, counted, k=4)[:4].tolist() == dealt[:4].tolist()
    assert calls == [4]
    assert complement_order(share, 0.5, scores, counted, k=5).tolist() == dealt.tolist()
    assert calls == [4, 4, 2]


def test_a_complete_shape_gets_its_parts_again_marked_covered(client, engine: SuggestionEngine) -> None:
    """Asked for more parts for a whole shape, the answer lists parts it already has, and says so:
    ``covered`` on every part lying mostly on the shape's own surface, those after the others,
    ``covered_share`` beside it; null for both when the request turns the check off."""
    cat = engine.catalog
    shape = max(multi_part_shapes(cat, 8), key=lambda sid: int(np.sum(cat.shape_of == cat.shape_code(sid))))
    rows = np.flatnonzero(cat.shape_of == cat.shape_code(shape))
    pts = (cat.part_samples(rows, 128) + cat.translations[rows][:, None, :]).reshape(-1, 3)
    body = {"points": pts.tolist(), "k": 10, "category": cat.records[rows[0]]["category"]}
    got = client.post("/suggest", json=body).json()["suggestions"]
    flags = [s["covered"] for s in got]
    share = engine.config.complement_cover_share
    assert any(flags), [s["covered_share"] for s in got]
    assert flags == sorted(flags, key=lambda f: bool(f)), flags  # no covered part before an uncovered one
    assert all((s["covered_share"] >= share) == s["covered"] for s in got)
    off = client.post("/suggest", json={**body, "complement_check": False}).json()["suggestions"]
    assert all(s["covered"] is None and s["covered_share"] is None for s in off)
