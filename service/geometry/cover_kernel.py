"""How much each part of a shape lies on the others, compiled (numba): a uniform grid of cells as
wide as the distance, each sample checked against the samples of the 27 cells around its own.

``service.modeling.assembly.own_cover_shares`` reads this for every training shape of a category
(300 at most) on the first ``/assemble`` of that category and catalog snapshot. With a k-d tree of
the rest of the shape built for every part that first call took 0.17-0.45 s (against 10-80 ms
for the calls after it), past ``/assemble``'s 150 ms target, and again after every catalog write.

Same answers as the k-d tree's (``scipy.spatial.cKDTree.query`` with ``distance_upper_bound``):
a sample is covered when some sample of another part lies at a squared distance, summed axis by
axis in that order, strictly below the squared distance (``tests/service/test_cover_kernel.py``
compares the two on samples placed exactly at the bound).

Shapes: points (M, 3) float64; owner (M,) int64, each sample's part in 0..n-1.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def cover_shares(points: np.ndarray, owner: np.ndarray, n_parts: int,
                 distance: float) -> np.ndarray:  # pragma: no cover - compiled
    """For each part, the share of its samples with a sample of another part closer than
    ``distance``.

    Shapes:
        points (M, 3) float64, each part's samples contiguous; owner (M,) int64 in [0, n_parts),
        non-decreasing -> (n_parts,) float64.
    """
    m = points.shape[0]
    out = np.zeros(n_parts)
    start = np.zeros(n_parts + 1, np.int64)
    for i in range(m):
        start[owner[i] + 1] += 1
    for p in range(n_parts):
        start[p + 1] += start[p]
    if m == 0 or not distance > 0:
        return out
    bound = distance * distance
    # Each part's box grown by the distance: a sample outside every other part's grown box is
    # not covered (most samples are decided here, without a search).
    box_lo = np.full((n_parts, 3), np.inf)
    box_hi = np.full((n_parts, 3), -np.inf)
    for i in range(m):
        for a in range(3):
            box_lo[owner[i], a] = min(box_lo[owner[i], a], points[i, a] - distance)
            box_hi[owner[i], a] = max(box_hi[owner[i], a], points[i, a] + distance)
    lo = np.empty(3)
    extent = 0.0
    for a in range(3):
        lo[a] = box_lo[:, a].min()
        extent = max(extent, box_hi[:, a].max() - lo[a])
    # Cells at least as wide as the distance (every sample nearer than it lies in one of the 27
    # cells around), few enough per axis for one int64 key; each part's samples in key order.
    cell = max(distance, extent / 1e6)
    size = math.floor(extent / cell) + 1
    keys = np.empty(m, np.int64)
    cells = np.empty((m, 3), np.int64)
    for i in range(m):
        for a in range(3):
            cells[i, a] = math.floor((points[i, a] - lo[a]) / cell)
        keys[i] = (cells[i, 0] * size + cells[i, 1]) * size + cells[i, 2]
    order = np.empty(m, np.int64)
    for p in range(n_parts):
        a, b = start[p], start[p + 1]
        order[a:b] = a + np.argsort(keys[a:b])
    sorted_keys = keys[order]
    for i in range(m):
        own = owner[i]
        found = False
        for q_part in range(n_parts):
            if q_part == own or start[q_part] == start[q_part + 1]:
                continue
            if (points[i, 0] < box_lo[q_part, 0] or points[i, 0] > box_hi[q_part, 0]
                    or points[i, 1] < box_lo[q_part, 1] or points[i, 1] > box_hi[q_part, 1]
                    or points[i, 2] < box_lo[q_part, 2] or points[i, 2] > box_hi[q_part, 2]):
                continue
            a, b = start[q_part], start[q_part + 1]
            for dx in range(-1, 2):
                for dy in range(-1, 2):
                    # The three cells along z are consecutive keys: one search, then a scan
                    # (past the grid's edge the keys run into the next row's cells: extra
                    # samples measured, none missed).
                    first = ((cells[i, 0] + dx) * size + cells[i, 1] + dy) * size + cells[i, 2] - 1
                    j = a + np.searchsorted(sorted_keys[a:b], first)
                    while j < b and sorted_keys[j] <= first + 2:
                        q = order[j]
                        j += 1
                        ex = points[i, 0] - points[q, 0]
                        ey = points[i, 1] - points[q, 1]
                        ez = points[i, 2] - points[q, 2]
                        if (ex * ex + ey * ey) + ez * ez < bound:
                            found = True
                            break
                    if found:
                        break
                if found:
                    break
            if found:
                break
        if found:
            out[own] += 1.0
    for p in range(n_parts):
        if start[p + 1] > start[p]:
            out[p] = out[p] / (start[p + 1] - start[p])
    return out


def warm() -> None:
    """Compile (or load from numba's cache) ``cover_shares``; the server's warm-up and the Docker
    build (``python -m service.geometry.cover_kernel``) run it."""
    cover_shares(np.zeros((2, 3)), np.arange(2, dtype=np.int64), 2, 0.05)


if __name__ == "__main__":
    warm()
