"""Closed triangle-mesh primitives: boxes, tapered rods, ellipsoids, capsules, tori, surfaces of
revolution, extruded outlines, lofts and swept tubes.

All builders are pure and return a watertight :class:`Mesh` with outward faces, built in a local
frame (documented per function) and positioned by the caller with a 4x4 transform. Segment
counts stay low (8-24) so that a whole shape stays within a few thousand faces.
"""

from __future__ import annotations

import itertools

import numpy as np
from numpy.typing import ArrayLike

from training.data.generator.mesh import Mesh, align_y_to, compose, rotation, translation
from training.data.generator.outlines import ccw, rounded_rect, signed_area, triangulate

_EPS = 1e-9


def _ring_faces(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Quads (as triangle pairs) joining two closed rings of vertex indices of equal length."""
    a2, b2 = np.roll(a, -1), np.roll(b, -1)
    return np.concatenate([np.stack([a, a2, b2], 1), np.stack([a, b2, b], 1)])


def _fan_faces(ring: np.ndarray, pole: int, pole_after: bool) -> np.ndarray:
    r2 = np.roll(ring, -1)
    p = np.full_like(ring, pole)
    return np.stack([ring, r2, p], 1) if pole_after else np.stack([ring, p, r2], 1)


def _positive(section: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """The triangles (indices into ``section``) each turned counter-clockwise in the plane."""
    p = section[tris]
    area = (p[:, 1, 0] - p[:, 0, 0]) * (p[:, 2, 1] - p[:, 0, 1]) - (p[:, 1, 1] - p[:, 0, 1]) * (
        p[:, 2, 0] - p[:, 0, 0]
    )
    return np.where(area[:, None] < 0, tris[:, ::-1], tris)


def rings_mesh(
    rings: np.ndarray, section: np.ndarray | None = None, closed: bool = False, cap: np.ndarray | None = None
) -> Mesh:
    """Skin consecutive rings of points; cap both ends with the triangulated section.

    Args:
        rings: (m, k, 3) points, ring i is the section placed at station i.
        section: (k, 2) the 2D section all rings are images of (to triangulate the caps);
            ignored when ``closed``.
        closed: join the last ring back to the first (a loop such as a torus), no caps.
        cap: (k - 2, 3) optional triangulation of the section (indices), instead of ear
            clipping (e.g. a strip for band-like sections).
    """
    m, k, _ = rings.shape
    idx = np.arange(m * k).reshape(m, k)
    faces = [_ring_faces(idx[i], idx[i + 1]) for i in range(m - 1)]
    if closed:
        faces.append(_ring_faces(idx[-1], idx[0]))
    else:
        assert section is not None, "open rings need the 2D section to cap their ends"
        if cap is not None:
            tris = _positive(np.asarray(section, float), np.asarray(cap, np.int64))
        else:
            tris = triangulate(ccw(section))
            if signed_area(section) < 0:  # triangulate() saw the reversed polygon
                tris = (k - 1) - tris
        if signed_area(section) < 0:
            # A clockwise section turns the side faces the other way: turn the caps with them.
            tris = tris[:, ::-1]
        faces.append(idx[0][tris][:, ::-1])
        faces.append(idx[-1][tris])
    return Mesh(rings.reshape(-1, 3).astype(float), np.concatenate(faces).astype(np.int64)).oriented_outward()


def lathe(profile: np.ndarray, segments: int = 16, closed: bool = False) -> Mesh:
    """Surface of revolution about the y axis.

    Args:
        profile: (n, 2) points (r, y) with r >= 0. Open profiles whose end points have r == 0 close
            there with a single pole vertex (ends with r > 0 are closed by adding such a pole).
        closed: the profile is a closed loop away from the axis (a shell such as a lampshade or
            a tyre), giving a torus-like surface.
    """
    prof = np.asarray(profile, dtype=float)
    if not closed:
        if prof[0, 0] > _EPS:
            prof = np.concatenate([[[0.0, prof[0, 1]]], prof])
        if prof[-1, 0] > _EPS:
            prof = np.concatenate([prof, [[0.0, prof[-1, 1]]]])
    theta = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    verts: list[np.ndarray] = []
    rings: list[np.ndarray | int] = []
    count = 0
    for r, y in prof:
        if not closed and r <= _EPS:
            verts.append(np.array([[0.0, y, 0.0]]))
            rings.append(count)
            count += 1
        else:
            verts.append(np.stack([r * np.cos(theta), np.full(segments, y), r * np.sin(theta)], 1))
            rings.append(np.arange(count, count + segments))
            count += segments
    pairs = list(itertools.pairwise(rings))
    if closed:
        pairs.append((rings[-1], rings[0]))
    faces = []
    for a, b in pairs:
        if isinstance(a, np.ndarray) and isinstance(b, np.ndarray):
            faces.append(_ring_faces(a, b))
        elif isinstance(a, np.ndarray):
            faces.append(_fan_faces(a, int(b), pole_after=True))
        elif isinstance(b, np.ndarray):
            faces.append(_fan_faces(b, int(a), pole_after=False))
    return Mesh(np.concatenate(verts), np.concatenate(faces).astype(np.int64)).oriented_outward()


def box(sx: float, sy: float, sz: float) -> Mesh:
    """An axis-aligned box centred at the origin."""
    corners = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    faces = np.array(
        [
            [0, 1, 3],
            [0, 3, 2],
            [4, 6, 7],
            [4, 7, 5],
            [0, 4, 5],
            [0, 5, 1],
            [2, 3, 7],
            [2, 7, 6],
            [0, 2, 6],
            [0, 6, 4],
            [1, 5, 7],
            [1, 7, 3],
        ]
    )
    return Mesh(corners * [sx, sy, sz], faces).oriented_outward()


def frustum(r_bottom: float, r_top: float, height: float, segments: int = 16) -> Mesh:
    """A (tapered) cylinder along +y from y = 0 to y = height."""
    return lathe(np.array([[r_bottom, 0.0], [r_top, height]]), segments)


def rod(p0: ArrayLike, p1: ArrayLike, r0: float, r1: float | None = None, segments: int = 12) -> Mesh:
    """A (tapered) cylinder from point p0 (radius r0) to point p1 (radius r1, default r0)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    length = float(np.linalg.norm(p1 - p0))
    local = frustum(r0, r0 if r1 is None else r1, length, segments)
    return local.transformed(compose(translation(*p0), align_y_to(p1 - p0)))


def ellipsoid(rx: float, ry: float, rz: float, segments: int = 16, rings: int = 8) -> Mesh:
    """An ellipsoid centred at the origin."""
    t = np.linspace(-0.5 * np.pi, 0.5 * np.pi, rings + 1)
    unit = lathe(np.stack([np.cos(t), np.sin(t)], 1), segments)
    return Mesh(unit.vertices * [rx, ry, rz], unit.faces)


def capsule(length: float, radius: float, segments: int = 12, cap_rings: int = 3) -> Mesh:
    """A capsule along +y: cylinder part of ``length`` from y = 0, hemispheres beyond both ends."""
    t = np.linspace(-0.5 * np.pi, 0.0, cap_rings + 1)
    bottom = np.stack([radius * np.cos(t), radius * np.sin(t)], 1)
    top = bottom[::-1].copy()
    top[:, 1] = -top[:, 1] + length
    return lathe(np.concatenate([bottom, top]), segments)


def torus(major: float, minor: float, segments: int = 20, minor_segments: int = 8) -> Mesh:
    """A torus around the y axis (ring in the xz plane)."""
    t = np.linspace(0, 2 * np.pi, minor_segments, endpoint=False)
    loop = np.stack([major + minor * np.cos(t), minor * np.sin(t)], 1)
    return lathe(loop, segments, closed=True)


def offset_outline(poly: np.ndarray, distance: float) -> np.ndarray:
    """Move every vertex of a CCW outline inward by ``distance`` along its corner bisector."""
    p = ccw(poly)
    e_in = p - np.roll(p, 1, axis=0)
    e_out = np.roll(p, -1, axis=0) - p
    n_in = np.stack([e_in[:, 1], -e_in[:, 0]], 1) / np.linalg.norm(e_in, axis=1, keepdims=True)
    n_out = np.stack([e_out[:, 1], -e_out[:, 0]], 1) / np.linalg.norm(e_out, axis=1, keepdims=True)
    bis = n_in + n_out
    bis /= np.maximum(np.linalg.norm(bis, axis=1, keepdims=True), 1e-9)
    cos_half = np.clip(np.einsum("ij,ij->i", bis, n_out), 0.35, 1.0)
    return p - bis * (distance / cos_half)[:, None]


def extrude(outline: np.ndarray, depth: float, bevel: float = 0.0) -> Mesh:
    """Extrude a 2D outline (in the xy plane) along z, centred at z = 0.

    ``bevel`` > 0 chamfers both rims: the end faces are the outline shrunk by ``bevel``.
    """
    p = ccw(outline)
    if bevel > 0:
        inner = offset_outline(p, bevel)
        zs = [(-depth / 2, inner), (-depth / 2 + bevel, p), (depth / 2 - bevel, p), (depth / 2, inner)]
    else:
        zs = [(-depth / 2, p), (depth / 2, p)]
    rings = np.stack([np.column_stack([q, np.full(len(q), z)]) for z, q in zs])
    return rings_mesh(rings, p)


def loft(
    section: np.ndarray,
    stations: np.ndarray,
    centers: np.ndarray,
    scales: np.ndarray,
    axis: str = "x",
    cap: np.ndarray | None = None,
) -> Mesh:
    """Skin a 2D section placed at several stations along a coordinate axis, capped at both ends.

    Args:
        section: (k, 2) closed outline in the plane normal to ``axis``; its (u, v) coordinates map
            to (y, z) for axis x, (z, x) for axis y and (x, y) for axis z.
        stations: (m,) coordinates along the axis.
        centers: (m, 2) offset of the section at each station, in (u, v).
        scales: (m, 2) scale of the section at each station, in (u, v) (keep them > 0).
        cap: optional triangulation of the section for the end caps (see ``rings_mesh``).
    """
    sec = np.asarray(section, float)
    m = len(stations)
    uv = sec[None] * np.asarray(scales, float)[:, None, :] + np.asarray(centers, float)[:, None, :]
    s = np.broadcast_to(np.asarray(stations, float)[:, None], (m, len(sec)))
    order = {
        "x": (s, uv[..., 0], uv[..., 1]),
        "y": (uv[..., 1], s, uv[..., 0]),
        "z": (uv[..., 0], uv[..., 1], s),
    }[axis]
    return rings_mesh(np.stack(order, axis=-1), sec, cap=cap)


def _frames(path: np.ndarray, closed: bool, up: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Normals and binormals along a path: projected ``up`` if given, else parallel transport."""
    nxt = np.roll(path, -1, axis=0) if closed else np.concatenate([path[1:], 2 * path[-1:] - path[-2:-1]])
    prv = np.roll(path, 1, axis=0) if closed else np.concatenate([2 * path[:1] - path[1:2], path[:-1]])
    t = nxt - prv
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    normals = np.empty_like(t)
    if up is not None:
        u = np.asarray(up, float)
        n = u[None] - np.einsum("ij,j->i", t, u)[:, None] * t
        normals = n / np.linalg.norm(n, axis=1, keepdims=True)
    else:
        ref = np.array([0.0, 1.0, 0.0]) if abs(t[0, 1]) < 0.9 else np.array([1.0, 0.0, 0.0])
        n = ref - np.dot(ref, t[0]) * t[0]
        normals[0] = n / np.linalg.norm(n)
        for i in range(1, len(t)):
            n = normals[i - 1] - np.dot(normals[i - 1], t[i]) * t[i]
            normals[i] = n / np.linalg.norm(n)
    return normals, np.cross(t, normals)


def sweep(
    section: np.ndarray,
    path: np.ndarray,
    closed: bool = False,
    up: np.ndarray | None = None,
    scales: np.ndarray | None = None,
) -> Mesh:
    """Sweep a 2D section along a 3D polyline (a bent tube, plank or rail).

    Args:
        section: (k, 2) closed outline; u follows the path normal, v the binormal.
        path: (m, 3) points; consecutive points must differ.
        closed: the path is a loop (no caps).
        up: keep the section's u axis as close as possible to this direction (planar bends);
            default: rotation-minimising frames.
        scales: (m,) optional scale of the section along the path (tapering).
    """
    path = np.asarray(path, float)
    normals, binormals = _frames(path, closed, up)
    sec = np.asarray(section, float)
    s = np.ones(len(path)) if scales is None else np.asarray(scales, float)
    rings = path[:, None, :] + s[:, None, None] * (
        sec[None, :, 0, None] * normals[:, None, :] + sec[None, :, 1, None] * binormals[:, None, :]
    )
    return rings_mesh(rings, sec, closed=closed)


def arc_path(radius: float, start: float, stop: float, n: int = 12) -> np.ndarray:
    """Points of a circular arc in the xy plane centred at the origin, angles in radians."""
    t = np.linspace(start, stop, n)
    return np.stack([radius * np.cos(t), radius * np.sin(t), np.zeros(n)], 1)


def bent_path(points: np.ndarray, radius: float, n_bend: int = 4) -> np.ndarray:
    """A polyline through ``points`` with every inner corner replaced by a circular-ish fillet.

    Used for tubular frames (cantilever chairs, hairpin legs, rails): straight runs joined by
    bends of about ``radius``.
    """
    pts = np.asarray(points, float)
    out = [pts[0]]
    for i in range(1, len(pts) - 1):
        a, b, c = pts[i - 1], pts[i], pts[i + 1]
        da, dc = a - b, c - b
        la, lc = np.linalg.norm(da), np.linalg.norm(dc)
        r = min(radius, 0.45 * la, 0.45 * lc)
        p, q = b + da / la * r, b + dc / lc * r
        for t in np.linspace(0, 1, n_bend + 2):
            out.append((1 - t) ** 2 * p + 2 * (1 - t) * t * b + t**2 * q)
    out.append(pts[-1])
    return np.array(out)


def plate(outline_xz: np.ndarray, thickness: float, bevel: float = 0.0) -> Mesh:
    """A horizontal slab: outline (x, z) extruded along y, centred at y = 0 (seats, table tops)."""
    return extrude(outline_xz, thickness, bevel).transformed(rotation("x", 0.5 * np.pi))


def panel(outline_zy: np.ndarray, thickness: float, bevel: float = 0.0) -> Mesh:
    """A vertical slab facing +x: outline (z, y) extruded along x, centred at x = 0 (backs)."""
    return extrude(outline_zy, thickness, bevel).transformed(rotation("y", -0.5 * np.pi))


def side_panel(outline_xy: np.ndarray, thickness: float, bevel: float = 0.0) -> Mesh:
    """A vertical slab seen from the side: outline (x, y) extruded along z, centred at z = 0."""
    return extrude(outline_xy, thickness, bevel)


def curved_plank(
    span: float, bulge: float, height: float, thickness: float, n: int = 9, corner: float = 0.0
) -> Mesh:
    """A vertical plank along z bent backwards (towards -x) by ``bulge`` at its middle.

    Its cross-section is ``height`` (y) x ``thickness`` (x); the chord spans z in [-span/2, span/2]
    and the ends stay at x = 0 (chair top rails, curved backs). Symmetric under z -> -z.
    """
    z = np.linspace(-span / 2, span / 2, n)
    path = np.stack([-bulge * (1 - (2 * z / span) ** 2), np.zeros(n), z], 1)
    return sweep(rounded_rect(height, thickness, corner, 2), path, up=np.array([0.0, 1.0, 0.0]))
