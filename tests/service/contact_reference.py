"""The contact refinement as it was before the batched search (commit 5dbd0ab), kept as the oracle.

``service.suggest.contact.refine_offsets`` must choose the same offsets as this reference: one part at a
time, a KD-tree per part, every candidate offset measured on all samples. Copied verbatim except
for the imports and the assembly's KD-tree, built here (the service's ``Assembly`` no longer
keeps one); the tests compare the two on synthetic contacts and on real catalog parts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from service.suggest.contact import Assembly, ContactParams, ContactState, Refinement, Surface

_BEHIND = float(np.sqrt(0.5))
_AXES = np.concatenate([np.eye(3), -np.eye(3)])
_CORNERS = np.array([(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64)
_CORNERS /= np.sqrt(3.0)


def _subsample(idx: np.ndarray, m: int, seed: int) -> np.ndarray:
    if len(idx) <= m:
        return idx
    return np.sort(np.random.default_rng(seed).choice(idx, size=m, replace=False))


def _closest(idx: np.ndarray, dist: np.ndarray, m: int) -> np.ndarray:
    """The ``m`` entries of ``idx`` with the smallest ``dist`` (ties: lower index first)."""
    if len(idx) <= m:
        return idx
    return idx[np.sort(np.argsort(dist, kind="stable")[:m])]


@dataclass
class _Probe:
    """Measurements at many offsets: gap and depth per offset, and (at one offset) the details."""

    gap: np.ndarray          # (k,)
    depth: np.ndarray        # (k,)
    pull: np.ndarray         # (k, 3) towards the nearest assembly sample (unit, or 0)
    push: np.ndarray         # (k, 3) out of the penetration, depth-weighted sum of normals


class _Search:
    """One part against one assembly, measured at many candidate offsets at once."""

    def __init__(self, part: Surface, assembly: Assembly, params: ContactParams, reach: float):
        self.params = params
        self.reach = reach
        pts = part.points
        # Assembly samples that can come within reach of the part: inside its box, grown by reach.
        lo, hi = pts.min(axis=0) - reach, pts.max(axis=0) + reach
        near_a = np.flatnonzero(np.all((assembly.points >= lo) & (assembly.points <= hi), axis=1))
        # Part samples that can come within reach of the assembly.
        d, _ = cKDTree(assembly.points).query(pts, k=1, distance_upper_bound=reach)
        near_p = np.flatnonzero(np.isfinite(d))
        self.empty = len(near_a) == 0 or len(near_p) == 0
        if self.empty:
            return
        a_norm = assembly.surface.normals
        self.a_pts = assembly.points[near_a]
        self.a_nrm = a_norm[near_a] if a_norm is not None else None
        self.a_tree = cKDTree(self.a_pts)
        self.p_pts, self.p_nrm = pts, part.normals
        self.p_tree = cKDTree(pts)
        # The samples measured are those nearest the other side: gap and penetration live there.
        m = params.search_points
        self.q_part = pts[_closest(near_p, d[near_p], m)]                                # part -> asm
        da, _ = self.p_tree.query(self.a_pts, k=1)
        self.q_asm = self.a_pts[_closest(np.arange(len(near_a)), da, m)]                 # asm -> part

    def probe(self, offsets: np.ndarray, directions: bool = True) -> _Probe:
        """Gap, depth and the directions that would improve them, for the part moved by each offset.

        ``directions=False`` leaves ``pull`` and ``push`` zero (the line search needs only gap
        and depth once its directions are chosen).

        Shapes:
            offsets (k, 3) -> _Probe with (k,) and (k, 3) arrays.
        """
        k = len(offsets)
        ub = self.reach + self.params.max_offset
        # Part samples moved by o, against the assembly (x = part sample, its nearest assembly sample).
        q1 = (self.q_part[None] + offsets[:, None]).reshape(-1, 3)
        d1, i1 = self.a_tree.query(q1, k=1, distance_upper_bound=ub)
        # Assembly samples against the part moved by o, i.e. assembly samples moved by -o.
        q2 = (self.q_asm[None] - offsets[:, None]).reshape(-1, 3)
        d2, i2 = self.p_tree.query(q2, k=1, distance_upper_bound=ub)
        # Part inside the assembly: the part must move out along the assembly's normal.
        in1 = self._inside(q1, d1, i1, self.a_tree, self.a_pts, self.a_nrm, ub)
        # Assembly inside the part: the part must move against its own normal there.
        in2 = self._inside(q2, d2, i2, self.p_tree, self.p_pts, self.p_nrm, ub)
        j1 = np.where(i1 < len(self.a_pts), i1, 0)
        j2 = np.where(i2 < len(self.p_pts), i2, 0)
        d1k, d2k = d1.reshape(k, -1), d2.reshape(k, -1)
        dep1 = np.where(in1, d1, 0.0).reshape(k, -1)
        dep2 = np.where(in2, d2, 0.0).reshape(k, -1)
        depth = np.maximum(dep1.max(axis=1), dep2.max(axis=1))
        gap = np.where(depth > 0, 0.0, np.minimum(d1k.min(axis=1), d2k.min(axis=1)))
        push = np.zeros((k, 3))
        if not directions:
            return _Probe(gap=gap, depth=depth, pull=push, push=push)
        if self.a_nrm is not None:
            push += (np.nan_to_num(self.a_nrm[j1]) * dep1.reshape(-1, 1)).reshape(k, -1, 3).sum(axis=1)
        if self.p_nrm is not None:
            push -= (self.p_nrm[j2] * dep2.reshape(-1, 1)).reshape(k, -1, 3).sum(axis=1)
        # Pull: from the closest part sample to its nearest assembly sample.
        a1, a2 = d1k.argmin(axis=1), d2k.argmin(axis=1)
        rows = np.arange(k)
        v1 = self.a_pts[j1.reshape(k, -1)[rows, a1]] - q1.reshape(k, -1, 3)[rows, a1]
        v2 = q2.reshape(k, -1, 3)[rows, a2] - self.p_pts[j2.reshape(k, -1)[rows, a2]]
        pull = np.where((d1k[rows, a1] <= d2k[rows, a2])[:, None], v1, v2)
        pull = np.where(np.isfinite(pull), pull, 0.0)
        return _Probe(gap=gap, depth=depth, pull=_unit(pull), push=push)


    def _inside(self, x: np.ndarray, d: np.ndarray, i: np.ndarray, tree: cKDTree, pts: np.ndarray,
                nrm: np.ndarray | None, ub: float) -> np.ndarray:
        """Inside test of samples ``x`` whose nearest samples (``d``, ``i``) are known: the nearest
        one first (cheap), then all ``inside_neighbours`` nearest for the few that pass it."""
        inside = _inside(x, d[:, None], i[:, None], pts, nrm)
        nk = self.params.inside_neighbours
        if nk > 1 and inside.any():
            rows = np.flatnonzero(inside)
            dn, jn = tree.query(x[rows], k=nk, distance_upper_bound=ub)
            inside[rows] = _inside(x[rows], dn.reshape(len(rows), -1), jn.reshape(len(rows), -1), pts, nrm)
        return inside


def _inside(x: np.ndarray, d: np.ndarray, i: np.ndarray, pts: np.ndarray,
            nrm: np.ndarray | None) -> np.ndarray:
    """Which samples ``x`` lie behind every one of their nearest samples of an oriented surface.

    Asking all the nearest samples (not only the nearest) keeps thin parts honest: a point beside
    a thin plate has samples of both faces among its neighbours, and one of them sees it outside.

    Shapes:
        x (n, 3); d, i (n, k) distances and indices of the k nearest samples (index len(pts) and
        distance inf where fewer were in range) -> (n,) bool.
    """
    if nrm is None:
        return np.zeros(len(x), dtype=bool)
    ok = i < len(pts)
    j = np.where(ok, i, 0)
    s = np.einsum("ijk,ijk->ij", x[:, None, :] - pts[j], nrm[j])
    with np.errstate(invalid="ignore"):
        behind = ok & np.isfinite(s) & (s < -_BEHIND * d)
    return behind.all(axis=1) & ok[:, 0]


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 1e-12, v / np.maximum(n, 1e-12), 0.0)


def measure_contact(part: Surface, assembly: Assembly, reach: float = 0.5) -> ContactState:
    """Sampled gap and depth of a placed part against an assembly (gap capped at ``reach``)."""
    params = ContactParams(max_offset=0.0, search_points=len(part.points) + len(assembly.points))
    search = _Search(part, assembly, params, reach)
    if search.empty:
        return ContactState(gap=float(reach), depth=0.0)
    p = search.probe(np.zeros((1, 3)))
    return ContactState(gap=float(min(p.gap[0], reach)), depth=float(p.depth[0]))


def _best_touching(search: _Search, directions: np.ndarray, steps: np.ndarray, tol: float
                   ) -> tuple[np.ndarray, ContactState] | None:
    """The smallest offset ``t u`` (u in directions, t in steps) after which the part touches.

    Steps are tried from the smallest up, all directions of a step in one probe, so the search
    stops at the first step where some direction resolves the contact (the first such direction
    wins: the measured ones come first).
    """
    for t in steps:
        offsets = directions * t
        p = search.probe(offsets, directions=False)
        ok = np.flatnonzero((p.gap <= tol) & (p.depth <= tol))
        if len(ok):
            j = int(ok[0])
            return offsets[j], ContactState(float(p.gap[j]), float(p.depth[j]))
    return None


def refine_offset(part: Surface, assembly: Assembly, params: ContactParams) -> Refinement:
    """The smallest move (within ``params.max_offset``) after which the placed part touches.

    Args:
        part: the part's samples (with normals) at h's placement, canonical frame.
        assembly: the assembly it is placed against.
        params: search bound, tolerance and sample count.

    Returns the offset to add to the translation (zero when the contact cannot be resolved
    within the bound, or needs no change) and the sampled contact before and after.
    """
    zero = np.zeros(3)
    tol = params.tolerance
    reach = params.max_offset + 2 * tol
    search = _Search(part, assembly, params, reach)
    if search.empty:  # nothing within reach: apart by design or far off; keep h's translation
        far = ContactState(gap=float(reach), depth=0.0)
        return Refinement(zero, far, far, False)
    p0 = search.probe(zero[None])
    before = ContactState(float(p0.gap[0]), float(p0.depth[0]))
    if before.touching(tol) or params.max_offset <= 0:
        return Refinement(zero, before, before, before.touching(tol))
    # Steps of one tolerance: the touching band along any direction is at least 2 tolerances wide
    # (gap from tol down to 0, then depth from 0 up to tol), so no step jumps over it.
    steps = np.arange(1, int(np.floor(params.max_offset / tol + 1e-9)) + 1) * tol
    informed = np.concatenate([p0.pull, _unit(p0.push)])
    informed = informed[np.linalg.norm(informed, axis=1) > 0]
    for directions in (np.concatenate([informed, _AXES]), _CORNERS):
        if len(directions):
            found = _best_touching(search, directions, steps, tol)
            if found is not None:
                return Refinement(found[0], before, found[1], True)
    return Refinement(zero, before, before, False)
