"""Model v3 as the service serves it: the inferred category, the mode share of the suggestions,
size fitting and the warnings of queries the model does not know (docs/modeling.md).

These run on the shipped artifacts (exported/); labels are read here only to measure.
"""

from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh
from fastapi.testclient import TestClient
from service_testkit import assembly_query

from service.artifacts.catalog import Catalog
from service.geometry.frames import Frame
from service.suggest.engine import SuggestionEngine, SuggestOptions
from service.suggest.preferences import share_order, spread_order


def _held_out_shapes(catalog: Catalog, per_category: int) -> list[str]:
    counts = np.bincount(catalog.shape_of)
    by_cat: dict[str, list[str]] = {}
    for i, r in enumerate(catalog.records):
        if r.get("split") == "test" and counts[catalog.shape_of[i]] >= 3:
            ids = by_cat.setdefault(r["category"], [])
            if r["shape_id"] not in ids and len(ids) < per_category:
                ids.append(r["shape_id"])
    return [sid for ids in by_cat.values() for sid in ids]


def _needs_heads(engine: SuggestionEngine) -> None:
    if not (engine.networks.has_category_head and engine.networks.has_scale_head):
        pytest.skip("these artifacts predate model v3 (no category or scale head)")


def test_share_order_deals_slots_in_proportion_to_the_weights() -> None:
    modes = np.repeat([0, 1, 2, 3], 10)                   # 10 candidates per mode, any order
    rng = np.random.default_rng(0)
    modes = modes[rng.permutation(len(modes))]
    order = share_order(modes, np.array([0.5, 0.3, 0.17, 0.03]), min_weight=0.05)
    first10 = modes[order[:10]]
    assert [int(np.sum(first10 == k)) for k in range(4)] == [5, 3, 2, 0]
    assert sorted(order.tolist()) == list(range(len(modes)))   # a permutation
    light = np.flatnonzero(modes[order] == 3)
    assert light.min() == 30                                  # the light mode comes after the others
    within = [p for p in order.tolist() if modes[p] == 0]
    assert within == sorted(within)                           # each mode keeps its likelihood order


def test_the_share_order_keeps_its_head_in_likelihood_order_and_counts_it() -> None:
    modes = np.array([0, 0, 0, 1, 0, 2, 1, 0, 2, 1, 0, 2])    # likelihood order: mode 0 surest
    order = share_order(modes, np.array([0.5, 0.3, 0.2]), min_weight=0.05, head=3)
    assert order[:3].tolist() == [0, 1, 2]                    # the head as ranked
    # Mode 0 already has 3 of the slots: the next go to modes 1 and 2 (quotients 0.3, 0.2 and
    # 0.3 / 3 against 0.5 / 7), and mode 0 comes back only after them.
    assert modes[order[3:6]].tolist() == [1, 2, 1]
    assert sorted(order.tolist()) == list(range(len(modes)))
    assert share_order(modes, np.array([0.5, 0.3, 0.2]), 0.05, head=99).tolist() == list(range(12))


def test_spread_order_moves_near_copies_behind_the_other_parts() -> None:
    sigmas = np.full((2, 4), 0.1)
    emb = np.array([[0, 0, 0, 0],        # head
                    [1, 0, 0, 0],        # head (a near-copy in the head stays)
                    [0.05, 0, 0, 0],     # 0.25 sigma from the first: waits
                    [0, 1, 0, 0],
                    [0, 1.02, 0, 0],     # a near-copy of the one before: waits
                    [0, 0, 1, 0],
                    [0, 0, 0, 1]], dtype=np.float64)
    modes = np.array([0, 1, 0, 1, 0, 1, 0])
    order = spread_order(emb, modes, sigmas, head=2, k=5, min_sigmas=1.0)
    assert order.tolist() == [0, 1, 3, 5, 6, 2, 4]
    assert spread_order(emb, modes, sigmas, head=2, k=5, min_sigmas=0).tolist() == list(range(7))
    # Once k parts are shown the rest keeps its order; a head past the list changes nothing.
    assert spread_order(emb, modes, sigmas, head=2, k=3, min_sigmas=1.0).tolist() == [0, 1, 3, 2, 4, 5, 6]
    assert spread_order(emb, modes, sigmas, head=9, k=5, min_sigmas=1.0).tolist() == list(range(7))
    # Distances are in the candidate's own mode's sigmas: a wide mode takes more as a copy.
    wide = np.array([[0.1] * 4, [10.0] * 4])
    assert spread_order(emb, modes, wide, head=2, k=5, min_sigmas=1.0).tolist() == [0, 1, 4, 6, 2, 3, 5]


def _spread_one_by_one(emb: np.ndarray, modes: np.ndarray, sigmas: np.ndarray, head: int, k: int,
                       min_sigmas: float) -> list[int]:
    """The spread's definition, part after part: what ``spread_order`` computes in vector steps."""
    shown, waiting = list(range(min(head, len(modes)))), []
    i = len(shown)
    while i < len(modes) and len(shown) < k:
        z = (emb[shown] - emb[i]) / sigmas[modes[i]]
        if shown and np.sqrt(np.mean(z * z, axis=1)).min() < min_sigmas:
            waiting.append(i)
        else:
            shown.append(i)
        i += 1
    return shown + waiting + list(range(i, len(modes)))


def test_spread_order_matches_its_definition_on_clustered_parts() -> None:
    rng = np.random.default_rng(3)
    for trial in range(40):
        n, d, kk = int(rng.integers(1, 60)), 6, 4
        centres = rng.normal(0, 1, (5, d))
        emb = centres[rng.integers(0, 5, n)] + rng.normal(0, 0.05, (n, d))   # near-copies in clusters
        modes = rng.integers(0, kk, n)
        sigmas = rng.uniform(0.05, 0.5, (kk, d))
        head, k, tau = int(rng.integers(0, 6)), int(rng.integers(1, 12)), float(rng.choice([0.5, 1.0, 3.0]))
        got = spread_order(emb, modes, sigmas, head, k, tau).tolist()
        assert got == _spread_one_by_one(emb, modes, sigmas, head, k, tau), trial


def test_the_spread_keeps_the_head_and_shows_no_near_copy_after_it(artifacts: object,
                                                                  catalog: Catalog) -> None:
    """A seat alone, through the engine: with the spread on, the head is as before and no part
    after it lies within one of its mode's sigmas of a part shown before it. (A shortlist of 256:
    near-copies wait only while other parts are left, and the shipped 96 can run out of those
    for a lone seat at a spread of 1.0.)"""
    from service_testkit import make_settings

    from service.artifacts.loading import load_served_artifacts

    row = catalog.lookup("chair-0000/1")
    points = (catalog.part_points(row) + catalog.translations[row]).astype(np.float32)
    options = SuggestOptions(k=10, categories=("chair",), refine_contact=False)
    answers = {}
    for spread in (0.0, 1.0):
        settings = make_settings(artifacts, share_spread_sigmas=spread,  # type: ignore[arg-type]
                                 complement_candidates=256)
        engine = SuggestionEngine(load_served_artifacts(settings), settings)
        answers[spread] = engine.suggest(points, options)
    off, on = answers[0.0], answers[1.0]
    head = make_settings(artifacts).share_order_head  # type: ignore[arg-type]
    assert [s.part_id for s in on.suggestions[:head]] == [s.part_id for s in off.suggestions[:head]]
    emb = catalog.embeddings[[s.part_index for s in on.suggestions]].astype(np.float64)
    sigmas = on.mode_sigmas.astype(np.float64)
    for i in range(head, len(emb)):
        z = (emb[:i] - emb[i]) / sigmas[on.suggestions[i].mode]
        assert np.sqrt(np.mean(z * z, axis=1)).min() >= 1.0, i
    assert len({s.label for s in on.suggestions}) > len({s.label for s in off.suggestions})


def test_the_share_order_gives_each_live_mode_its_share(artifacts: object, query: object) -> None:
    from service_testkit import make_settings

    from service.artifacts.loading import load_served_artifacts

    # Every slot dealt (no head in likelihood order): the apportionment itself.
    settings = make_settings(artifacts, suggest_order="share", share_order_head=0,  # type: ignore[arg-type]
                             share_spread_sigmas=0)
    engine = SuggestionEngine(load_served_artifacts(settings), settings)
    k = 20
    result = engine.suggest(query.points, SuggestOptions(k=k, refine_contact=False,  # type: ignore[attr-defined]
                                                         complement_check=False))
    w = result.mode_weights.astype(np.float64)
    seq = [s.mode for s in result.suggestions]
    heavy = [m for m in seq if w[m] >= settings.share_min_mode_weight]
    assert len(set(heavy)) >= 2, (seq, w)       # a multimodal model: several modes get slots
    # No light mode ahead of a live one.
    assert seq[:len(heavy)] == heavy, (seq, w)
    # Highest-averages apportionment (Sainte-Lague): each slot goes to the mode with the largest
    # phi_k / (2 slots_k + 1) among the modes that still have candidates. A mode runs out when few
    # parts have it as their most responsible mode, so only the modes that show up again later
    # are known to have candidates left: the one chosen must beat each of them.
    taken = dict.fromkeys(set(heavy), 0)
    for p, m in enumerate(heavy):
        rivals = set(heavy[p:])
        best = max(rivals, key=lambda x: (w[x] / (2 * taken[x] + 1), -x))
        assert m == best, (p, heavy, w)
        taken[m] += 1


def test_category_is_inferred_when_none_is_named(engine: SuggestionEngine, catalog: Catalog) -> None:
    _needs_heads(engine)
    shapes = _held_out_shapes(catalog, 5)
    right = 0
    for sid in shapes:
        last = [r["part_id"] for r in catalog.records if r["shape_id"] == sid][-1]
        q = assembly_query(catalog, sid, last, 1000)
        truth = catalog.records[catalog.lookup(last)]["category"]
        result = engine.suggest(q.points, SuggestOptions(k=5, exclude_shapes=(sid,)))
        inferred = result.inferred_category
        assert inferred is not None and 0 <= inferred.confidence <= 1
        right += inferred.category == truth
        if inferred.applied:
            assert {s.category for s in result.suggestions} == {inferred.category}
        else:
            assert any(w.code == "category_unsure" for w in result.warnings)
    # Model v3 names 111 of 120 held-out all-but-one queries right (docs/benchmark.md has the
    # benchmark's figure); a model that reads the category from nothing gets about 1 in 9.
    assert right >= 0.85 * len(shapes), f"{right} of {len(shapes)} held-out queries got their category"
    named = engine.suggest(q.points, SuggestOptions(k=5, categories=("chair",)))
    assert named.inferred_category is None and {s.category for s in named.suggestions} == {"chair"}


# g keeps 4.9 modes of weight >= 0.05 for one part alone (v3-24k-s24000, docs/benchmark.md). In
# the default order (share: its first 5 slots as ranked, the rest dealt by Sainte-Lague) these 6
# held-out chairs' seats get [2, 2, 4, 2, 3, 3] kinds of part in the top 10; dealt by D'Hondt,
# which favours the heaviest mode, one of them got a single kind ([2, 1, 3, 2, 3, 3]).
def test_a_seat_alone_gets_several_kinds_of_part(artifacts: object, catalog: Catalog) -> None:
    from service_testkit import make_settings

    from service.artifacts.loading import load_served_artifacts

    settings = make_settings(artifacts)  # type: ignore[arg-type]
    assert settings.suggest_order == "share"
    engine = SuggestionEngine(load_served_artifacts(settings), settings)
    _needs_heads(engine)
    kinds = []
    for sid in _held_out_shapes(catalog, 6):
        rows = [i for i, r in enumerate(catalog.records) if r["shape_id"] == sid]
        seat = [i for i in rows if catalog.records[i]["label"] == "seat"]
        if catalog.records[rows[0]]["category"] != "chair" or not seat:
            continue
        points = catalog.part_points(seat[0]) + catalog.translations[seat[0]]
        result = engine.suggest(points, SuggestOptions(k=10, categories=("chair",), exclude_shapes=(sid,)))
        kinds.append(len({s.label for s in result.suggestions}))
        assert int(np.sum(result.mode_weights >= 0.05)) >= 2
    print(f"\nkinds of part in the top 10 of each seat alone: {kinds}")
    assert kinds and min(kinds) >= 2, kinds


def test_a_query_in_the_wrong_frame_is_answered_with_a_warning(engine: SuggestionEngine,
                                                              query: object) -> None:
    points = np.asarray(query.points) * 250.0 + 40.0          # type: ignore[attr-defined]
    plain = engine.suggest(points, SuggestOptions(k=3))
    assert any(w.code == "frame" and "frame.radius" in w.message for w in plain.warnings)
    framed = engine.suggest(points, SuggestOptions(k=3, frame=Frame(center=np.full(3, 40.0), radius=250.0)))
    assert not any(w.code == "frame" for w in framed.warnings)


def test_a_far_too_large_query_is_unfamiliar_and_a_held_out_one_is_not(engine: SuggestionEngine,
                                                                        catalog: Catalog) -> None:
    """The closest candidate's distance from its mode (``ood_max_mode_distance``): held-out shapes
    without one part stay within it; the same shapes four times too large, sent without a frame,
    are flagged (the shipped model: at most 1.0 against a median of 4.3, docs/settings.md)."""
    _needs_heads(engine)
    for sid in _held_out_shapes(catalog, 2):
        rows = [i for i, r in enumerate(catalog.records) if r["shape_id"] == sid]
        points = np.concatenate([catalog.part_points(i) + catalog.translations[i] for i in rows[1:]])
        given = engine.suggest(points, SuggestOptions(k=3, exclude_shapes=(sid,)))
        assert not any(w.code == "unfamiliar" for w in given.warnings), (sid, given.warnings)
        large = engine.suggest(points * 4.0, SuggestOptions(k=3, exclude_shapes=(sid,)))
        assert any(w.code == "unfamiliar" and "frame.radius" in w.message for w in large.warnings), sid


def test_fitting_scales_the_placed_box_and_can_be_turned_off(engine: SuggestionEngine,
                                                             catalog: Catalog, query: object) -> None:
    _needs_heads(engine)
    points = query.points                                     # type: ignore[attr-defined]
    ids = [s.part_id for s in engine.suggest(points, SuggestOptions(k=10)).suggestions]
    on = engine.place(points, ids, refine_contact=False, fit_scale=True).placements
    off = engine.place(points, ids, refine_contact=False, fit_scale=False).placements
    s = engine.config
    for a, b in zip(on, off, strict=True):
        i = catalog.lookup(a.part_id)
        extent = (catalog.bbox_max[i] - catalog.bbox_min[i]).astype(np.float64)
        np.testing.assert_allclose(b.scale, 1.0)
        np.testing.assert_allclose(np.asarray(b.bbox_max) - b.bbox_min, extent, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(np.asarray(a.bbox_max) - a.bbox_min, extent * a.scale, rtol=1e-5,
                                   atol=1e-6)
        np.testing.assert_allclose(a.translation, b.translation)  # fitting scales about the centre
        assert np.all((a.scale >= s.scale_min - 1e-9) & (a.scale <= s.scale_max + 1e-9))
    assert max(float(np.abs(np.log(p.scale)).max()) for p in on) > 0.01   # the head is not inert


def test_api_answers_carry_the_new_fields(client: TestClient, query: object) -> None:
    points = np.asarray(query.points).tolist()               # type: ignore[attr-defined]
    body = client.post("/suggest", json={"points": points, "k": 3}).json()
    assert "warnings" in body and "inferred_category" in body
    assert all(len(s["scale"]) == 3 for s in body["suggestions"])
    pid = body["suggestions"][0]["part_id"]
    placed = client.post("/place", json={"points": points, "part_ids": [pid], "fit_scale": False}).json()
    assert placed["placements"][0]["scale"] == [1.0, 1.0, 1.0]


def test_export_applies_a_per_axis_scale(client: TestClient, catalog: Catalog) -> None:
    pid = catalog.part_ids[0]
    sizes = []
    for scale in (1.0, [2.0, 1.0, 0.5]):
        part = {"part_id": pid, "translation": [0, 0, 0], "scale": scale}
        r = client.post("/export", json={"format": "obj", "frame": {"up_axis": "z"}, "parts": [part]})
        assert r.status_code == 200, r.text
        mesh = trimesh.load(io.BytesIO(r.content), file_type="obj", force="mesh", process=False)
        sizes.append(mesh.extents)
    # Per axis of the request's frame (z up): x doubled, y kept, z halved.
    np.testing.assert_allclose(sizes[1] / sizes[0], [2.0, 1.0, 0.5], rtol=1e-3)


def _share_order_by_slots(modes: np.ndarray, weights: np.ndarray, min_weight: float, head: int) -> list[int]:
    """The share order dealt slot by slot, as its definition reads (the test's oracle)."""
    first = min(head, len(modes))
    queues = {int(k): [i for i in np.flatnonzero(modes == k).tolist() if i >= first]
              for k in np.unique(modes) if weights[k] >= min_weight}
    taken = {k: int(np.count_nonzero(modes[:first] == k)) for k in queues}
    order, heads = list(range(first)), dict.fromkeys(queues, 0)
    while open_modes := [k for k in queues if heads[k] < len(queues[k])]:
        k = max(open_modes, key=lambda m: (weights[m] / (2 * taken[m] + 1), -m))
        order.append(queues[k][heads[k]])
        heads[k] += 1
        taken[k] += 1
    return order + [i for i in range(len(modes)) if i not in set(order)]


def test_the_share_order_equals_dealing_slot_by_slot() -> None:
    rng = np.random.default_rng(5)
    for trial in range(300):
        K = int(rng.integers(1, 9))
        w = rng.dirichlet(np.ones(K) * 0.5)
        if trial % 5 == 0:
            w = np.round(w, 1)  # ties between modes, and modes of weight 0
        modes = rng.integers(0, K, size=int(rng.integers(0, 60)))
        head, floor = int(rng.integers(0, 8)), float(rng.choice([0.0, 0.05, 0.2]))
        assert share_order(modes, w, floor, head).tolist() == _share_order_by_slots(modes, w, floor, head)
