"""Contact refinement's line search, compiled (numba): nearest samples found in a uniform grid.

``service.suggest.contact`` owns what is measured and searched (its module docstring); this module
runs that search part by part without leaving compiled code, because the same search written
with numpy and scipy's cKDTree cost 12-13 ms for the ten suggestions of the benchmark query,
most of it in some 15,000 KD-tree queries and the Python rounds around them (issue 20 asks for
3 ms). The answers are the search's own: every candidate offset in order, the first that
touches wins (``tests/service/contact_reference.py`` is the oracle the tests compare with).

What makes it fast, without changing an answer:

* nearest samples come from a uniform grid of each side's samples (a few cells around the query,
  widened ring by ring only while a closer sample can still exist);
* the samples measured (each side's nearest the other) are chosen from one pass over the pairs
  of samples within reach of each other, which gives both sides' nearest distances at once;
* when fewer than the measured count of assembly samples lie within reach of the part, the rest
  are searched nearest-first by a lower bound (balls around clusters of the part's samples) and
  only until that bound rules the others out;
* an offset is skipped when the nearest distances measured at earlier offsets prove that no
  sample can be within the tolerance there (a sample's nearest distance moves at most as far as
  the part does), or when a sample last seen inside by more than the tolerance is still that
  deep there (it is measured first): either way the offset cannot touch;
* a side whose other side has no normals (a caller's points: nothing can be inside them) gives
  only its nearest distance, each sample searched within the nearest found so far and skipped
  when its distance at h's placement, less the offset's length, already rules it out; the other
  side is measured in full, skipping samples that bound puts beyond every search, and a
  measurement stops at its first sample inside by more than the tolerance;
* the per-sample helpers are inlined: called, each passed the sides' arrays with their reference
  counts (the kernel on the refinements of 12 ``/assemble`` runs: 40 against 49 ms);
* numba's numpy error model: no division here can be by zero (cell sizes and norms are checked
  positive), so the checks Python's model adds to every division only cost time (3-9%).

Everything is in the canonical frame (unit radius), float64.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# cos(45 deg): a sample counts as inside only if it lies roughly behind its nearest samples.
BEHIND = math.sqrt(0.5)
# Cells along a grid's longest side, at most (the grid of 20,000 assembly samples stays 64^3).
_MAX_CELLS = 64
# Violating samples remembered per side and part (measured first at the next offsets).
_WITNESSES = 4
# Cells along a grid's longest side per cube root of its points: about one cell per point of a
# surface's samples near the query (finer grids visit more empty cells: measured 2-5x slower).
_PER_ROOT = 1.0
# The same for the clusters that prune the choice of measured samples (a few dozen per part).
_CLUSTER_PER_ROOT = 0.5

# A uniform grid of points (``build_grid``): its corner, cell size, cells per axis, the points'
# indices cell by cell, each cell's first entry of that order, and the points in that order.
Grid = tuple[np.ndarray, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]

# One side of the measurements: its measured samples, +1 if they move with the part (the part's
# samples) or -1 (the assembly's, which move by -o relative to a part moved by o), and the other
# side's samples, normals (read only if it has them) and grid.
Side = tuple[np.ndarray, float, np.ndarray, np.ndarray, bool, Grid]

# Directions tried besides the measured ones: the 6 axes first, then the 8 diagonals (unit).
AXES = np.concatenate([np.eye(3), -np.eye(3)])
CORNERS = np.array([(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)],
                   dtype=np.float64) / math.sqrt(3.0)

# Refinement outcomes (``refine_parts``'s ``status``).
FAR = 0          # nothing of the part or the assembly within reach of the other: left alone
TOUCHING = 1     # touching already: resolved without a move
MOVED = 2        # the first touching offset found: resolved
UNRESOLVED = 3   # no offset within the bound touches: h's translation is kept


@njit(cache=True, nogil=True, error_model="numpy")
def build_grid(pts: np.ndarray, per_root: float) -> Grid:
    """A uniform grid of points, about ``per_root`` n^(1/3) cells along its longest side.

    Shapes:
        pts (n, 3), n >= 1 -> lo (3,) the grid's corner, h the cell size, dims (3,) cells per axis,
        order (n,) point indices cell by cell, start (cells + 1,) each cell's first entry of order,
        spts (n, 3) the points in that order (read in sequence by ``nearest``).
    """
    n = pts.shape[0]
    lo = np.empty(3)
    hi = np.empty(3)
    for a in range(3):
        lo[a] = pts[0, a]
        hi[a] = pts[0, a]
    for i in range(1, n):
        for a in range(3):
            lo[a] = min(lo[a], pts[i, a])
            hi[a] = max(hi[a], pts[i, a])
    ext = max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2])
    per = min(_MAX_CELLS - 1, max(1, round(per_root * n ** (1.0 / 3.0))))
    h = ext / per if ext > 0 else 1.0
    dims = np.empty(3, np.int64)
    for a in range(3):
        dims[a] = min(_MAX_CELLS, int((hi[a] - lo[a]) / h) + 1)
    cell = np.empty(n, np.int64)
    counts = np.zeros(dims[0] * dims[1] * dims[2] + 1, np.int64)
    for i in range(n):
        c0 = min(int((pts[i, 0] - lo[0]) / h), dims[0] - 1)
        c1 = min(int((pts[i, 1] - lo[1]) / h), dims[1] - 1)
        c2 = min(int((pts[i, 2] - lo[2]) / h), dims[2] - 1)
        cell[i] = (c0 * dims[1] + c1) * dims[2] + c2
        counts[cell[i] + 1] += 1
    start = np.cumsum(counts)
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[cell[i]]] = i
        fill[cell[i]] += 1
    return lo, h, dims, order, start, np.ascontiguousarray(pts[order])


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _cell_of(x: float, lo: float, h: float) -> int:
    c = math.floor((x - lo) / h)
    return int(min(max(c, -(2.0 ** 40)), 2.0 ** 40))  # a query far off the grid stays an integer


@njit(cache=True, nogil=True, error_model="numpy")
def nearest(x0: float, x1: float, x2: float, grid: Grid, k: int, ub: float, out_d: np.ndarray,
            out_i: np.ndarray) -> None:
    """The ``k`` nearest points to x strictly within ``ub`` (as cKDTree's ``distance_upper_bound``),
    nearest first; missing ones get distance inf and index -1.

    Shapes:
        grid: of n points (``build_grid``); out_d (>= k,) float64, out_i (>= k,) int64.
    """
    lo, h, dims, order, start, spts = grid
    for j in range(k):
        out_d[j] = np.inf
        out_i[j] = -1
    ub2 = ub * ub
    c0, c1, c2 = _cell_of(x0, lo[0], h), _cell_of(x1, lo[1], h), _cell_of(x2, lo[2], h)
    n0, n1, n2 = dims[0], dims[1], dims[2]
    # Rings of cells at Chebyshev distance r around x's cell; none of the grid lies closer than r0.
    r = max(0, -c0, c0 - (n0 - 1), -c1, c1 - (n1 - 1), -c2, c2 - (n2 - 1))
    while True:
        a0, b0 = max(c0 - r, 0), min(c0 + r, n0 - 1)
        a1, b1 = max(c1 - r, 0), min(c1 + r, n1 - 1)
        a2, b2 = max(c2 - r, 0), min(c2 + r, n2 - 1)
        worst = out_d[k - 1] if out_i[k - 1] >= 0 else ub2
        for i0 in range(a0, b0 + 1):
            e0 = i0 == c0 - r or i0 == c0 + r
            g0 = max(lo[0] + i0 * h - x0, 0.0, x0 - (lo[0] + (i0 + 1) * h))
            if g0 * g0 >= worst:  # the whole slab is too far
                continue
            for i1 in range(a1, b1 + 1):
                e1 = e0 or i1 == c1 - r or i1 == c1 + r
                g1 = max(lo[1] + i1 * h - x1, 0.0, x1 - (lo[1] + (i1 + 1) * h))
                if g0 * g0 + g1 * g1 >= worst:
                    continue
                step = 1 if e1 else 2 * r
                i2 = c2 - r if not e1 else a2
                while i2 <= b2:
                    if i2 >= a2:
                        g2 = max(lo[2] + i2 * h - x2, 0.0, x2 - (lo[2] + (i2 + 1) * h))
                        if g0 * g0 + g1 * g1 + g2 * g2 < worst:  # the cell can hold a nearer point
                            cell = (i0 * n1 + i1) * n2 + i2
                            for e in range(start[cell], start[cell + 1]):
                                d0, d1, d2 = spts[e, 0] - x0, spts[e, 1] - x1, spts[e, 2] - x2
                                dd = d0 * d0 + d1 * d1 + d2 * d2
                                if dd < worst:  # insert, keeping the first found first on ties
                                    j = k - 1
                                    while j > 0 and (out_i[j - 1] < 0 or out_d[j - 1] > dd):
                                        out_d[j], out_i[j] = out_d[j - 1], out_i[j - 1]
                                        j -= 1
                                    out_d[j] = dd
                                    out_i[j] = order[e]
                                    worst = out_d[k - 1] if out_i[k - 1] >= 0 else ub2
                    i2 += step
        # Points of cells not visited yet lie farther than the visited cube's nearest face.
        bound = min(x0 - (lo[0] + (c0 - r) * h), lo[0] + (c0 + r + 1) * h - x0,
                    x1 - (lo[1] + (c1 - r) * h), lo[1] + (c1 + r + 1) * h - x1,
                    x2 - (lo[2] + (c2 - r) * h), lo[2] + (c2 + r + 1) * h - x2)
        if bound * bound >= worst or (c0 - r <= 0 and c0 + r >= n0 - 1 and c1 - r <= 0 and c1 + r >= n1 - 1
                                      and c2 - r <= 0 and c2 + r >= n2 - 1):
            break
        r += 1
    for j in range(k):  # squared distances while searching
        out_d[j] = math.sqrt(out_d[j]) if out_i[j] >= 0 else np.inf


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _inside(x0: float, x1: float, x2: float, d: np.ndarray, idx: np.ndarray, k: int,
            pts: np.ndarray, nrm: np.ndarray) -> bool:
    """Whether x lies behind every one of its ``k`` nearest samples (all present) of an oriented surface."""
    for j in range(k):
        p = idx[j]
        if p < 0:
            return False
        s = (x0 - pts[p, 0]) * nrm[p, 0] + (x1 - pts[p, 1]) * nrm[p, 1] + (x2 - pts[p, 2]) * nrm[p, 2]
        if not (math.isfinite(s) and s < -BEHIND * d[j]):
            return False
    return True


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _classify(x0: float, x1: float, x2: float, pts: np.ndarray, nrm: np.ndarray, has_nrm: bool, grid: Grid,
              nk: int, ub: float, bd: np.ndarray, bi: np.ndarray) -> bool:
    """Whether x, whose nearest sample is in bd[0], bi[0], is inside the other side's surface: its
    nearest sample first (cheap), then all ``nk`` nearest for the few that pass (bd, bi reused)."""
    if not has_nrm or bi[0] < 0 or not _inside(x0, x1, x2, bd, bi, 1, pts, nrm):
        return False
    if nk <= 1:
        return True
    d, i = bd[0], bi[0]
    nearest(x0, x1, x2, grid, nk, ub, bd, bi)
    inside = _inside(x0, x1, x2, bd, bi, nk, pts, nrm)
    bd[0], bi[0] = d, i
    return inside


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _measure(side: Side, o: np.ndarray, nk: int, ub: float, s: int, bd: np.ndarray, bi: np.ndarray
             ) -> tuple[float, bool]:
    """Sample ``s`` of one side (moved with the part by o) against the other side: its nearest
    distance (within ``ub``) and whether it is inside; the nearest sample in bd[0], bi[0]."""
    q, sign, pts, nrm, has_nrm, grid = side
    x0, x1, x2 = q[s, 0] + sign * o[0], q[s, 1] + sign * o[1], q[s, 2] + sign * o[2]
    nearest(x0, x1, x2, grid, 1, ub, bd, bi)
    return bd[0], _classify(x0, x1, x2, pts, nrm, has_nrm, grid, nk, ub, bd, bi)


@njit(cache=True, nogil=True, error_model="numpy")
def _ball(pts: np.ndarray, rows: np.ndarray) -> tuple[float, float, float, float]:
    """A ball holding ``pts[rows]``: the centre of their box and the farthest of them from it,
    a little larger so that rounding never leaves one outside."""
    mn = np.full(3, np.inf)
    mx = np.full(3, -np.inf)
    for p in rows:
        for a in range(3):
            mn[a] = min(mn[a], pts[p, a])
            mx[a] = max(mx[a], pts[p, a])
    c0, c1, c2 = 0.5 * (mn[0] + mx[0]), 0.5 * (mn[1] + mx[1]), 0.5 * (mn[2] + mx[2])
    rad = 0.0
    for p in rows:
        rad = max(rad, math.sqrt((pts[p, 0] - c0) ** 2 + (pts[p, 1] - c1) ** 2 + (pts[p, 2] - c2) ** 2))
    return c0, c1, c2, rad * (1.0 + 1e-12) + 1e-15


@njit(cache=True, nogil=True, error_model="numpy")
def _clusters(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clusters of points (the cells of a coarse grid) and a ball holding each (``_ball``).

    Shapes:
        pts (n, 3) -> order (n,) point indices cluster by cluster, start (c + 1,) each cluster's
        first entry of order, balls (c, 4) centre and radius (empty clusters: radius -1).
    """
    _, _, _, order, start, _ = build_grid(pts, _CLUSTER_PER_ROOT)
    balls = np.full((len(start) - 1, 4), -1.0)
    for c in range(len(start) - 1):
        if start[c] < start[c + 1]:
            c0, c1, c2, rad = _ball(pts, order[start[c]:start[c + 1]])
            balls[c, 0], balls[c, 1], balls[c, 2], balls[c, 3] = c0, c1, c2, rad
    return order, start, balls


@njit(cache=True, nogil=True, error_model="numpy")
def _pairs(src: np.ndarray, grid: Grid, bound: float,
           clusters: tuple[np.ndarray, np.ndarray, np.ndarray]
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every pair of a ``src`` and a ``dst`` sample strictly within ``bound`` of each other, folded
    into both sides' nearest: exact for every sample whose nearest is within the bound.

    A cluster of ``src`` (a coarse grid) whose centre is farther than the bound plus its radius
    from ``dst`` has no such pair and is skipped.

    Shapes:
        src (n, 3); grid: of the t samples of the other side, dst (``build_grid``); clusters:
        ``_clusters(src)`` ->
        d_src (n,), i_src (n,) each src sample's nearest distance and dst row (inf, -1 where none is
        within the bound); d_dst (t,), i_dst (t,) the same for dst (rows of its original order).
    """
    lo, h, dims, order, start, dst = grid
    n, t = len(src), len(dst)
    d_src = np.full(n, np.inf)
    i_src = np.full(n, -1, np.int64)
    d_dst = np.full(t, np.inf)
    i_dst = np.full(t, -1, np.int64)
    bd = np.empty(1)
    bi = np.empty(1, np.int64)
    b2 = bound * bound
    corder, cstart, balls = clusters
    for c in range(len(balls)):
        if cstart[c] == cstart[c + 1]:
            continue
        nearest(balls[c, 0], balls[c, 1], balls[c, 2], grid, 1, bound + balls[c, 3], bd, bi)
        if bi[0] < 0:
            continue
        for e in range(cstart[c], cstart[c + 1]):
            p = corder[e]
            x0, x1, x2 = src[p, 0], src[p, 1], src[p, 2]
            a0 = max(0, _cell_of(x0 - bound, lo[0], h))
            z0 = min(dims[0] - 1, _cell_of(x0 + bound, lo[0], h))
            a1 = max(0, _cell_of(x1 - bound, lo[1], h))
            z1 = min(dims[1] - 1, _cell_of(x1 + bound, lo[1], h))
            a2 = max(0, _cell_of(x2 - bound, lo[2], h))
            z2 = min(dims[2] - 1, _cell_of(x2 + bound, lo[2], h))
            best = b2
            for i0 in range(a0, z0 + 1):
                g0 = max(lo[0] + i0 * h - x0, 0.0, x0 - (lo[0] + (i0 + 1) * h))
                for i1 in range(a1, z1 + 1):
                    g1 = max(lo[1] + i1 * h - x1, 0.0, x1 - (lo[1] + (i1 + 1) * h))
                    if g0 * g0 + g1 * g1 >= b2:
                        continue
                    for i2 in range(a2, z2 + 1):
                        g2 = max(lo[2] + i2 * h - x2, 0.0, x2 - (lo[2] + (i2 + 1) * h))
                        if g0 * g0 + g1 * g1 + g2 * g2 >= b2:
                            continue
                        cell = (i0 * dims[1] + i1) * dims[2] + i2
                        for f in range(start[cell], start[cell + 1]):
                            e0, e1, e2 = dst[f, 0] - x0, dst[f, 1] - x1, dst[f, 2] - x2
                            dd = e0 * e0 + e1 * e1 + e2 * e2
                            if dd < b2:
                                if dd < best:
                                    best = dd
                                    i_src[p] = order[f]
                                if dd < d_dst[order[f]]:
                                    d_dst[order[f]] = dd
                                    i_dst[order[f]] = p
            if i_src[p] >= 0:
                d_src[p] = best
    for p in range(n):  # squared while searching
        d_src[p] = math.sqrt(d_src[p])
    for f in range(t):
        d_dst[f] = math.sqrt(d_dst[f])
    return d_src, i_src, d_dst, i_dst


@njit(cache=True, nogil=True, error_model="numpy")
def _closest(idx: np.ndarray, dist: np.ndarray, m: int) -> np.ndarray:
    """The ``m`` entries of ``idx`` with the smallest ``dist`` (ties: lower index first), in index order."""
    if len(idx) <= m:
        return idx
    return np.sort(idx[np.argsort(dist, kind="mergesort")[:m]])


@njit(cache=True, nogil=True, error_model="numpy")
def _nearest_rest(a_pts: np.ndarray, balls: np.ndarray, pgrid: Grid, d2: np.ndarray, i2: np.ndarray,
                  known: np.ndarray, m: int, ub: float, bd: np.ndarray, bi: np.ndarray) -> np.ndarray:
    """The assembly samples among which the m nearest the part are chosen, when fewer than m have
    a part sample within reach (``known``, all nearer than the rest): ``known`` and enough of the
    rest, their exact nearest distances written to d2, i2 (beyond ``ub``: distance ub or more).

    The rest are measured in the order of a lower bound of their nearest distance (to balls
    around clusters of the part's samples), each search bounded by the distance the m-th nearest
    measured so far has, and the measuring stops once the bound puts every sample left farther
    than that: the same m nearest, ties to the lower row, as measuring every sample one by one
    (as the search did before 2026-12-07; for the benchmark query's legs, whose box holds the
    seat, a part's box was no bound: that measured every sample, 0.25 ms of a 0.4 ms part).

    Shapes:
        a_pts (t, 3); balls (c, 4): ``_clusters`` of the part's samples (those ``pgrid`` holds);
        d2 (t,), i2 (t,) updated in place; known (j,) rows, j < m ->
        rows (at least m unless t < m: then all of them), in row order.
    """
    t = len(a_pts)
    if t <= m:  # all of them, however far; their distances only matter within ub
        for s in range(t):
            if i2[s] < 0:
                nearest(a_pts[s, 0], a_pts[s, 1], a_pts[s, 2], pgrid, 1, ub, bd, bi)
                d2[s], i2[s] = bd[0], bi[0]
        return np.arange(t)
    # Balls around clusters of the part's samples: a sample is at least its distance to the
    # nearest ball's surface from the part.
    rest = np.flatnonzero(i2 < 0)
    lower = np.empty(len(rest))
    for j in range(len(rest)):
        s = rest[j]
        g = np.inf
        for b in range(len(balls)):
            if balls[b, 3] < 0:
                continue  # an empty cluster
            e0, e1, e2 = a_pts[s, 0] - balls[b, 0], a_pts[s, 1] - balls[b, 1], a_pts[s, 2] - balls[b, 2]
            g = min(g, math.sqrt(e0 * e0 + e1 * e1 + e2 * e2) - balls[b, 3])
        lower[j] = max(g, 0.0)
    need = m - len(known)
    best = np.full(need, np.inf)   # the smallest distances measured so far, ascending
    chosen = np.zeros(t, np.bool_)
    for j in range(len(known)):
        chosen[known[j]] = True
    for j in np.argsort(lower, kind="mergesort"):
        worst = best[need - 1]
        if lower[j] > worst:  # every sample left is farther than the need-th nearest measured
            break
        s = rest[j]
        # Strictly within the bound, so a tie with the need-th is measured too (the lower row wins).
        nearest(a_pts[s, 0], a_pts[s, 1], a_pts[s, 2], pgrid, 1, worst * (1.0 + 1e-12) + 1e-300, bd, bi)
        if bi[0] < 0:
            continue
        d2[s], i2[s] = bd[0], bi[0]
        chosen[s] = True
        k = need - 1
        if bd[0] <= best[k]:
            while k > 0 and best[k - 1] > bd[0]:
                best[k] = best[k - 1]
                k -= 1
            best[k] = bd[0]
    return np.flatnonzero(chosen)


@njit(cache=True, nogil=True, error_model="numpy")
def _refine_one(part: np.ndarray, pnrm: np.ndarray, has_pn: bool, apts: np.ndarray, anrm: np.ndarray,
                has_an: bool, max_offset: float, tol: float, m: int, nk: int, reach: float,
                steps: np.ndarray, out_off: np.ndarray, out_state: np.ndarray) -> int:
    """One part's search (``refine_parts``): its outcome; its offset and states written out."""
    ub = reach + max_offset
    bd = np.empty(max(nk, 1))
    bi = np.empty(max(nk, 1), np.int64)
    # Assembly samples that can come within reach of the part: inside its box, grown by reach.
    plo = np.empty(3)
    phi = np.empty(3)
    for a in range(3):
        plo[a] = part[:, a].min() - reach
        phi[a] = part[:, a].max() + reach
    keep = np.zeros(len(apts), np.bool_)
    for i in range(len(apts)):
        keep[i] = (plo[0] <= apts[i, 0] <= phi[0] and plo[1] <= apts[i, 1] <= phi[1]
                   and plo[2] <= apts[i, 2] <= phi[2])
    near_a = np.flatnonzero(keep)
    if len(near_a) == 0:
        return FAR
    a_pts = np.ascontiguousarray(apts[near_a])
    a_nrm = np.ascontiguousarray(anrm[near_a]) if has_an else anrm[:1]
    agrid = build_grid(a_pts, _PER_ROOT)
    pgrid = build_grid(part, _PER_ROOT)
    # The samples measured are those nearest the other side: gap and penetration live there. Part
    # samples only if within reach of the assembly; the assembly's nearest the part, at any distance.
    # One pass over the pairs within reach gives the part samples' nearest, and the assembly
    # samples' for all that have a part sample within reach: when m do, they are the m nearest.
    clusters = _clusters(part)  # the pairs' pruning and the nearest-first search share them
    d1, i1, d2, i2 = _pairs(part, agrid, reach, clusters)
    near_p = np.flatnonzero(i1 >= 0)
    if len(near_p) == 0:
        return FAR
    r1 = _closest(near_p, d1[near_p], m)
    known = np.flatnonzero(i2 >= 0)
    if len(known) < m:
        known = _nearest_rest(a_pts, clusters[2], pgrid, d2, i2, known, m, ub, bd, bi)
    r2 = _closest(known, d2[known], m)
    q1 = np.ascontiguousarray(part[r1])
    q2 = np.ascontiguousarray(a_pts[r2])
    sides = ((q1, 1.0, a_pts, a_nrm, has_an, agrid), (q2, -1.0, part, pnrm, has_pn, pgrid))

    # h's placement, measured in full: the state before, and the directions the search tries first.
    # The nearest samples are those the choice measured (within reach < ub; or exact, cut at ub).
    zero = np.zeros(3)
    dmin = np.full(2, np.inf)
    closest = np.zeros(2, np.int64)    # per side: the measured sample nearest the other side
    nearest_of = np.zeros(2, np.int64)  # and its nearest sample there (0 where none)
    depth = 0.0
    push = np.zeros(3)
    # Each measured sample's nearest distance here, at most ub (side 0's rows, then side 1's): moved
    # by o it is at least this minus |o| from the other side, which the search below relies on.
    n0 = len(q1)
    ref = np.full(n0 + len(q2), ub)
    for side in range(2):
        q, sign, pts, nrm, has_nrm, grid = sides[side]
        chosen, dist, found = (r1, d1, i1) if side == 0 else (r2, d2, i2)
        for s in range(len(q)):
            dd, ii = dist[chosen[s]], found[chosen[s]]
            if not dd < ub:
                dd, ii = np.inf, -1
            else:
                ref[side * n0 + s] = dd
            bd[0], bi[0] = dd, ii
            inside = _classify(q[s, 0], q[s, 1], q[s, 2], pts, nrm, has_nrm, grid, nk, ub, bd, bi)
            if dd < dmin[side]:
                dmin[side], closest[side], nearest_of[side] = dd, s, max(bi[0], 0)
            if inside:  # out along the other side's normal there, deeper samples pushing harder
                depth = max(depth, dd)
                for a in range(3):
                    v = nrm[bi[0], a]
                    push[a] += sign * (v if math.isfinite(v) else 0.0) * dd
    dmin1, dmin2 = dmin[0], dmin[1]
    a1, a2, j1, j2 = closest[0], closest[1], nearest_of[0], nearest_of[1]
    near0 = min(dmin1, dmin2)
    gap0 = 0.0 if depth > 0 else near0
    out_state[0], out_state[1] = gap0, depth
    out_state[2], out_state[3] = gap0, depth
    if gap0 <= tol and depth <= tol:
        return TOUCHING
    if max_offset <= 0:
        return UNRESOLVED
    # Pull: from the closest sample to its nearest sample of the other side.
    pull = np.empty(3)
    for a in range(3):
        pull[a] = a_pts[j1, a] - q1[a1, a] if dmin1 <= dmin2 else q2[a2, a] - part[j2, a]
    dirs = np.empty((2 + len(AXES), 3))
    nd = 0
    for v in (pull, push):
        nv = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
        if nv > 1e-12 and math.isfinite(nv):
            for a in range(3):
                dirs[nd, a] = v[a] / nv
            nd += 1
    for j in range(len(AXES)):
        dirs[nd] = AXES[j]
        nd += 1

    # Full measurements so far (offset, nearest distance): bounds for the offsets to come.
    hist_o = np.empty((len(steps) * (nd + len(CORNERS)) + 1, 3))
    hist_g = np.empty(len(hist_o))
    hist_o[0] = zero
    hist_g[0] = min(near0, ub)
    nh = 1
    wit_side = np.full(2 * _WITNESSES, -1, np.int64)   # newest first
    wit_row = np.zeros(2 * _WITNESSES, np.int64)
    slack = 1e-9 * tol
    # The distance-only sides' samples (measured in full below otherwise), in the order of their bound.
    dist_only = np.ones(len(ref), np.bool_)
    dist_only[:n0] = not sides[0][4]
    dist_only[n0:] = not sides[1][4]
    by_ref = np.flatnonzero(dist_only)
    by_ref = by_ref[np.argsort(ref[by_ref], kind="mergesort")]
    o = np.empty(3)
    for pas in range(2):
        directions = dirs[:nd] if pas == 0 else CORNERS
        for t in steps:
            for u in range(len(directions)):
                for a in range(3):
                    o[a] = directions[u, a] * t
                lb = -np.inf
                for e in range(nh):
                    dx, dy, dz = o[0] - hist_o[e, 0], o[1] - hist_o[e, 1], o[2] - hist_o[e, 2]
                    lb = max(lb, hist_g[e] - math.sqrt(dx * dx + dy * dy + dz * dz))
                if lb > tol + slack:
                    continue  # no sample can be within the tolerance here
                ruled_out = False
                for w in range(2 * _WITNESSES):
                    if wit_side[w] < 0:
                        break
                    dd, inside = _measure(sides[wit_side[w]], o, nk, ub, wit_row[w], bd, bi)
                    if inside and dd > tol:
                        ruled_out = True
                        break
                if ruled_out:
                    continue
                shift = math.sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2])
                # A side whose other side has no normals (a caller's points) only gives the nearest
                # distance: its samples in the order of their bound, each searched only within the
                # nearest found so far, until the bound of those left says none can be nearer.
                near = ub
                for j in range(len(by_ref)):
                    e = int(by_ref[j])
                    if ref[e] - shift > near + slack:
                        break
                    side, s = (0, e) if e < n0 else (1, e - n0)
                    q, sign, _, _, _, grid = sides[side]
                    nearest(q[s, 0] + sign * o[0], q[s, 1] + sign * o[1], q[s, 2] + sign * o[2], grid, 1,
                            near, bd, bi)
                    if bi[0] >= 0:
                        near = bd[0]
                # The other side's samples in full (inside or not), stopping at the first inside by
                # more than the tolerance; a sample its bound puts beyond ub is neither.
                depth = 0.0
                for side in range(2):
                    if not sides[side][4]:
                        continue
                    for s in range(len(sides[side][0])):
                        if ref[side * n0 + s] - shift >= ub + slack:
                            continue
                        dd, inside = _measure(sides[side], o, nk, ub, s, bd, bi)
                        near = min(near, dd)
                        if inside:
                            depth = max(depth, dd)
                            if dd > tol:
                                wit_side[1:] = wit_side[:-1].copy()
                                wit_row[1:] = wit_row[:-1].copy()
                                wit_side[0], wit_row[0] = side, s
                                ruled_out = True
                                break
                    if ruled_out:
                        break
                if ruled_out:
                    continue
                hist_o[nh] = o
                hist_g[nh] = near
                nh += 1
                gap = 0.0 if depth > 0 else near
                if gap <= tol and depth <= tol:
                    out_off[:] = o
                    out_state[2], out_state[3] = gap, depth
                    return MOVED
    return UNRESOLVED


@njit(cache=True, nogil=True, error_model="numpy")
def refine_parts(ppts: np.ndarray, pnrm: np.ndarray, has_pn: np.ndarray, pstart: np.ndarray,
                 pcount: np.ndarray, apts: np.ndarray, anrm: np.ndarray, has_an: bool, max_offset: float,
                 tol: float, m: int, nk: int, reach: float, steps: np.ndarray, out_off: np.ndarray,
                 out_state: np.ndarray, status: np.ndarray) -> None:
    """The line search of each part against one assembly (``service.suggest.contact.refine_offsets``).

    Shapes:
        ppts, pnrm (P, 3): the parts' samples and normals, part j at rows pstart[j]:pstart[j] + pcount[j];
        has_pn (n,) bool; apts, anrm (A, 3) the assembly's (anrm unread unless has_an); steps (t,)
        the line search's step lengths ->
        out_off (n, 3) offsets (zero unless MOVED), out_state (n, 4) gap and depth before, then
        after, status (n,) one of FAR, TOUCHING, MOVED, UNRESOLVED.
    """
    for j in range(len(pstart)):
        out_off[j] = 0.0
        out_state[j] = 0.0
        if pcount[j] == 0:
            status[j] = FAR
            continue
        rows = slice(pstart[j], pstart[j] + pcount[j])
        status[j] = _refine_one(ppts[rows], pnrm[rows], has_pn[j], apts, anrm, has_an, max_offset, tol, m, nk,
                                reach, steps, out_off[j], out_state[j])


@njit(cache=True, nogil=True, error_model="numpy")
def cover_shares(points: np.ndarray, start: np.ndarray, distance: float) -> np.ndarray:
    """For each part of one shape, the share of its samples with a sample of another part strictly
    within ``distance`` (``nearest``'s bound, as cKDTree's ``distance_upper_bound``): how much real
    parts lie on each other (``service.modeling.assembly.own_cover_shares``).

    Each part's grid is built once and searched only from the samples of the other parts that its
    box, grown by the distance, holds and that no part covered yet.

    Shapes:
        points (M, 3) float64, part p's samples at start[p]:start[p + 1]; start (parts + 1,) int64
        -> (parts,) float64.
    """
    n_parts = len(start) - 1
    out = np.zeros(n_parts)
    if not distance > 0:
        return out
    covered = np.zeros(points.shape[0], np.bool_)
    bd = np.empty(1)
    bi = np.empty(1, np.int64)
    for q in range(n_parts):
        if start[q] == start[q + 1]:
            continue
        own = points[start[q]:start[q + 1]]
        grid = build_grid(own, _PER_ROOT)
        lo = np.empty(3)
        hi = np.empty(3)
        for a in range(3):
            lo[a] = own[:, a].min() - distance
            hi[a] = own[:, a].max() + distance
        for i in range(points.shape[0]):
            if covered[i] or start[q] <= i < start[q + 1]:
                continue
            x0, x1, x2 = points[i, 0], points[i, 1], points[i, 2]
            if x0 < lo[0] or x0 > hi[0] or x1 < lo[1] or x1 > hi[1] or x2 < lo[2] or x2 > hi[2]:
                continue
            nearest(x0, x1, x2, grid, 1, distance, bd, bi)
            covered[i] = bi[0] >= 0
    for p in range(n_parts):
        n = start[p + 1] - start[p]
        if n > 0:
            out[p] = covered[start[p]:start[p + 1]].sum() / n
    return out


def warm() -> None:
    """Compile (or load from numba's cache) every function above with the argument types
    ``service.suggest.contact`` passes: the first compile takes about 25 s on these machines,
    a cached load under 1 s. The Docker image runs it at build time (``python -m
    service.suggest.contact_kernel``) so that a container starts from the cache."""
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(64, 3))
    nrm = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    out_off, out_state, status = np.zeros((1, 3)), np.zeros((1, 4)), np.zeros(1, np.int64)
    refine_parts(pts, nrm, np.ones(1, np.bool_), np.zeros(1, np.int64), np.full(1, 64, np.int64),
                 pts + 0.05, nrm, True, 0.1, 0.01, 16, 4, 0.12, np.arange(1, 11) * 0.01,
                 out_off, out_state, status)
    cover_shares(pts, np.array([0, 32, 64]), 0.05)


if __name__ == "__main__":
    warm()
