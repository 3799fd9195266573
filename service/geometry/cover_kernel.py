"""How much each part of a shape lies on the others, compiled (numba): each part's samples in a
dense table of cells over its box grown by the distance, each sample checked against the samples
of the 27 cells around it in the tables of the parts whose grown box holds it.

``service.modeling.assembly.own_cover_shares`` reads this for every training shape of a category
(300 at most) on the first ``/assemble`` of that category and catalog snapshot. With a k-d tree of
the rest of the shape built for every part that first call took 86-450 ms (against 10-100 ms for
the calls after it), past ``/assemble``'s 150 ms target, and again after every catalog write; a
grid shared by the parts, searched by binary search, took it to 34-180 ms; the tables per part
halve what is left (car: 31 against 68 ms over its training shapes).

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
    # Each part's samples in a dense table of cells over its grown box: cells at least as wide as
    # the distance (every sample nearer than it lies in one of the 27 cells around), about eight
    # cells per sample and at most 1024 along a side (wider cells only cost more samples looked
    # at), the samples sorted by cell (z fastest), each cell's first sample in ``first``.
    cell = np.empty(n_parts)
    dims = np.zeros((n_parts, 3), np.int64)
    table_at = np.zeros(n_parts + 1, np.int64)
    for p in range(n_parts):
        count = start[p + 1] - start[p]
        if count == 0:
            cell[p] = distance
            table_at[p + 1] = table_at[p] + 1
            continue
        ex = box_hi[p, 0] - box_lo[p, 0]
        ey = box_hi[p, 1] - box_lo[p, 1]
        ez = box_hi[p, 2] - box_lo[p, 2]
        cell[p] = max(distance, (ex * ey * ez / (8.0 * count)) ** (1.0 / 3.0), max(ex, ey, ez) / 1024.0)
        n_cells = 1
        for a in range(3):
            dims[p, a] = math.floor((box_hi[p, a] - box_lo[p, a]) / cell[p]) + 1
            n_cells *= dims[p, a]
        table_at[p + 1] = table_at[p] + n_cells + 1
    first = np.zeros(table_at[n_parts], np.int64)
    key = np.empty(m, np.int64)
    for i in range(m):
        p = owner[i]
        c = cell[p]
        kx = math.floor((points[i, 0] - box_lo[p, 0]) / c)
        ky = math.floor((points[i, 1] - box_lo[p, 1]) / c)
        kz = math.floor((points[i, 2] - box_lo[p, 2]) / c)
        key[i] = (kx * dims[p, 1] + ky) * dims[p, 2] + kz
        first[table_at[p] + key[i] + 1] += 1
    for p in range(n_parts):
        for t in range(table_at[p] + 1, table_at[p + 1]):
            first[t] += first[t - 1]
    order = np.empty(m, np.int64)
    fill = first.copy()
    for i in range(m):
        p = owner[i]
        slot = table_at[p] + key[i]
        order[start[p] + fill[slot]] = i
        fill[slot] += 1
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
            c = cell[q_part]
            kx = math.floor((points[i, 0] - box_lo[q_part, 0]) / c)
            ky = math.floor((points[i, 1] - box_lo[q_part, 1]) / c)
            kz = math.floor((points[i, 2] - box_lo[q_part, 2]) / c)
            nx, ny, nz = dims[q_part, 0], dims[q_part, 1], dims[q_part, 2]
            base = table_at[q_part]
            z0, z1 = max(kz - 1, 0), min(kz + 1, nz - 1)
            for x in range(max(kx - 1, 0), min(kx + 1, nx - 1) + 1):
                for y in range(max(ky - 1, 0), min(ky + 1, ny - 1) + 1):
                    row = (x * ny + y) * nz
                    for j in range(start[q_part] + first[base + row + z0],
                                   start[q_part] + first[base + row + z1 + 1]):
                        q = order[j]
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
