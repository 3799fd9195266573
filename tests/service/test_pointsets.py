"""The one Chamfer distance: its value, and the early-exit test that must agree with it."""

from __future__ import annotations

from functools import partial

import numpy as np
import pytest
from scipy.spatial import cKDTree

from service.geometry.pointsets import chamfer_below, chamfer_distance


def test_chamfer_distance_of_known_sets() -> None:
    a = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    b = np.array([[0.0, 0.5, 0.0]])
    # a -> b: 0.5 and sqrt(1.25); b -> a: 0.5
    want = 0.5 * ((0.5 + np.sqrt(1.25)) / 2 + 0.5)
    assert chamfer_distance(a, b) == pytest.approx(want)
    assert chamfer_distance(b, a) == pytest.approx(want)
    assert chamfer_distance(a, a) == 0.0
    assert chamfer_distance(a, b, cKDTree(a), cKDTree(b)) == chamfer_distance(a, b)


def test_the_early_exit_agrees_with_the_distance() -> None:
    """Pairs near, far and at the threshold, some with points past the pruned search's cut."""
    rng = np.random.default_rng(0)
    checked, a_trees = 0, 0
    for _ in range(200):
        a = rng.normal(size=(rng.integers(5, 60), 3)) * rng.uniform(0.01, 0.3)
        b = a[: rng.integers(1, len(a) + 1)] + rng.normal(size=3) * rng.uniform(0.0, 0.5)
        b = np.concatenate([b, rng.normal(size=(rng.integers(0, 10), 3))])   # some far points
        d = chamfer_distance(a, b)
        for distance in (0.5 * d, 0.999 * d, 1.001 * d, 2.0 * d, 0.02, 0.1):
            if distance <= 0:
                continue
            asked: list[str] = []
            tree_a, tree_b = cKDTree(a), cKDTree(b)

            def ask(name: str, tree: cKDTree, asked: list[str] = asked) -> cKDTree:
                asked.append(name)
                return tree

            got = chamfer_below(a, b, distance, partial(ask, "a", tree_a), partial(ask, "b", tree_b))
            assert got == (d < distance), (d, distance)
            checked += 1
            a_trees += "a" in asked
    assert checked > 1000
    assert 0 < a_trees < checked   # a's tree is built only when the first side does not settle it
