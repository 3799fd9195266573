"""The answer order's fit key (service.suggest.fit_rank): the formula, and the engine ordering by it."""

from __future__ import annotations

import numpy as np
import pytest
from service_testkit import AssemblyQuery

from service.settings import Settings
from service.suggest.engine import SuggestionEngine, SuggestOptions
from service.suggest.fit_rank import fit_keys


def test_fit_keys_subtract_log_scale_and_move() -> None:
    scores = np.array([10.0, 10.0, 10.0, 9.0])
    scales = np.array([[1, 1, 1], [2, 2, 2], [1, 1, 1], [1, 1, 1]], dtype=float)
    centres = np.array([[0, 0, 0], [0, 0, 0], [0.3, 0.4, 0], [0, 0, 0]], dtype=float)
    own = np.zeros((4, 3))
    keys = fit_keys(scores, scales, centres, own, scale_weight=2.0, move_weight=10.0)
    np.testing.assert_allclose(keys, [10.0, 10.0 - 2.0 * np.log(2.0), 10.0 - 10.0 * 0.5, 9.0])
    # A half-size part is as far from fitting as a double-size one.
    half = fit_keys(scores[:1], np.full((1, 3), 0.5), centres[:1], own[:1], 2.0, 0.0)
    np.testing.assert_allclose(half, [10.0 - 2.0 * np.log(2.0)])
    # Weights 0: the log-likelihoods themselves.
    np.testing.assert_array_equal(fit_keys(scores, scales, centres, own, 0.0, 0.0), scores)
    assert fit_keys(np.zeros(0), np.ones((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), 1.0, 1.0).shape == (0,)


def _engine(engine: SuggestionEngine, settings: Settings, **update: object) -> SuggestionEngine:
    base = {"suggest_complement_check": False, "suggest_order": "likelihood", "infer_category": False}
    return SuggestionEngine(engine.artifacts, settings.model_copy(update={**base, **update}))


def _moves(engine: SuggestionEngine, result) -> np.ndarray:  # type: ignore[no-untyped-def]
    cat = engine.catalog
    return np.array([np.linalg.norm(s.translation - s.contact_offset - cat.translations[s.part_index])
                     for s in result.suggestions])


@pytest.mark.parametrize("weight", [0.0, 25.0, 1000.0])
def test_the_answer_is_in_fit_key_order(engine: SuggestionEngine, settings: Settings, query: AssemblyQuery,
                                        weight: float) -> None:
    """With the check off and the likelihood order, the answer is sorted by the key it documents,
    read back from the answer's own fields; weights 0 leave the likelihood order."""
    e = _engine(engine, settings, rank_move_weight=weight, rank_scale_weight=weight / 2,
                suggest_refine_contact=False)
    result = e.suggest(query.points, SuggestOptions(k=20, fit_scale=True))
    s = result.suggestions
    assert len(s) == 20
    keys = fit_keys(np.array([x.score for x in s]), np.stack([x.scale for x in s]),
                    np.stack([x.translation for x in s]),
                    e.catalog.translations[[x.part_index for x in s]], weight / 2, weight)
    assert np.all(np.diff(keys) <= 1e-6 * np.maximum(1.0, np.abs(keys[1:])))


def test_fit_penalties_reorder_the_same_candidates(engine: SuggestionEngine, settings: Settings,
                                                   query: AssemblyQuery) -> None:
    """The key only reorders: with k at the shortlist both answers hold the same parts; and a
    heavy move weight brings parts that sat near their placed spot into the top 5."""
    k = min(settings.complement_candidates, settings.max_k)   # the shortlist either way
    plain = _engine(engine, settings, rank_move_weight=0.0, rank_scale_weight=0.0, complement_candidates=k)
    moved = _engine(engine, settings, rank_move_weight=1000.0, rank_scale_weight=0.0, complement_candidates=k)
    a = plain.suggest(query.points, SuggestOptions(k=k))
    b = moved.suggest(query.points, SuggestOptions(k=k))
    assert sorted(s.part_id for s in a.suggestions) == sorted(s.part_id for s in b.suggestions)
    assert [s.part_id for s in a.suggestions[:5]] != [s.part_id for s in b.suggestions[:5]]
    assert np.mean(_moves(moved, b)[:5]) < np.mean(_moves(plain, a)[:5])
