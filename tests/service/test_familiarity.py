"""The familiarity check: g's answer for a query against its answers for training partial assemblies.

The numeric parts against brute force; then the shipped model through the real app: shapes of no
known category get an ``unfamiliar_shape`` warning, held-out partial assemblies do not (labels
are never read: the partial assemblies are random part subsets of held-out shapes).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import trimesh
from fastapi.testclient import TestClient

from service.artifacts.catalog import Catalog, partial_assembly_bank
from service.settings import Settings
from service.suggest.engine import SuggestionEngine, SuggestOptions
from service.suggest.familiarity import FamiliarityCheck, Projection, calibrate_threshold, mixture_descriptor
from service.suggest.preferences import Preferences
from service.suggest.region import Region


def test_descriptor_is_means_then_log_weights():
    w = np.array([[0.5, 0.5, 0.0]], np.float32)
    m = np.arange(6, dtype=np.float32).reshape(1, 3, 2)
    d = mixture_descriptor(w, m)
    assert d.shape == (1, 9) and d.dtype == np.float32
    np.testing.assert_array_equal(d[0, :6], np.arange(6))
    np.testing.assert_allclose(d[0, 6:], [np.log(0.5), np.log(0.5), np.log(1e-6)], rtol=1e-6)


def test_distances_are_the_nearest_bank_entry():
    rng = np.random.default_rng(0)
    bank, queries = rng.normal(size=(300, 20)), rng.normal(size=(17, 20))
    check = FamiliarityCheck(bank, threshold=1.0)
    brute = np.linalg.norm(queries[:, None] - bank[None], axis=2).min(axis=1)
    np.testing.assert_allclose(check.distances(queries), brute, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(check.distances(bank[:5]), 0.0, atol=2e-3)


def test_a_projected_bank_measures_in_its_principal_subspace():
    """Descriptors that vary in 5 of 40 directions: 5 components keep every distance."""
    rng = np.random.default_rng(1)
    basis = np.linalg.qr(rng.normal(size=(40, 5)))[0].T            # (5, 40) orthonormal rows
    bank = rng.normal(size=(200, 5)) @ basis + 3.0
    queries = rng.normal(size=(7, 5)) @ basis + 3.0
    proj = Projection.fit(bank, 5)
    np.testing.assert_allclose(proj.components @ proj.components.T, np.eye(5), atol=1e-5)
    full = FamiliarityCheck(bank, threshold=1.0)
    projected = FamiliarityCheck(proj(bank), threshold=1.0, projection=proj)
    assert projected.dim == 40
    np.testing.assert_allclose(projected.distances(queries), full.distances(queries), rtol=1e-3, atol=1e-3)
    with pytest.raises(ValueError):
        FamiliarityCheck(proj(bank)[:, :4], threshold=1.0, projection=proj)


def test_calibration_ignores_the_same_shape():
    """Two answers per shape, each pair 0.01 apart, shapes 1, 2, 3 ... apart along a line: the
    nearest answer of *another* shape is what counts, never the twin."""
    x = np.repeat(np.arange(10, dtype=np.float64) * np.arange(1, 11), 2)  # 0, 0, 1, 1, 4, 4, ...
    x[1::2] += 0.01
    desc = np.stack([x, np.zeros_like(x)], axis=1)
    groups = np.repeat(np.arange(10), 2)
    assert calibrate_threshold(desc, groups, 1.0) > 10
    assert calibrate_threshold(desc, np.arange(20), 1.0) < 0.02
    with pytest.raises(ValueError):
        calibrate_threshold(desc, np.zeros(20), 0.99)
    with pytest.raises(ValueError):
        FamiliarityCheck(desc, threshold=0.0)


def _unfamiliar(engine: SuggestionEngine, points: np.ndarray) -> bool:
    res = engine.suggest(np.asarray(points, np.float32), SuggestOptions(k=5, refine_contact=False))
    return any(w.code == "unfamiliar_shape" for w in res.warnings)


def test_held_out_partial_assemblies_are_familiar(engine: SuggestionEngine, catalog: Catalog):
    """Random part subsets of 150 held-out shapes (the bank holds training shapes only): the
    threshold is the 0.99 quantile, so a few may pass it; the shipped model flags none of 648."""
    assert engine.familiarity is not None
    clouds, _ = partial_assembly_bank(catalog, 1, 1024, seed=11, split="test")
    flagged = [_unfamiliar(engine, p) for p in clouds[:150]]
    assert np.mean(flagged) <= 0.03, np.mean(flagged)


def _primitives(rng: np.random.Generator) -> dict[str, np.ndarray]:
    ball = rng.normal(size=(2000, 3))
    ball *= (rng.uniform(0, 1, (2000, 1)) ** (1 / 3)) / np.linalg.norm(ball, axis=1, keepdims=True)
    t = np.linspace(0, 20, 2000)
    return {"sphere": trimesh.creation.icosphere(3, 0.7).sample(2000),
            "torus": trimesh.creation.torus(0.6, 0.15).sample(2000),
            "cone": trimesh.creation.cone(0.5, 1.2).sample(2000),
            "helix": np.stack([0.6 * np.cos(t), t / 20 - 0.5, 0.6 * np.sin(t)], 1),
            "ball": 0.7 * ball,
            "boxes": np.concatenate([trimesh.creation.box(rng.uniform(0.05, 0.6, 3)).apply_translation(
                rng.uniform(-0.5, 0.5, 3)).sample(400) for _ in range(5)])}


def test_shapes_of_no_known_category_are_unfamiliar(engine: SuggestionEngine):
    """The category head is sure of these (a torus is "watercraft 0.95"); the check is not fooled.
    Of 33 such shapes at three sizes the 24,000-step model flagged 55% (the model before it 79%:
    docs/training.md "Unfamiliar shapes"); of these six, at most one may be missed."""
    shapes = _primitives(np.random.default_rng(0))
    missed = [name for name, pts in shapes.items() if not _unfamiliar(engine, pts)]
    assert len(missed) <= 1, missed


def test_the_warning_reaches_the_answer(client: TestClient):
    torus = trimesh.creation.torus(0.6, 0.15).sample(1500)
    body = client.post("/suggest", json={"points": np.round(torus, 5).tolist(), "k": 3}).json()
    codes = [w["code"] for w in body["warnings"]]
    assert "unfamiliar_shape" in codes, body["warnings"]
    warning = next(w for w in body["warnings"] if w["code"] == "unfamiliar_shape")
    assert "training shape" in warning["message"] and "threshold" in warning["message"]
    assert warning["guess"] is True       # what the page and the Blender add-on show beside the answer
    assert len(body["suggestions"]) == 3  # a warning, not a refusal


def test_the_check_can_be_turned_off_or_loosened(engine: SuggestionEngine, settings: Settings):
    torus = np.asarray(trimesh.creation.torus(0.6, 0.15).sample(1500), np.float32)
    options = SuggestOptions(k=3, refine_contact=False)
    assert _unfamiliar(engine, torus)
    off = SuggestionEngine(engine.artifacts, settings.model_copy(update={"familiarity_check": False}))
    assert off.familiarity is None and not _unfamiliar(off, torus)
    loose = SuggestionEngine(engine.artifacts, settings.model_copy(update={"familiarity_threshold": 1e3}))
    assert loose.familiarity is not None and loose.familiarity.threshold == 1e3
    assert not any(w.code == "unfamiliar_shape" for w in loose.suggest(torus, options).warnings)


def test_an_unfamiliar_shape_can_be_answered_one_part_of_each_kind(engine: SuggestionEngine,
                                                                   settings: Settings, catalog: Catalog):
    """``unfamiliar_diversity`` (off by default): a query far past the familiarity threshold is
    answered as the diversity gallery it could have asked for, one part of each of g's modes
    first, rather than several of the kind g rates first; a familiar query, and a warned one
    that names a spot, keep their order."""
    torus = np.asarray(trimesh.creation.torus(0.6, 0.15).sample(1500), np.float32)
    options = SuggestOptions(k=5, refine_contact=False)
    assert not settings.unfamiliar_diversity
    hedging = SuggestionEngine(engine.artifacts, settings.model_copy(update={"unfamiliar_diversity": True}))

    def ids(points: np.ndarray, opts: SuggestOptions, eng: SuggestionEngine = hedging) -> list[str]:
        return [s.part_id for s in eng.suggest(points, opts).suggestions]

    hedged = hedging.suggest(torus, options)
    warning = next(w for w in hedged.warnings if w.code == "unfamiliar_shape")
    assert "diversity" in warning.message
    asked = replace(options, preferences=Preferences(diversity=True))
    assert ids(torus, options) == ids(torus, asked, engine)
    as_ordered = engine.suggest(torus, options)
    assert [s.part_id for s in hedged.suggestions] != [s.part_id for s in as_ordered.suggestions]
    assert len({s.mode for s in hedged.suggestions}) > len({s.mode for s in as_ordered.suggestions})
    assert "diversity" not in next(w for w in as_ordered.warnings if w.code == "unfamiliar_shape").message
    # Only far enough past the threshold (``unfamiliar_diversity_ratio``): a torus is far past it.
    near = SuggestionEngine(engine.artifacts, settings.model_copy(
        update={"unfamiliar_diversity": True, "unfamiliar_diversity_ratio": 1e6}))
    assert ids(torus, options, near) == ids(torus, options, engine)
    spot = replace(options, region=Region.ball(np.array([0.0, -0.3, 0.0]), 0.4))
    assert ids(torus, spot) == ids(torus, spot, engine)
    spotted = next(w for w in hedging.suggest(torus, spot).warnings if w.code == "unfamiliar_shape")
    assert "diversity" not in spotted.message
    clouds, _ = partial_assembly_bank(catalog, 1, 1024, seed=11, split="test")
    for cloud in clouds[:5]:
        assert ids(cloud, options) == ids(cloud, options, engine)
