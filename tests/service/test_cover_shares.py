"""The compiled cover shares (``service.suggest.contact_kernel.cover_shares``, on contact
refinement's grids) are the k-d tree's: for each part, the share of its samples with a sample of
another part strictly closer than the distance, the squared distance summed axis by axis as
``scipy.spatial.cKDTree`` sums it. Compared on random
shapes, on samples placed exactly at the bound, and on the shipped catalog's training shapes."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from service.artifacts.catalog import Catalog, drawn_training_shapes
from service.suggest.contact_kernel import cover_shares


def _tree_shares(clouds: list[np.ndarray], distance: float) -> np.ndarray:
    """What ``own_cover_shares`` computed before the kernel: a k-d tree of the rest per part."""
    out = []
    for j, pts in enumerate(clouds):
        rest = [c for i, c in enumerate(clouds) if i != j]
        if not rest:
            out.append(0.0)
            continue
        d, _ = cKDTree(np.concatenate(rest)).query(pts, k=1, distance_upper_bound=distance)
        out.append(float(np.mean(np.isfinite(d))))
    return np.asarray(out)


def _kernel_shares(clouds: list[np.ndarray], distance: float) -> np.ndarray:
    start = np.concatenate([[0], np.cumsum([len(c) for c in clouds])]).astype(np.int64)
    return cover_shares(np.concatenate(clouds), start, distance)


def test_random_shapes_get_the_k_d_trees_shares() -> None:
    """Parts of 1 to 300 samples, touching, overlapping, apart, at scales from a hundredth to a
    thousand times the distance."""
    rng = np.random.default_rng(0)
    for trial in range(300):
        n = int(rng.integers(1, 8))
        spread = 10.0 ** rng.uniform(-2, 3)
        clouds = [rng.normal(size=3) * spread + rng.normal(size=(int(rng.integers(1, 300)), 3)) * spread * 0.3
                  for _ in range(n)]
        distance = float(rng.choice([0.01, 0.05, 0.2, 1.0]))
        assert np.array_equal(_kernel_shares(clouds, distance), _tree_shares(clouds, distance)), trial


def test_a_sample_exactly_at_the_distance_is_not_covered() -> None:
    """0.25 and its square are exact in float64: a sample 0.25 away along an axis is at the bound,
    not below it, for the tree and the kernel alike; one a step closer is covered."""
    a = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    at = np.array([[0.25, 0.0, 0.0]])
    closer = np.array([[np.nextafter(0.25, 0.0), 0.0, 0.0]])
    for clouds, want in (([a, at], [0.0, 0.0]), ([a, closer], [1.0, 1.0])):
        assert _tree_shares(clouds, 0.25).tolist() == want
        assert _kernel_shares(clouds, 0.25).tolist() == want
    assert _kernel_shares([a, closer], 0.0).tolist() == [0.0, 0.0]        # nothing is closer than 0
    assert _kernel_shares([a], 0.25).tolist() == [0.0]                    # no other part


def test_the_catalogs_training_shapes_get_the_k_d_trees_shares(catalog: Catalog) -> None:
    for category in ("car", "lamp"):
        for _, rows in drawn_training_shapes(catalog, category, 40, seed=1):
            clouds = [catalog.part_points(i).astype(np.float64) + catalog.translations[i] for i in rows]
            assert np.array_equal(_kernel_shares(clouds, 0.05), _tree_shares(clouds, 0.05))
