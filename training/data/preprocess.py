"""Components and contact graphs from raw shapes (paper, Section 4 "Data Preprocessing").

Per shape: normalise (bounding-box centre, unit radius), take the pieces (scene-graph leaves or
connected components) as initial components, build the contact graph (an edge where two
components come closer than ``tau_proximity``), then merge in the paper's order:

1. size: a component whose PCA-aligned bounding-box diagonal is below ``tau_size`` is merged
   into its largest neighbour (by area), smallest first, until none is left that has one;
2. overlap: adjacent components whose directional Hausdorff distance is below
   ``tau_hausdorff`` in either direction (one lies on or inside the other) are grouped;
3. identical: components with the same geometry (the same multiset of scene-graph geometry
   keys, or the same vertices up to a translation) become one component even when they do not
   touch; its contact edges are the union of its members'.

Shapes with ``min_components..max_components`` components and a connected graph are kept. Each
kept component stores its mesh centred at its bounding-box centre, that centre (translation),
its area, its majority label and cached area-weighted surface samples.

Distances are measured on dense surface samples plus vertices with KD-trees (sample samples are
on the surface, so they never *under*estimate a distance), refined by exact point-to-triangle
distances near the threshold where the mesh is small enough.
"""

from __future__ import annotations

import hashlib
import logging
import multiprocessing
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from scipy.cluster.hierarchy import DisjointSet
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from tqdm import tqdm

from service.geometry.mesh import (
    MeshError,
    mesh_area,
    normalize_frame,
    points_to_mesh_distance,
    resample_points,
    sample_surface,
)
from training.data.ingest import ShapeFileError, find_shape_files, load_shape_file
from training.data.processed import ProcessedDataset
from training.data.shapes import RawShape

log = logging.getLogger(__name__)


@dataclass
class PreprocessConfig:
    """Thresholds of Section 4 (distances are fractions of the shape's radius) and sampling."""

    # Contact edge when the minimum distance between two components is below this (paper: 0.05).
    tau_proximity: float = 0.05
    # Merge a component whose PCA-aligned bounding-box diagonal is below this (paper: 0.2).
    tau_size: float = 0.2
    # Group components whose directional Hausdorff distance is below this (paper: 0.05).
    tau_hausdorff: float = 0.05
    # Keep shapes with this many components after merging (paper: at most N_max CC = 8).
    min_components: int = 2
    max_components: int = 8
    # Area-weighted surface samples cached per component (float16); training draws from them.
    points_per_component: int = 2048
    # Root seed; each shape's seed derives from it and the shape's category and id.
    seed: int = 0
    # Density of the samples used to measure distances, per unit area of the unit-radius shape:
    # spacing ~ 1/sqrt(density) = 0.02 keeps sampling error well under tau_proximity.
    contact_samples_per_area: float = 2500.0
    min_contact_samples: int = 32
    max_contact_samples: int = 4096
    # Exact point-to-triangle refinement is skipped beyond this many (point, triangle) pairs.
    exact_distance_budget: int = 2_000_000
    # Two components are identical up to translation when their centred vertex sets match
    # within this distance (unit-radius frame).
    identical_tolerance: float = 1e-3


# Why a shape is left out: its file, its geometry, or its components after merging.
RejectCode = Literal["unreadable", "invalid", "too_few_components", "too_many_components", "disconnected"]


@dataclass(frozen=True)
class Merges:
    """Unions done by each merge rule of Section 4 (size, overlap, identical)."""

    size: int = 0
    overlap: int = 0
    identical: int = 0


@dataclass(frozen=True, eq=False)
class Kept:
    """A shape that passed: its components, in the order of their first piece's name.

    Shapes:
        points (C, P, 3) float16 cached surface samples, centred at each component's box centre;
        translation (C, 3) float32 those centres; area (C,) float32; edges (E, 2) int32 local
        indices (i < j); meshes C x ((V, 3) float32, (F, 3) int32) centred meshes; labels C
        majority labels (or None).
    """

    pieces: int
    merges: Merges
    points: np.ndarray
    translation: np.ndarray
    area: np.ndarray
    edges: np.ndarray
    meshes: list[tuple[np.ndarray, np.ndarray]]
    labels: list[str | None]

    @property
    def n_components(self) -> int:
        return len(self.translation)


@dataclass(frozen=True)
class Rejected:
    """A shape that is left out, and why (``n_components`` is 0 when merging never ran)."""

    pieces: int
    merges: Merges
    n_components: int
    code: RejectCode
    reason: str


@dataclass(frozen=True)
class ShapeRecord:
    """One shape file's outcome, and where it came from (``source``: path under the raw folder)."""

    shape_id: str
    category: str
    style: str | None
    source: str
    outcome: Kept | Rejected


# --------------------------------------------------------------------------------------------
# Per-shape work.


def shape_seed(config: PreprocessConfig, category: str, shape_id: str) -> np.random.SeedSequence:
    """A seed sequence that depends only on the root seed and the shape: order/worker independent."""
    digest = hashlib.sha256(f"{category}/{shape_id}".encode()).digest()
    return np.random.SeedSequence([config.seed, int.from_bytes(digest[:8], "little")])


def _int_seed(ss: np.random.SeedSequence) -> int:
    return int(ss.generate_state(1, dtype=np.uint64)[0])


@dataclass
class _Piece:
    """A piece in the unit-radius frame with its distance-test samples."""

    name: str
    vertices: np.ndarray   # (V, 3) float64
    faces: np.ndarray      # (F, 3) int64; empty for point-only pieces
    key: str
    label: str | None
    area: float
    points: np.ndarray     # (K, 3) float64: surface samples + vertices (or the raw points)
    samples: np.ndarray    # (S, 3) float64: area-weighted samples only (for PCA axes)
    lo: np.ndarray = field(init=False)
    hi: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.lo, self.hi = self.points.min(axis=0), self.points.max(axis=0)


def _prepare_pieces(shape: RawShape, config: PreprocessConfig, ss: np.random.SeedSequence) -> list[_Piece]:
    if not shape.pieces:
        raise ValueError("has no pieces")
    all_vertices = np.concatenate([p.vertices for p in shape.pieces])
    _, center, radius = normalize_frame(all_vertices)
    point_only = [len(p.faces) == 0 for p in shape.pieces]
    n_points_total = sum(len(p.vertices) for p, po in zip(shape.pieces, point_only, strict=True) if po)
    seeds = ss.spawn(len(shape.pieces))
    pieces = []
    for raw, po, child in zip(shape.pieces, point_only, seeds, strict=True):
        v = (np.asarray(raw.vertices, dtype=np.float64) - center) / radius
        f = np.asarray(raw.faces, dtype=np.int64).reshape(-1, 3)
        area = mesh_area(v, f)
        if po or area <= 0:
            # Point clouds are sampled uniformly on the surface: the share of points is the share
            # of area. Degenerate meshes contribute their vertices only.
            area = len(v) / n_points_total if po else 0.0
            pts = resample_points(v, min(len(v), config.max_contact_samples), _int_seed(child))
            samples = pts
            f = np.zeros((0, 3), np.int64)
        else:
            n = int(np.clip(round(config.contact_samples_per_area * area), config.min_contact_samples,
                            config.max_contact_samples))
            samples = sample_surface(v, f, n, _int_seed(child)).astype(np.float64)
            pts = np.concatenate([samples, v])
        pieces.append(_Piece(raw.name, v, f, raw.geometry_key, raw.label, area, pts, samples))
    return pieces


class _Measure:
    """Distance tests between point sets of pieces or groups, with exact refinement."""

    def __init__(self, config: PreprocessConfig):
        self.config = config
        self.slack = 2.0 / np.sqrt(config.contact_samples_per_area)

    def exact(self, points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray | None:
        """Exact distances from points to a mesh, or None when too costly (no faces, over budget).

        Only triangles whose box comes within ``reach`` of the points' box can be closer than
        that, so the others are dropped first: callers only care about distances below reach.
        """
        if len(faces) == 0 or len(points) == 0:
            return None
        reach = max(self.config.tau_proximity, self.config.tau_hausdorff) + self.slack
        tri = vertices[faces]
        lo, hi = points.min(axis=0) - reach, points.max(axis=0) + reach
        keep = np.all((tri.max(axis=1) >= lo) & (tri.min(axis=1) <= hi), axis=1)
        if not keep.any():
            return np.full(len(points), np.inf)
        if len(points) * int(keep.sum()) > self.config.exact_distance_budget:
            return None
        return points_to_mesh_distance(points, vertices, faces[keep])

    def in_contact(self, a: _Piece, b: _Piece, tree_b: cKDTree) -> bool:
        """Is the minimum distance between two pieces below tau_proximity?"""
        tau = self.config.tau_proximity
        reach = tau + self.slack
        near = a.points[np.all((a.points > b.lo - reach) & (a.points < b.hi + reach), axis=1)]
        if len(near) == 0:
            return False
        d, _ = tree_b.query(near, k=1, distance_upper_bound=reach)
        if d.min() < tau:
            return True
        if not np.isfinite(d).any():
            return False
        # Samples overestimate distances by up to their spacing: check the closest ones exactly.
        order = np.argsort(d, kind="stable")[:32]
        cand = near[order[np.isfinite(d[order])]]
        exact = self.exact(cand, b.vertices, b.faces)
        return exact is not None and bool(exact.min() < tau)

    def within_hausdorff(self, a_points: np.ndarray, tree_b: cKDTree, b_vertices: np.ndarray,
                         b_faces: np.ndarray) -> bool:
        """Is the directional Hausdorff distance from A's points to B below tau_hausdorff?"""
        tau = self.config.tau_hausdorff
        # Most pairs fail on a few points (a leg is far from most of a seat): try a strided subset first.
        probe = a_points[::max(1, len(a_points) // 64)]
        d, _ = tree_b.query(probe, k=1, distance_upper_bound=tau + self.slack)
        if not np.isfinite(d).all():
            return False
        d, _ = tree_b.query(a_points, k=1, distance_upper_bound=tau + self.slack)
        if not np.isfinite(d).all():
            return False
        # Points whose sampled distance is at or above tau may still be closer: check them exactly,
        # farthest first, so a pair that fails usually fails on the first small batch.
        far = np.flatnonzero(d >= tau)
        far = far[np.argsort(-d[far], kind="stable")]
        for start in range(0, len(far), 64):
            exact = self.exact(a_points[far[start:start + 64]], b_vertices, b_faces)
            if exact is None or exact.max() >= tau:
                return False
        return True


def _contact_edges(pieces: list[_Piece], measure: _Measure, trees: list[cKDTree]) -> set[tuple[int, int]]:
    tau = measure.config.tau_proximity
    lo = np.stack([p.lo for p in pieces])
    hi = np.stack([p.hi for p in pieces])
    # Axis-aligned boxes further apart than tau cannot be in contact.
    gap = np.maximum(lo[:, None] - hi[None], lo[None] - hi[:, None]).max(axis=2)
    edges = set()
    for i, j in zip(*np.nonzero(np.triu(gap < tau, k=1)), strict=True):
        a, b = (int(i), int(j)) if len(pieces[i].points) <= len(pieces[j].points) else (int(j), int(i))
        if measure.in_contact(pieces[a], pieces[b], trees[b]) \
                or measure.in_contact(pieces[b], pieces[a], trees[a]):
            edges.add((int(i), int(j)))
    return edges


class _Groups:
    """Groups of pieces (scipy's disjoint sets), with per-group caches for the merge rules.

    A group is named by its smallest piece index: the name does not depend on the order of the
    merges, and sorted names put the components in the order of their first piece.
    """

    def __init__(self, pieces: list[_Piece]):
        self.pieces = pieces
        self._sets = DisjointSet(range(len(pieces)))
        self._least = list(range(len(pieces)))   # by scipy's root: the smallest member
        self._tree: dict[int, cKDTree] = {}
        self._diagonal: dict[int, float] = {}

    def find(self, i: int) -> int:
        return self._least[self._sets[i]]

    def union(self, i: int, j: int) -> bool:
        ri, rj = self.find(i), self.find(j)
        if not self._sets.merge(i, j):
            return False
        self._least[self._sets[i]] = min(ri, rj)
        for cache in (self._tree, self._diagonal):
            cache.pop(ri, None)
            cache.pop(rj, None)
        return True

    def members(self) -> dict[int, list[int]]:
        out: dict[int, list[int]] = {}
        for i in range(len(self.pieces)):
            out.setdefault(self.find(i), []).append(i)
        return out

    def adjacency(self, edges: set[tuple[int, int]]) -> dict[int, set[int]]:
        adj: dict[int, set[int]] = {r: set() for r in self.members()}
        for i, j in edges:
            ri, rj = self.find(i), self.find(j)
            if ri != rj:
                adj[ri].add(rj)
                adj[rj].add(ri)
        return adj

    def points(self, members: list[int]) -> np.ndarray:
        return np.concatenate([self.pieces[m].points for m in members])

    def mesh(self, members: list[int]) -> tuple[np.ndarray, np.ndarray]:
        vs = [self.pieces[m].vertices for m in members if len(self.pieces[m].faces)]
        fs = [self.pieces[m].faces for m in members if len(self.pieces[m].faces)]
        if not vs:
            return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
        offsets = np.cumsum([0] + [len(v) for v in vs[:-1]])
        return np.concatenate(vs), np.concatenate([f + o for f, o in zip(fs, offsets, strict=True)])

    def tree(self, root: int, members: list[int]) -> cKDTree:
        if root not in self._tree:
            self._tree[root] = cKDTree(self.points(members))
        return self._tree[root]

    def area(self, members: list[int]) -> float:
        return float(sum(self.pieces[m].area for m in members))

    def pca_diagonal(self, root: int, members: list[int]) -> float:
        """Diagonal of the bounding box aligned with the principal axes of the surface samples."""
        if root not in self._diagonal:
            self._diagonal[root] = self._pca_diagonal(members)
        return self._diagonal[root]

    def _pca_diagonal(self, members: list[int]) -> float:
        samples = np.concatenate([self.pieces[m].samples for m in members])
        extent_pts = np.concatenate([self.pieces[m].vertices for m in members])
        centred = samples - samples.mean(axis=0)
        if len(samples) < 3:
            axes = np.eye(3)
        else:
            _, _, axes = np.linalg.svd(centred, full_matrices=False)
        proj = extent_pts @ axes.T
        return float(np.linalg.norm(proj.max(axis=0) - proj.min(axis=0)))


def _merge_small(groups: _Groups, edges: set[tuple[int, int]], tau_size: float) -> int:
    merges = 0
    while True:
        members = groups.members()
        adj = groups.adjacency(edges)
        diagonal = {r: groups.pca_diagonal(r, m) for r, m in members.items()}
        small = sorted((diagonal[r], r) for r in members if adj[r] and diagonal[r] < tau_size)
        if not small:
            return merges
        _, r = small[0]
        target = max(adj[r], key=lambda n: (groups.area(members[n]), -n))
        groups.union(r, target)
        merges += 1


def _merge_overlapping(groups: _Groups, edges: set[tuple[int, int]], measure: _Measure) -> int:
    members = groups.members()
    adj = groups.adjacency(edges)
    pairs = sorted({(min(a, b), max(a, b)) for a in adj for b in adj[a]})
    meshes = {r: groups.mesh(m) for r, m in members.items()}
    trees = {r: groups.tree(r, m) for r, m in members.items()}
    points = {r: groups.points(m) for r, m in members.items()}
    found = [(a, b) for a, b in pairs
             if measure.within_hausdorff(points[a], trees[b], *meshes[b])
             or measure.within_hausdorff(points[b], trees[a], *meshes[a])]
    return sum(groups.union(a, b) for a, b in found)


def _identical_signature(groups: _Groups, members: list[int]) -> tuple[np.ndarray, float]:
    v = np.concatenate([groups.pieces[m].vertices for m in members])
    return v - (v.min(axis=0) + v.max(axis=0)) / 2, groups.area(members)


def _merge_identical(groups: _Groups, tol: float) -> int:
    members = groups.members()
    roots = sorted(members)
    keys = {r: tuple(sorted(groups.pieces[m].key for m in members[r])) for r in roots}
    found = []
    by_key: dict[tuple[str, ...], list[int]] = {}
    for r in roots:
        by_key.setdefault(keys[r], []).append(r)
    for same in by_key.values():
        found += [(same[0], other) for other in same[1:]]
    # Identical up to translation, for sources without shared geometry: same vertex count and
    # area, then centred vertex sets that match both ways.
    sigs = {r: _identical_signature(groups, members[r]) for r in roots}
    for i, a in enumerate(roots):
        va, area_a = sigs[a]
        for b in roots[i + 1:]:
            vb, area_b = sigs[b]
            if len(va) != len(vb) or abs(area_a - area_b) > 1e-3 * max(area_a, area_b, 1e-12):
                continue
            if np.abs(np.ptp(va, axis=0) - np.ptp(vb, axis=0)).max() > tol:
                continue
            d_ab, _ = cKDTree(vb).query(va, distance_upper_bound=tol)
            if np.isfinite(d_ab).all():
                d_ba, _ = cKDTree(va).query(vb, distance_upper_bound=tol)
                if np.isfinite(d_ba).all():
                    found.append((a, b))
    return sum(groups.union(a, b) for a, b in found)


def _connected(n: int, edges: list[tuple[int, int]]) -> int:
    """Number of connected parts of a graph over nodes 0..n-1."""
    e = np.asarray(edges, np.int64).reshape(-1, 2)
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
    return int(connected_components(graph, directed=False)[0])


def preprocess_shape(shape: RawShape, config: PreprocessConfig) -> Kept | Rejected:
    """Merge one shape's pieces into components and build its contact graph.

    Returns:
        ``Kept`` (the components' arrays) or ``Rejected`` (why not); both count the pieces and
        the unions each merge rule did.
    """
    # Loaders list scene nodes in their own order: sort by name so the result depends on the
    # shape alone (components come out in the order of their first piece's name).
    order = sorted(range(len(shape.pieces)), key=lambda i: (shape.pieces[i].name, i))
    shape = RawShape(shape.shape_id, shape.category, [shape.pieces[i] for i in order], shape.style,
                     shape.source)
    ss = shape_seed(config, shape.category, shape.shape_id)
    prep_ss, out_ss = ss.spawn(2)
    try:
        pieces = _prepare_pieces(shape, config, prep_ss)
    except (MeshError, ValueError) as err:
        return Rejected(len(shape.pieces), Merges(), 0, "invalid", f"invalid geometry: {err}")
    groups, edges, merges = _merge(pieces, config)
    members = groups.members()
    roots = sorted(members)  # a group's root is its smallest piece index: a stable order
    index = {r: k for k, r in enumerate(roots)}
    comp_edges = sorted({(min(index[a], index[b]), max(index[a], index[b]))
                         for a, nbrs in groups.adjacency(edges).items() for b in nbrs})
    rejected = _rejection(len(roots), comp_edges, config)
    if rejected is not None:
        code, reason = rejected
        return Rejected(len(shape.pieces), merges, len(roots), code, reason)
    return _kept(groups, [members[r] for r in roots], comp_edges, config, out_ss, merges)


def _merge(pieces: list[_Piece], config: PreprocessConfig
           ) -> tuple[_Groups, set[tuple[int, int]], Merges]:
    """The contact edges between pieces, and the groups the three merge rules make, in order."""
    measure = _Measure(config)
    trees = [cKDTree(p.points) for p in pieces]
    edges = _contact_edges(pieces, measure, trees)
    groups = _Groups(pieces)
    size = _merge_small(groups, edges, config.tau_size)
    overlap = _merge_overlapping(groups, edges, measure)
    identical = _merge_identical(groups, config.identical_tolerance)
    return groups, edges, Merges(size, overlap, identical)


def _rejection(n: int, comp_edges: list[tuple[int, int]], config: PreprocessConfig
               ) -> tuple[RejectCode, str] | None:
    """Why a shape with ``n`` components and these contact edges is left out (None: it is kept)."""
    if n < config.min_components:
        return "too_few_components", f"{n} component(s) after merging, fewer than {config.min_components}"
    if n > config.max_components:
        return "too_many_components", f"{n} components after merging, more than {config.max_components}"
    parts = _connected(n, comp_edges)
    if parts > 1:
        return "disconnected", f"contact graph is not connected ({parts} separate parts)"
    return None


def _kept(groups: _Groups, components: list[list[int]], comp_edges: list[tuple[int, int]],
          config: PreprocessConfig, out_ss: np.random.SeedSequence, merges: Merges) -> Kept:
    """Each component's centred mesh, cached samples, translation, area and majority label."""
    pieces, n, P = groups.pieces, len(components), config.points_per_component
    points = np.empty((n, P, 3), np.float16)
    translation = np.empty((n, 3), np.float32)
    area = np.empty(n, np.float32)
    meshes, labels = [], []
    for k, (m, comp_ss) in enumerate(zip(components, out_ss.spawn(n), strict=True)):
        v, f = groups.mesh(m)
        if len(f):
            centre = (v.min(axis=0) + v.max(axis=0)) / 2
            pts = sample_surface(v, f, P, _int_seed(comp_ss)).astype(np.float64)
        else:  # point-only component: its points are the samples
            v = np.concatenate([pieces[i].vertices for i in m])
            centre = (v.min(axis=0) + v.max(axis=0)) / 2
            pts = resample_points(v, P, _int_seed(comp_ss))
        points[k] = (pts - centre).astype(np.float16)
        translation[k] = centre
        area[k] = groups.area(m)
        meshes.append(((v - centre).astype(np.float32), f.astype(np.int32)))
        labels.append(_majority_label([pieces[i] for i in m]))
    return Kept(len(pieces), merges, points, translation, area,
                np.asarray(comp_edges, np.int32).reshape(-1, 2), meshes, labels)


def _majority_label(pieces: list[_Piece]) -> str | None:
    """The label with the most area; ties broken by name so the result does not depend on piece order."""
    votes: dict[str, float] = {}
    for p in pieces:
        if p.label is not None:
            votes[p.label] = votes.get(p.label, 0.0) + p.area
    return max(sorted(votes), key=lambda lab: votes[lab]) if votes else None


# --------------------------------------------------------------------------------------------
# Folder.


def _process_file(job: tuple[str, str, dict[str, Any]]) -> ShapeRecord:
    path_s, raw_s, config_d = job
    path, config = Path(path_s), PreprocessConfig(**config_d)
    source = path.relative_to(raw_s).as_posix()
    try:
        shape = load_shape_file(path)
    except (ShapeFileError, MeshError) as err:
        return ShapeRecord(path.stem, path.parent.name, None, source,
                           Rejected(0, Merges(), 0, "unreadable", f"unreadable: {err}"))
    return ShapeRecord(shape.shape_id, shape.category, shape.style, source, preprocess_shape(shape, config))


def _run(jobs: list[tuple[str, str, dict[str, Any]]], workers: int) -> Iterator[ShapeRecord]:
    if workers <= 1:
        yield from map(_process_file, jobs)
        return
    # spawn, not fork: the parent may hold BLAS or tqdm threads.
    with multiprocessing.get_context("spawn").Pool(workers) as pool:
        yield from pool.imap(_process_file, jobs, chunksize=4)


def assemble(records: list[ShapeRecord], config: PreprocessConfig) -> ProcessedDataset:
    """Concatenate per-shape records (in the given order) into a ProcessedDataset."""
    kept_records = [(r, r.outcome) for r in records if isinstance(r.outcome, Kept)]
    kept = [k for _, k in kept_records]
    P = config.points_per_component
    first = np.zeros(len(kept) + 1, np.int64)
    first[1:] = np.cumsum([k.n_components for k in kept])
    meshes = [m for k in kept for m in k.meshes]
    vfirst = np.zeros(len(meshes) + 1, np.int64)
    vfirst[1:] = np.cumsum([len(v) for v, _ in meshes])
    ffirst = np.zeros(len(meshes) + 1, np.int64)
    ffirst[1:] = np.cumsum([len(f) for _, f in meshes])
    edges = [k.edges + first[s] for s, k in enumerate(kept)]
    shapes = [{"shape_id": r.shape_id, "category": r.category, "style": r.style, "source": r.source,
               "labels": k.labels, "pieces": k.pieces} for r, k in kept_records]
    return ProcessedDataset(
        points=_concat([k.points for k in kept], np.zeros((0, P, 3), np.float16)),
        translation=_concat([k.translation for k in kept], np.zeros((0, 3), np.float32)),
        area=_concat([k.area for k in kept], np.zeros(0, np.float32)),
        shape_of=np.repeat(np.arange(len(kept), dtype=np.int32), np.diff(first)),
        first_comp=first,
        edges=np.concatenate(edges).astype(np.int32) if edges else np.zeros((0, 2), np.int32),
        mesh_vertices=_concat([v for v, _ in meshes], np.zeros((0, 3), np.float32)),
        mesh_faces=_concat([f for _, f in meshes], np.zeros((0, 3), np.int32)),
        vertex_first=vfirst, face_first=ffirst, shapes=shapes,
        info=_dataset_info(records, config, int(first[-1])),
    )


def _concat(arrays: list[np.ndarray], empty: np.ndarray) -> np.ndarray:
    return np.concatenate(arrays) if arrays else empty


def _dataset_info(records: list[ShapeRecord], config: PreprocessConfig, components: int) -> dict[str, Any]:
    """The dataset's ``info``: config, counts, merges, per-category outcomes and every rejection."""
    rejected = [(r, r.outcome) for r in records if isinstance(r.outcome, Rejected)]
    merges = {k: int(sum(getattr(r.outcome.merges, k) for r in records))
              for k in ("size", "overlap", "identical")}
    # Components per shape, over every shape that reached merging, and over the kept ones.
    histogram: dict[str, dict[str, int]] = {}
    histogram_kept: dict[str, dict[str, int]] = {}
    per_category: dict[str, dict[str, Any]] = {}
    for r in records:
        o = r.outcome
        if not (isinstance(o, Rejected) and o.code in ("unreadable", "invalid")):
            for hist, counted in ((histogram, True), (histogram_kept, isinstance(o, Kept))):
                h = hist.setdefault(r.category, {})
                if counted:
                    h[str(o.n_components)] = h.get(str(o.n_components), 0) + 1
        c = per_category.setdefault(r.category, {"kept": 0, "rejected": {}})
        if isinstance(o, Rejected):
            c["rejected"][o.code] = c["rejected"].get(o.code, 0) + 1
        else:
            c["kept"] += 1
    return {
        "config": asdict(config),
        "seed": config.seed,
        "counts": {"shapes_in": len(records), "kept": len(records) - len(rejected), "rejected": len(rejected),
                   "pieces_in": int(sum(r.outcome.pieces for r in records)), "components": components},
        "merge_counts": merges,
        "per_category": per_category,
        "components_histogram": histogram,
        "components_histogram_kept": histogram_kept,
        "rejected": [{"shape_id": r.shape_id, "category": r.category, "source": r.source,
                      "code": o.code, "reason": o.reason} for r, o in rejected],
    }


def preprocess_folder(raw: Path, out: Path, config: PreprocessConfig | None = None,
                      workers: int = 2) -> ProcessedDataset:
    """Preprocess every shape file under ``raw`` and write the dataset to ``out``.

    The output depends only on the files and the config (not on ``workers`` or file order):
    shapes are sorted by category then id, and each shape's randomness comes from its own seed.
    """
    raw, out = Path(raw), Path(out)
    config = config or PreprocessConfig()
    if not raw.is_dir():
        raise FileNotFoundError(f"raw shape folder not found: {raw} (run `complementme data generate` or "
                                "`complementme data ingest` first)")
    files = find_shape_files(raw)
    if not files:
        raise FileNotFoundError(f"no shape files ({', '.join(('.glb', '.obj', '.pts', '...'))}) under {raw}")
    jobs = [(str(p), str(raw), asdict(config)) for p in files]
    records = []
    with tqdm(total=len(jobs), desc="preprocess", unit="shape") as bar:
        for r in _run(jobs, workers):
            records.append(r)
            bar.update()
    records.sort(key=lambda r: (r.category, r.shape_id, r.source))
    seen: dict[tuple[str, str], str] = {}
    for r in records:
        key = (r.category, r.shape_id)
        if key in seen:
            raise ValueError(f"duplicate shape id {r.shape_id!r} in category {r.category!r}: "
                             f"{seen[key]} and {r.source} under {raw}")
        seen[key] = r.source
    ds = assemble(records, config)
    ds.save(out)
    log.info("preprocessed %d shapes: %d kept, %d rejected", len(records), ds.n_shapes,
             len(records) - ds.n_shapes)
    return ds
