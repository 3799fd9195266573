"""Closed 2D outlines (table tops, wing and guitar-body profiles, cross-sections) and their
triangulation.

Every outline is a simple polygon, counter-clockwise, without repeated points. Curvy outlines
are made from a few control points smoothed by corner cutting, so a style fixes the control
polygon's construction and the random proportions only move its points.

Shapes:
    an outline is (n, 2) float64.
"""

from __future__ import annotations

import numpy as np


def signed_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return float(0.5 * (np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def ccw(poly: np.ndarray) -> np.ndarray:
    """The polygon in counter-clockwise order."""
    poly = np.asarray(poly, dtype=float)
    return poly if signed_area(poly) > 0 else poly[::-1].copy()


def ellipse(a: float, b: float, n: int = 24) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([a * np.cos(t), b * np.sin(t)], axis=1)


def superellipse(a: float, b: float, exponent: float, n: int = 32) -> np.ndarray:
    """|x/a|^e + |y/b|^e = 1: e = 2 is an ellipse, large e tends to a rectangle."""
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    c, s = np.cos(t), np.sin(t)
    p = 2.0 / exponent
    return np.stack([a * np.sign(c) * np.abs(c) ** p, b * np.sign(s) * np.abs(s) ** p], axis=1)


def rounded_rect(width: float, height: float, radius: float, corner_segments: int = 4) -> np.ndarray:
    """A width x height rectangle centred at the origin with rounded corners."""
    r = min(radius, 0.49 * width, 0.49 * height)
    if r <= 1e-9:
        return np.array([[width, height], [-width, height], [-width, -height], [width, -height]]) / 2
    hw, hh = width / 2 - r, height / 2 - r
    pts = []
    for cx, cy, start in ((hw, hh, 0.0), (-hw, hh, 0.5 * np.pi), (-hw, -hh, np.pi), (hw, -hh, 1.5 * np.pi)):
        for t in np.linspace(start, start + 0.5 * np.pi, corner_segments + 1):
            pts.append((cx + r * np.cos(t), cy + r * np.sin(t)))
    return np.array(pts)


def regular_polygon(radius: float, n: int, phase: float = 0.0) -> np.ndarray:
    t = phase + np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([radius * np.cos(t), radius * np.sin(t)], axis=1)


def chaikin(poly: np.ndarray, iterations: int = 2, closed: bool = True) -> np.ndarray:
    """Corner cutting: each iteration replaces every corner by two points at 1/4 and 3/4."""
    p = np.asarray(poly, dtype=float)
    for _ in range(iterations):
        nxt = np.roll(p, -1, axis=0) if closed else p[1:]
        cur = p if closed else p[:-1]
        q = 0.75 * cur + 0.25 * nxt
        r = 0.25 * cur + 0.75 * nxt
        out = np.empty((2 * len(cur), 2))
        out[0::2], out[1::2] = q, r
        p = out if closed else np.concatenate([p[:1], out, p[-1:]])
    return p


def mirrored_outline(half: np.ndarray) -> np.ndarray:
    """A closed outline symmetric about the x axis from its upper half.

    ``half`` runs from the left end to the right end with y >= 0; points with y == 0 at both
    ends lie on the axis and are not duplicated.
    """
    half = np.asarray(half, dtype=float)
    lower = half[::-1].copy()
    lower[:, 1] *= -1
    inner = lower[1:-1] if abs(half[0, 1]) < 1e-12 and abs(half[-1, 1]) < 1e-12 else lower
    return ccw(np.concatenate([half, inner]))


def naca_airfoil(thickness: float, n: int = 8) -> np.ndarray:
    """Symmetric NACA 00xx section, chord along x from 0 (leading edge) to 1, 2n points.

    Leading and trailing edges get a small finite thickness so the section never degenerates.
    """
    beta = np.linspace(0, np.pi, n)
    x = 0.5 * (1 - np.cos(beta))
    t = 5 * thickness * (0.2969 * np.sqrt(x) - 0.1260 * x - 0.3516 * x**2 + 0.2843 * x**3 - 0.1036 * x**4)
    t = np.maximum(t, 0.004)
    upper = np.stack([x[::-1], t[::-1]], axis=1)  # trailing edge -> leading edge, on top
    lower = np.stack([x, -t], axis=1)  # leading edge -> trailing edge, below
    return np.concatenate([upper, lower])


def _in_triangle(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray, eps: float) -> np.ndarray:
    """Which points p (n, 2) lie inside or on the counter-clockwise triangle abc."""

    def side(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return (u[0] - p[:, 0]) * (v[1] - p[:, 1]) - (u[1] - p[:, 1]) * (v[0] - p[:, 0])

    return (side(a, b) >= -eps) & (side(b, c) >= -eps) & (side(c, a) >= -eps)


def triangulate(poly: np.ndarray) -> np.ndarray:
    """Ear-clipping triangulation of a simple counter-clockwise polygon.

    Returns:
        (n - 2, 3) int64 vertex indices, counter-clockwise.
    """
    poly = np.asarray(poly, dtype=float)
    if signed_area(poly) <= 0:
        raise ValueError("triangulate expects a counter-clockwise polygon with positive area")
    idx = list(range(len(poly)))
    tris: list[tuple[int, int, int]] = []
    eps = 1e-12 * float(np.ptp(poly, axis=0).max()) ** 2
    while len(idx) > 3:
        n = len(idx)
        best = None
        for k in range(n):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % n]
            a, b, c = poly[i0], poly[i1], poly[i2]
            turn = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
            if turn <= eps:
                continue
            # Another remaining vertex inside (or on) the ear forbids it; copies of a, b or c don't.
            others = np.array([j for j in idx if j not in (i0, i1, i2)], dtype=np.int64)
            if len(others):
                pts = poly[others]
                same = np.all(pts == a, axis=1) | np.all(pts == b, axis=1) | np.all(pts == c, axis=1)
                if np.any(_in_triangle(pts, a, b, c, eps) & ~same):
                    continue
            best = k
            break
        if best is None:
            # Numerically stuck (collinear runs): clip the most convex corner.
            turns = []
            for k in range(n):
                a, b, c = poly[idx[k - 1]], poly[idx[k]], poly[idx[(k + 1) % n]]
                turns.append((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))
            best = int(np.argmax(turns))
        tris.append((idx[best - 1], idx[best], idx[(best + 1) % n]))
        del idx[best]
    tris.append((idx[0], idx[1], idx[2]))
    return np.array(tris, dtype=np.int64)
