"""The benchmark's perturbed queries (``training.evaluate.robustness``): seeded, and each does what
its row in the report says."""

from __future__ import annotations

import numpy as np
import pytest

from training.evaluate.protocol import Query
from training.evaluate.robustness import PERTURBATIONS, perturbed


def _query(qid: str = "chair-0001:leg") -> Query:
    pts = np.random.default_rng(0).uniform(-0.7, 0.7, (1000, 3)).astype(np.float32)
    return Query(qid=qid, category="chair", shape_id="chair-0001", setting="all_but_one",
                 present=np.arange(3), removed=np.array([3]), label="leg", style=None, points=pts)


def test_each_perturbation_is_seeded_by_the_query_and_its_name() -> None:
    q = _query()
    for name, _, _ in PERTURBATIONS:
        a, b = perturbed(q, name, 0).points, perturbed(q, name, 0).points
        assert a.dtype == np.float32 and a.shape == q.points.shape and np.array_equal(a, b), name
    assert np.array_equal(perturbed(q, "as generated", 0).points, q.points)
    moved = [perturbed(q, name, 0).points for name, _, _ in PERTURBATIONS[1:]]
    assert all(not np.array_equal(m, q.points) for m in moved)
    assert not np.array_equal(perturbed(q, "noisy", 0).points, perturbed(q, "noisy", 1).points)
    other = _query("chair-0002:leg")
    assert not np.array_equal(perturbed(q, "noisy", 0).points, perturbed(other, "noisy", 0).points)
    with pytest.raises(ValueError, match="unknown perturbation 'melted'; known: as generated, proportions"):
        perturbed(q, "melted", 0)


def test_the_perturbations_do_what_the_report_says() -> None:
    q = _query()
    p = q.points.astype(np.float64)
    # Rotated about the up (y) axis by at most 15 degrees: heights and distances to the axis kept.
    r = perturbed(q, "rotated", 0).points.astype(np.float64)
    assert np.allclose(r[:, 1], p[:, 1], atol=1e-6)
    assert np.allclose(np.hypot(r[:, 0], r[:, 2]), np.hypot(p[:, 0], p[:, 2]), atol=1e-5)
    angle = np.abs(np.arctan2(r[:, 2], r[:, 0]) - np.arctan2(p[:, 2], p[:, 0]))
    angle = np.minimum(angle, 2 * np.pi - angle)
    assert 0 < np.median(angle) <= np.deg2rad(15) + 1e-6
    # Proportions: each axis scaled about the origin by a factor within exp(+-0.4), nothing else.
    s = perturbed(q, "proportions", 0).points.astype(np.float64) / p
    factors = np.median(s, axis=0)
    assert np.allclose(s, factors, rtol=1e-5) and np.all(np.abs(np.log(factors)) <= 0.4 + 1e-6)
    # Off frame: one uniform scale within exp(+-0.2) and a move of at most 0.1 per axis.
    f = perturbed(q, "off frame", 0).points.astype(np.float64)
    scale = np.linalg.norm(f[1] - f[0]) / np.linalg.norm(p[1] - p[0])
    assert abs(np.log(scale)) <= 0.2 + 1e-6
    assert np.all(np.abs(f - scale * p).max(axis=0) <= 0.1 + 1e-5)
    # Noisy: sigma 0.02 on every coordinate.
    assert np.std(perturbed(q, "noisy", 0).points - p) == pytest.approx(0.02, rel=0.05)
    # Holed: the same count, only original points, and none left within 0.3 of some point.
    h = perturbed(q, "holed", 0).points
    assert len(h) == len(p) and {tuple(x) for x in h} <= {tuple(x) for x in q.points}
    gone = [x for x in q.points if not np.any(np.linalg.norm(h - x, axis=1) <= 0.3)]
    assert gone
