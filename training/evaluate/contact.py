"""Contact geometry of a placed part: gap to the assembly and interpenetration depth.

The paper places parts by regressing a translation, and its own figures show the known failure:
parts that float a little off the assembly or sink into it. The benchmark measures how often a
placement is implausible, with these definitions (all distances in the unit-radius frame):

* ``d(x, M)``: exact Euclidean distance from a point ``x`` to the surface of a triangle mesh
  ``M`` (closest point on any triangle, Ericson's "ClosestPtPointTriangle" via trimesh).
* ``inside(x, M)``: ``|w(x)| > 0.5`` where ``w`` is the generalised winding number of ``M`` at
  ``x`` (Jacobson, Kavan, Sorkine-Hornung 2013): the sum over triangles of their signed solid
  angle seen from ``x`` divided by 4 pi. It is 1 inside and 0 outside a closed mesh, degrades
  gracefully on meshes with small holes, and the absolute value ignores a flipped orientation.
* Penetration depth of part ``P`` (mesh ``M_P``, surface samples ``S_P``) into the assembly of
  components ``c`` (meshes ``M_c``, samples ``S_c``): the largest ``d(x, M_c)`` over samples
  ``x`` of ``S_P`` inside some ``M_c``, and symmetrically over samples of ``S_c`` inside
  ``M_P`` (a small component swallowed by a big part also counts); 0 when no sample is inside.
* Gap: 0 when any sample of one side is inside the other side (the surfaces meet); otherwise
  the smallest of ``d(x, M_c)`` over ``x`` in ``S_P`` and of ``d(y, M_P)`` over ``y`` in the
  ``S_c``. Only the few samples nearest to the other side's samples (``candidates``) are
  measured exactly; the others cannot hold the minimum.

A placement is *floating* when gap > tolerance and *interpenetrating* when depth > tolerance
(the benchmark's default tolerance is 0.02 of the shape radius).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree


@dataclass
class Mesh:
    """A triangle mesh with surface samples, placed in the shape frame.

    Shapes:
        vertices (V, 3) float64, faces (F, 3) int64, samples (S, 3) float64.
    """

    vertices: np.ndarray
    faces: np.ndarray
    samples: np.ndarray

    @property
    def triangles(self) -> np.ndarray:
        return self.vertices[self.faces]

    def moved(self, offset: np.ndarray) -> Mesh:
        o = np.asarray(offset, dtype=np.float64).reshape(1, 3)
        return Mesh(self.vertices + o, self.faces, self.samples + o)


def winding_number(points: np.ndarray, triangles: np.ndarray, chunk: int = 256) -> np.ndarray:
    """Generalised winding number of a triangle soup at each point (van Oosterom-Strackee).

    Shapes:
        points (n, 3), triangles (m, 3, 3) -> (n,) float64.
    """
    pts = np.asarray(points, dtype=np.float64)
    tris = np.asarray(triangles, dtype=np.float64)
    out = np.zeros(len(pts))
    if len(tris) == 0:
        return out
    for start in range(0, len(pts), chunk):
        p = pts[start:start + chunk, None, :]                     # (c, 1, 3)
        a, b, c = tris[None, :, 0] - p, tris[None, :, 1] - p, tris[None, :, 2] - p  # (c, m, 3)
        la, lb, lc = (np.sqrt(np.einsum("ijk,ijk->ij", v, v)) for v in (a, b, c))
        det = np.einsum("ijk,ijk->ij", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("ijk,ijk->ij", a, b) * lc
               + np.einsum("ijk,ijk->ij", b, c) * la + np.einsum("ijk,ijk->ij", c, a) * lb)
        out[start:start + chunk] = (2.0 * np.arctan2(det, den)).sum(axis=1) / (4.0 * np.pi)
    return out


def inside_mask(points: np.ndarray, mesh: Mesh, margin: float = 1e-6) -> np.ndarray:
    """Which points lie inside ``mesh`` (|winding number| > 0.5); bounding-box culled first.

    Shapes:
        points (n, 3) -> (n,) bool.
    """
    pts = np.asarray(points, dtype=np.float64)
    mask = np.zeros(len(pts), dtype=bool)
    if len(mesh.faces) == 0 or len(pts) == 0:
        return mask
    lo, hi = mesh.vertices.min(axis=0) - margin, mesh.vertices.max(axis=0) + margin
    in_box = np.all((pts >= lo) & (pts <= hi), axis=1)
    if in_box.any():
        mask[in_box] = np.abs(winding_number(pts[in_box], mesh.triangles)) > 0.5
    return mask


def distance_to_mesh(points: np.ndarray, mesh: Mesh, chunk_pairs: int = 200_000) -> np.ndarray:
    """Exact distance from each point to the nearest triangle of ``mesh``.

    Shapes:
        points (n, 3) -> (n,) float64.
    """
    pts = np.asarray(points, dtype=np.float64)
    tris = mesh.triangles
    if len(tris) == 0:
        raise ValueError("distance to a mesh without faces is undefined")
    out = np.full(len(pts), np.inf)
    per = max(1, chunk_pairs // len(tris))
    for start in range(0, len(pts), per):
        p = pts[start:start + per]
        pairs_t = np.broadcast_to(tris[None], (len(p), *tris.shape)).reshape(-1, 3, 3)
        pairs_p = np.repeat(p, len(tris), axis=0)
        closest = trimesh.triangles.closest_point(pairs_t, pairs_p)
        d = np.linalg.norm(closest - pairs_p, axis=1).reshape(len(p), len(tris))
        out[start:start + per] = d.min(axis=1)
    return out


def _depth_inside(samples: np.ndarray, container: Mesh, candidates: int) -> tuple[bool, float]:
    """Whether any sample is inside ``container``, and the largest distance to its surface among them."""
    inside = inside_mask(samples, container)
    if not inside.any():
        return False, 0.0
    pts = samples[inside]
    # The deepest points are the ones farthest from the container's surface samples.
    approx, _ = cKDTree(container.samples).query(pts, k=1)
    pick = np.argsort(-approx)[:candidates]
    return True, float(distance_to_mesh(pts[pick], container).max())


def _nearest_candidates(a: np.ndarray, b: np.ndarray, candidates: int) -> np.ndarray:
    """The ``candidates`` points of ``a`` nearest to the point set ``b``."""
    d, _ = cKDTree(b).query(a, k=1)
    return a[np.argsort(d)[:candidates]]


@dataclass
class Contact:
    """Gap and penetration depth of one placed part against an assembly (unit-radius units)."""

    gap: float
    depth: float

    def floating(self, tolerance: float) -> bool:
        return self.gap > tolerance

    def interpenetrating(self, tolerance: float) -> bool:
        return self.depth > tolerance


def contact(part: Mesh, assembly: list[Mesh], candidates: int = 32) -> Contact:
    """Gap and penetration depth of ``part`` (already placed) against ``assembly`` (see module doc).

    Args:
        part: the placed part, in the assembly's frame.
        assembly: the assembly's components, in the same frame.
        candidates: samples per side measured exactly for the gap, and per container for depth.
    """
    if not assembly:
        raise ValueError("contact needs an assembly of at least one component")
    depth = 0.0
    touching = False
    for comp in assembly:
        for samples, container in ((part.samples, comp), (comp.samples, part)):
            any_inside, d = _depth_inside(samples, container, candidates)
            touching = touching or any_inside
            depth = max(depth, d)
    if touching:
        return Contact(gap=0.0, depth=depth)
    asm_samples = np.concatenate([c.samples for c in assembly])
    gap = np.inf
    near_part = _nearest_candidates(part.samples, asm_samples, candidates)
    for comp in assembly:
        gap = min(gap, float(distance_to_mesh(near_part, comp).min()))
    near_asm = _nearest_candidates(asm_samples, part.samples, candidates)
    gap = min(gap, float(distance_to_mesh(near_asm, part).min()))
    return Contact(gap=gap, depth=depth)
