"""Preferences over g's modes: reweighting, exclusion, style filter, the mode-balanced gallery."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient
from service_testkit import AssemblyQuery

from service.errors import InputError
from service.suggest.engine import SuggestionEngine, SuggestOptions
from service.suggest.preferences import Preferences, diverse_order


def test_weights_reweight_and_exclude() -> None:
    phi = np.array([0.5, 0.3, 0.2])
    np.testing.assert_allclose(Preferences().weights(phi), phi)
    w = Preferences(mode_weights=(1.0, 2.0, 0.0)).weights(phi)
    np.testing.assert_allclose(w, [0.5 / 1.1, 0.6 / 1.1, 0.0])
    w = Preferences(exclude_modes=(0,)).weights(phi)
    np.testing.assert_allclose(w, [0.0, 0.6, 0.4])
    with pytest.raises(InputError) as err:
        Preferences(mode_weights=(0.0, 1.0, 1.0), exclude_modes=(1, 2)).weights(phi)
    assert err.value.code == "all_modes_excluded"


@pytest.mark.parametrize(("prefs", "code"), [
    (Preferences(mode_weights=(1.0, 1.0)), "bad_mode_weights"),
    (Preferences(mode_weights=(1.0, -1.0, 1.0)), "bad_mode_weights"),
    (Preferences(mode_weights=(1.0, float("nan"), 1.0)), "bad_mode_weights"),
    (Preferences(exclude_modes=(3,)), "unknown_mode"),
    (Preferences(exclude_modes=(-1,)), "unknown_mode"),
    (Preferences(exclude_modes=(0, 1, 2)), "all_modes_excluded"),
])
def test_check_refuses(prefs: Preferences, code: str) -> None:
    with pytest.raises(InputError) as err:
        prefs.check(3)
    assert err.value.code == code


def test_diverse_order_round_robin_by_weight() -> None:
    # Candidates in likelihood order, with their modes; mode 2 is the heaviest, mode 0 too light.
    modes = np.array([1, 1, 1, 2, 0, 2, 1])
    weights = np.array([0.01, 0.3, 0.69])
    order = diverse_order(modes, weights, min_weight=0.02)
    assert modes[order].tolist() == [2, 1, 2, 1, 1, 1, 0]
    assert order.tolist() == [3, 0, 5, 1, 2, 6, 4]
    assert sorted(order.tolist()) == list(range(len(modes)))


# ------------------------------------------------------------------ engine and API on artifacts


def test_exclude_mode_drops_its_parts(engine: SuggestionEngine, query: AssemblyQuery) -> None:
    base = engine.suggest(query.points, SuggestOptions(k=20, refine_contact=False))
    top_mode = base.suggestions[0].mode
    result = engine.suggest(query.points, SuggestOptions(
        k=20, refine_contact=False, preferences=Preferences(exclude_modes=(top_mode,))))
    assert all(s.mode != top_mode for s in result.suggestions)
    excluded = {s.part_id for s in base.suggestions if s.mode == top_mode}
    assert not excluded & {s.part_id for s in result.suggestions}


def test_mode_weights_favour_a_mode(engine: SuggestionEngine, query: AssemblyQuery) -> None:
    base = engine.suggest(query.points, SuggestOptions(k=20, refine_contact=False))
    modes = [s.mode for s in base.suggestions]
    # A live mode other than the first suggestion's (g's weights, not the top 20, which the
    # likelihood order may fill from one mode).
    w = base.mode_weights
    others = [m for m in np.argsort(-w).tolist() if m != modes[0] and w[m] >= 0.05]
    if not others:
        pytest.skip("g gives this query one live mode on these artifacts")
    rare = others[0]
    K = engine.artifacts.n_modes
    only = [0.0] * K
    only[rare] = 1.0
    alone = engine.suggest(query.points, SuggestOptions(
        k=20, refine_contact=False, preferences=Preferences(mode_weights=tuple(only))))
    assert alone.suggestions and all(s.mode == rare for s in alone.suggestions)
    # Boosting a mode never lowers its count in the top k: a part that overtakes one of the mode's
    # parts has a larger responsibility for the mode (> 1/K), so with a factor > K - 1 the boosted
    # mode explains it best afterwards.
    boost = [1.0] * K
    boost[rare] = 2.0 * K
    boosted = engine.suggest(query.points, SuggestOptions(
        k=20, refine_contact=False, preferences=Preferences(mode_weights=tuple(boost))))
    share = sum(s.mode == rare for s in boosted.suggestions)
    assert share >= sum(m == rare for m in modes)


def test_diversity_interleaves_modes(engine: SuggestionEngine, query: AssemblyQuery) -> None:
    """The gallery's rounds (without the complement check, which deals the parts it demotes in
    rounds of their own after the others)."""
    plain = engine.suggest(query.points, SuggestOptions(k=30, refine_contact=False, complement_check=False))
    gallery = engine.suggest(query.points, SuggestOptions(
        k=30, refine_contact=False, complement_check=False, preferences=Preferences(diversity=True)))
    modes = [s.mode for s in gallery.suggestions]
    w = gallery.mode_weights
    strong = {m for m in modes if w[m] >= engine.config.diversity_min_mode_weight}
    distinct = len(strong)
    # The first round shows one part of each mode (of at least diversity_min_mode_weight) that
    # has parts among the candidates, heaviest first; lighter modes only after them.
    assert set(modes[:distinct]) == strong
    assert [w[m] for m in modes[:distinct]] == sorted((w[m] for m in modes[:distinct]), reverse=True)
    assert all(m in strong for m in modes[:distinct])
    assert distinct >= len({s.mode for s in plain.suggestions[:distinct]})
    assert [s.rank for s in gallery.suggestions] == list(range(1, len(modes) + 1))


def test_style_filter(engine: SuggestionEngine, query: AssemblyQuery) -> None:
    styles = sorted({r["style"] for r in engine.catalog.records if r["style"]})
    style = styles[0]
    result = engine.suggest(query.points, SuggestOptions(k=10, styles=(style,), refine_contact=False))
    assert result.suggestions
    assert all(engine.catalog.records[s.part_index]["style"] == style for s in result.suggestions)
    with pytest.raises(InputError) as err:
        engine.suggest(query.points, SuggestOptions(styles=("no-such-style",)))
    assert err.value.code == "unknown_style" and style in err.value.message


def test_api_preferences(client: TestClient, query: AssemblyQuery, engine: SuggestionEngine) -> None:
    pts = query.points.tolist()
    K = engine.artifacts.n_modes
    ok = client.post("/suggest", json={"points": pts, "k": 5, "mode_weights": [1.0] * K,
                                       "exclude_modes": [0], "diversity": True, "refine_contact": False})
    assert ok.status_code == 200, ok.text
    assert all(s["mode"] != 0 for s in ok.json()["suggestions"])
    cases = [({"mode_weights": [1.0] * (K + 1)}, "bad_mode_weights"),
             ({"exclude_modes": [K]}, "unknown_mode"),
             ({"exclude_modes": list(range(K))}, "all_modes_excluded"),
             ({"style": "no-such-style"}, "unknown_style"),
             ({"mode_weights": [-1.0] * K}, "validation_error")]
    for extra, code in cases:
        r = client.post("/suggest", json={"points": pts, **extra})
        assert r.status_code == 422, (extra, r.text)
        assert r.json()["error"]["code"] == code
