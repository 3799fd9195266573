"""Contact-aware placement: nudge a placed part so it touches the assembly without sinking into it.

The placement network h regresses a translation, and regressed translations leave parts a
little off the assembly (floating) or a little inside it (interpenetrating): the paper's own
figures show both. ``refine_offset`` looks for a small offset (at most ``max_offset``, in the
canonical unit-radius frame) after which the part touches the assembly, measuring only
nearest-neighbour distances between surface samples:

* gap: the smallest distance between a part sample and an assembly sample (0 once a sample of
  one side is inside the other);
* depth: the deepest sample of one side inside the other. A sample ``x`` is inside a surface
  when, for each of its few nearest samples ``p`` of that surface with outward normal ``n``,
  ``(x - p) . n < -cos(45 deg) |x - p|``: the closest-point sign test of a signed distance,
  kept to points roughly behind the surface so that samples beside a sharp edge do not count,
  and asked of several neighbours so that a point beside a thin plate (whose neighbours lie on
  both faces) is not taken for inside.
  Part samples always carry normals (sampled from the part's mesh); the assembly's do when it
  is made of catalog parts (``/assemble``), not when it is a caller's point cloud, where only
  assembly samples inside the part are seen.

The part *touches* when gap and depth are both within ``tolerance``. The search is a short
line search: offsets ``t u`` for ``t`` in steps of ``tolerance`` up to ``max_offset``, along
the directions the measurements point to (towards the nearest assembly sample; out along the
normals of the penetrating samples) and the 6 axes, then, if none of those resolves it, along
the 8 diagonals, and the first touching offset (smallest step, then the directions in that
order) wins. When no offset within the bound resolves the contact (a part that needs a larger
move, or sits apart from the assembly by design) the offset is zero: h's translation is kept.

How it is made fast: ``service.suggest.contact_kernel`` runs the search compiled (numba), part
by part, and skips only offsets that provably cannot touch, so its answers are those of measuring
every offset in order (``tests/service/contact_reference.py`` keeps that as the oracle).

Everything is in the canonical frame; callers map offsets to their frame like translations.
"""

from __future__ import annotations

import hashlib
import itertools
import threading
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from service.artifacts.catalog import Catalog
from service.geometry.mesh import sample_surface_faces
from service.suggest import contact_kernel as kernel


@dataclass(frozen=True)
class Surface:
    """Surface samples, with outward unit normals where known.

    Shapes:
        points: (n, 3) float64.   normals: (n, 3) float64, NaN rows where unknown; or None.
    """

    points: np.ndarray
    normals: np.ndarray | None = None

    def moved(self, offset: np.ndarray) -> Surface:
        return Surface(self.points + np.asarray(offset, dtype=np.float64).reshape(1, 3), self.normals)

    def scaled(self, scale: np.ndarray | None) -> Surface:
        """A centred part's samples scaled per axis about its centre (normals transformed by the
        inverse scale and renormalised); itself for None or a scale of ones.

        Shapes:
            scale: (3,).
        """
        if scale is None:
            return self
        return fitted_surfaces([self], np.asarray(scale, dtype=np.float64).reshape(1, 3), np.zeros((1, 3)))[0]

    @staticmethod
    def union(surfaces: list[Surface]) -> Surface:
        """All samples of several surfaces (normals NaN for those that have none)."""
        pts = np.concatenate([s.points for s in surfaces]) if surfaces else np.zeros((0, 3))
        if all(s.normals is None for s in surfaces):
            return Surface(pts, None)
        normals = [s.normals if s.normals is not None else np.full_like(s.points, np.nan) for s in surfaces]
        return Surface(pts, np.concatenate(normals))


@dataclass(frozen=True)
class ContactParams:
    """How far and how finely to search (canonical units: the complete object's radius is 1)."""

    max_offset: float = 0.1       # largest refinement move
    tolerance: float = 0.01       # gap and depth accepted as touching; also the line-search step
    search_points: int = 128      # samples per side measured at each candidate offset
    inside_neighbours: int = 4    # nearest samples that must all see a sample behind them (inside)
    seed: int = 0                 # which samples are measured when there are more
    threads: int = 1              # parts searched at once (the compiled search releases the GIL)


@dataclass(frozen=True)
class ContactState:
    """Gap and penetration depth of a placed part against an assembly (sampled estimates)."""

    gap: float
    depth: float

    def touching(self, tolerance: float) -> bool:
        return self.gap <= tolerance and self.depth <= tolerance


@dataclass(frozen=True)
class Refinement:
    """The outcome of one refinement: the offset to add (zero if not resolved) and the states.

    Shapes:
        offset: (3,) float64, canonical frame.
    """

    offset: np.ndarray
    before: ContactState
    after: ContactState
    resolved: bool


def sample_oriented(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int) -> Surface:
    """``n`` area-weighted surface samples of a mesh with their faces' outward normals (seeded).

    The samples of ``sample_surface_faces`` (the same points for the same mesh and seed).

    Shapes:
        vertices (V, 3), faces (F, 3) -> Surface of n points with normals.

    Raises:
        MeshError (a ValueError): a mesh without faces of positive area.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    pts, tri = sample_surface_faces(v, f, n, seed)
    a, b, c = v[f[tri, 0]], v[f[tri, 1]], v[f[tri, 2]]
    normals = np.cross(b - a, c - a)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
    return Surface(pts, normals)


class SurfaceCache:
    """Oriented samples of catalog parts' meshes, made on first use and kept (LRU, thread-safe).

    Keyed by part id and a fingerprint of the mesh, so a part replaced under the same id (a
    catalog write) is sampled again.
    """

    def __init__(self, n: int, seed: int, max_entries: int):
        self.n, self.seed, self.max_entries = n, seed, max_entries
        self._items: OrderedDict[tuple, Surface] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, part_id: str, vertices: np.ndarray, faces: np.ndarray) -> Surface:
        digest = hashlib.blake2b(np.ascontiguousarray(vertices).tobytes(), digest_size=16)
        digest.update(np.ascontiguousarray(faces).tobytes())
        key = (part_id, digest.hexdigest())
        with self._lock:
            hit = self._items.get(key)
            if hit is not None:
                self._items.move_to_end(key)
                return hit
        surface = sample_oriented(vertices, faces, self.n, self.seed)
        with self._lock:
            self._items[key] = surface
            while len(self._items) > self.max_entries:
                self._items.popitem(last=False)
        return surface


class Assembly:
    """The assembly side of contact tests, prepared once and shared by every part placed against it."""

    def __init__(self, surface: Surface):
        if len(surface.points) == 0:
            raise ValueError("an assembly needs at least one sample")
        self.surface = surface
        self.points = np.ascontiguousarray(surface.points, dtype=np.float64)
        # The compiled search takes an array either way (it reads it only if the surface has normals).
        self.normals = (np.ascontiguousarray(surface.normals, dtype=np.float64) if surface.normals is not None
                        else np.zeros((1, 3)))


def _subsample(idx: np.ndarray, m: int, seed: int) -> np.ndarray:
    if len(idx) <= m:
        return idx
    return np.sort(np.random.default_rng(seed).choice(idx, size=m, replace=False))


def measure_contact(part: Surface, assembly: Assembly, reach: float = 0.5) -> ContactState:
    """Sampled gap and depth of a placed part against an assembly (gap capped at ``reach``)."""
    params = ContactParams(max_offset=0.0, search_points=len(part.points) + len(assembly.points))
    found = _search([part], assembly, params, reach)[0]
    return ContactState(gap=float(min(found.before.gap, reach)), depth=found.before.depth)


def refine_offset(part: Surface, assembly: Assembly, params: ContactParams) -> Refinement:
    """The smallest move (within ``params.max_offset``) after which the placed part touches.

    Args:
        part: the part's samples (with normals) at h's placement, canonical frame.
        assembly: the assembly it is placed against.
        params: search bound, tolerance and sample count.

    Returns the offset to add to the translation (zero when the contact cannot be resolved
    within the bound, or needs no change) and the sampled contact before and after. Several
    parts against one assembly: ``refine_offsets``.
    """
    return refine_offsets([part], assembly, params)[0]


def refine_offsets(parts: list[Surface], assembly: Assembly, params: ContactParams) -> list[Refinement]:
    """``refine_offset`` of each part against the same assembly (one compiled call for all)."""
    return _search(parts, assembly, params, params.max_offset + 2 * params.tolerance)


def _search(parts: list[Surface], assembly: Assembly, params: ContactParams, reach: float
            ) -> list[Refinement]:
    """Each part's line search, measuring within ``reach`` of the assembly (the module docstring).

    With ``params.threads`` > 1 that many threads take the parts one at a time: each part's
    search is independent of the others', so the answers are the same.
    """
    if not parts:
        return []
    batch = _Batch(parts, assembly, params, reach)
    workers = min(max(1, params.threads), len(parts))
    if workers <= 1:
        batch.run(0, len(parts))
        return batch.refinements()
    # Each thread takes the next part not yet taken: one part's search can cost ten times
    # another's (0.1 to 0.8 ms for the bench query's ten), and dealing every n-th part to a thread
    # left one thread with twice the other's work. The parts' arrays are made once, before: made
    # per part under the GIL they held the other thread back (10 parts: 2.0 ms on two threads
    # against 3.0 on one).
    taken = itertools.count()   # next() on a count is atomic under the GIL

    def work() -> None:
        for j in iter(taken.__next__, None):
            if j >= len(parts):
                return
            batch.run(j, j + 1)

    futures = [_pool(workers - 1).submit(work) for _ in range(workers - 1)]
    work()
    for f in futures:
        f.result()
    return batch.refinements()


_POOL: tuple[int, ThreadPoolExecutor] | None = None   # (its threads, the pool)
_POOL_LOCK = threading.Lock()


def _pool(workers: int) -> ThreadPoolExecutor:
    """The threads that search parts beside the calling one (made once, grown when asked for more)."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None or _POOL[0] < workers:
            _POOL = (workers, ThreadPoolExecutor(max_workers=workers, thread_name_prefix="contact"))
        return _POOL[1]


class _Batch:
    """The compiled search's arrays for several parts against one assembly, and its outputs: parts
    ``j`` to ``k`` are searched by ``run(j, k)`` (any thread; each part writes only its own rows)."""

    def __init__(self, parts: list[Surface], assembly: Assembly, params: ContactParams, reach: float):
        self.assembly, self.params, self.reach = assembly, params, reach
        self.counts = np.array([len(p.points) for p in parts], dtype=np.int64)
        self.starts = np.concatenate([[0], np.cumsum(self.counts)[:-1]]).astype(np.int64)
        self.points = np.ascontiguousarray(np.concatenate([p.points for p in parts]), dtype=np.float64)
        self.normals = np.ascontiguousarray(np.concatenate([_normals(p) for p in parts]), dtype=np.float64)
        self.has_normals = np.array([p.normals is not None for p in parts])
        tol = params.tolerance
        # Steps of one tolerance: the touching band along any direction is at least 2 tolerances wide
        # (gap from tol down to 0, then depth from 0 up to tol), so no step jumps over it.
        self.steps = np.arange(1, int(np.floor(params.max_offset / tol + 1e-9)) + 1) * tol
        self.offsets = np.zeros((len(parts), 3))
        self.states = np.zeros((len(parts), 4))
        self.status = np.zeros(len(parts), dtype=np.int64)

    def run(self, j: int, k: int) -> None:
        p, a = self.params, self.assembly
        kernel.refine_parts(self.points, self.normals, self.has_normals[j:k], self.starts[j:k],
                            self.counts[j:k], a.points, a.normals, a.surface.normals is not None,
                            float(p.max_offset), float(p.tolerance), int(p.search_points),
                            int(p.inside_neighbours), float(self.reach), self.steps, self.offsets[j:k],
                            self.states[j:k], self.status[j:k])

    def refinements(self) -> list[Refinement]:
        far = ContactState(gap=float(self.reach), depth=0.0)
        out = []
        for off, (g0, d0, g1, d1), st in zip(self.offsets, self.states.tolist(), self.status.tolist(),
                                             strict=True):
            if st == kernel.FAR:  # nothing within reach: apart by design or far off; keep h's translation
                out.append(Refinement(np.zeros(3), far, far, False))
            else:
                out.append(Refinement(off.copy(), ContactState(g0, d0), ContactState(g1, d1),
                                      st != kernel.UNRESOLVED))
        return out


def fitted_surfaces(surfaces: list[Surface], scales: np.ndarray, offsets: np.ndarray) -> list[Surface]:
    """Centred parts' samples scaled per axis about their centres, then moved: ``surfaces[j]``
    scaled by ``scales[j]`` (normals transformed by the inverse scale and renormalised; a part of
    scale ones keeps its normals) and moved by ``offsets[j]``, all parts in one pass (ten parts of
    512 samples took 0.40 ms one by one against 0.24, mostly numpy's per-call overhead).

    Shapes:
        scales, offsets: (n, 3) -> n Surfaces.
    """
    if not surfaces:
        return []
    counts = [len(b.points) for b in surfaces]
    sc = np.asarray(scales, dtype=np.float64).reshape(-1, 3)
    per_row = np.repeat(sc, counts, axis=0)
    points = (np.concatenate([b.points for b in surfaces]) * per_row
              + np.repeat(np.asarray(offsets, dtype=np.float64).reshape(-1, 3), counts, axis=0))
    normals = np.concatenate([_normals(b) for b in surfaces])
    fitted = np.repeat(np.any(sc != 1.0, axis=1), counts)
    if fitted.any():
        rows = slice(None) if fitted.all() else fitted   # all of them (usual): no gather and scatter
        n = normals[rows] / per_row[rows]
        normals[rows] = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    ends = np.cumsum(counts)[:-1]
    return [Surface(p, None if b.normals is None else nm)
            for b, p, nm in zip(surfaces, np.split(points, ends), np.split(normals, ends), strict=True)]


def _normals(surface: Surface) -> np.ndarray:
    return surface.normals if surface.normals is not None else np.full_like(surface.points, np.nan)


class PartContacts:
    """Contact refinement of catalog parts placed against one assembly (what the engine calls).

    Holds the cache of the parts' oriented samples; the catalog is passed per call, so a catalog
    that changes while serving is always read as it is now.
    """

    def __init__(self, params: ContactParams, part_samples: int, assembly_points: int, cache_entries: int):
        self.params = params
        self.assembly_points = assembly_points
        self.surfaces = SurfaceCache(part_samples, params.seed, cache_entries)

    def part_surface(self, catalog: Catalog, i: int) -> Surface:
        """Oriented samples of catalog part ``i``, centred like its mesh."""
        v, f = catalog.mesh(i)
        return self.surfaces.get(catalog.part_ids[i], v, f)

    def assembly_from_points(self, points: np.ndarray) -> Assembly:
        """An assembly from a caller's points (canonical), at most ``assembly_points`` of them (seeded).

        Shapes:
            points: (M, 3).
        """
        pts = np.asarray(points, dtype=np.float64)
        if len(pts) > self.assembly_points:
            pts = pts[_subsample(np.arange(len(pts)), self.assembly_points, self.params.seed)]
        return Assembly(Surface(pts))

    def placed(self, catalog: Catalog, rows: np.ndarray, translations: np.ndarray,
               scales: np.ndarray | None = None) -> list[Surface]:
        """Oriented samples of catalog parts ``rows[j]`` fitted to ``scales[j]`` (None: catalog
        size) and placed at ``translations[j]``: what ``refine_offsets`` refines.

        Shapes:
            rows: (n,) catalog rows; translations: (n, 3) canonical; scales: (n, 3) or None.
        """
        base = [self.part_surface(catalog, int(i)) for i in np.asarray(rows).tolist()]
        return fitted_surfaces(base, np.ones((len(base), 3)) if scales is None else scales, translations)
