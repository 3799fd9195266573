"""Distances between point sets: the symmetric Chamfer distance, the one owner of its formula.

The catalog's duplicate search, the trainer's shape look-alikes and automatic assembly's
duplicate test all ask how far apart two samplings of surfaces are; they share this definition
(the mean of the two one-sided mean nearest-neighbour distances), so a threshold means the same
in each. Callers that test many pairs pass the KD-trees they keep.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree


def chamfer_distance(a: np.ndarray, b: np.ndarray, tree_a: cKDTree | None = None,
                     tree_b: cKDTree | None = None) -> float:
    """Symmetric mean nearest-neighbour distance between two point sets (``tree_a``/``tree_b``:
    KD-trees of ``a``/``b`` when the caller keeps them; built here when None).

    Shapes:
        a (n, 3), b (m, 3) -> float.
    """
    da, _ = (tree_b if tree_b is not None else cKDTree(b)).query(a)
    db, _ = (tree_a if tree_a is not None else cKDTree(a)).query(b)
    return float(0.5 * (da.mean() + db.mean()))


def chamfer_below(a: np.ndarray, b: np.ndarray, distance: float, tree_a: Callable[[], cKDTree],
                  tree_b: Callable[[], cKDTree]) -> bool:
    """Whether ``chamfer_distance(a, b) < distance``, settled as early as the bounds allow.

    ``tree_a`` and ``tree_b`` return the sets' KD-trees when called (a caller caches them; ``a``'s
    tree is only asked for when the first side does not decide). Half of the one-sided mean from
    ``a`` to ``b`` already bounds the symmetric mean from below, and settles most pairs without
    building ``a``'s tree (two thirds of an assembly's time went to these trees and queries).

    Shapes:
        a (n, 3), b (m, 3).
    """
    # First with the search cut at 4 x distance (a pruned search is fast): a far point then
    # counts as the cut, which only lowers the mean, so the bound stays a bound.
    cut = 4.0 * distance
    d1, _ = tree_b().query(a, k=1, distance_upper_bound=cut)
    if 0.5 * float(np.minimum(d1, cut).mean()) >= distance:
        return False
    far = ~np.isfinite(d1)
    if np.any(far):  # only the points past the cut need the full search
        d1[far] = tree_b().query(a[far], k=1)[0]
    half = 0.5 * float(d1.mean())
    if half >= distance:
        return False
    d2, _ = tree_a().query(b, k=1)
    return half + 0.5 * float(d2.mean()) < distance
