"""Watercraft: sailboat, motorboat, cargo ship and rowing boat.

Labels (no ShapeNet part benchmark here): hull, deck, cabin, mast, sail, engine, funnel, cargo,
seat, oar. Frame: bow towards +x, up +y, beam along z. Hulls are open shells (a thick U section
lofted from stern to bow) with the deck laid inside at the gunwale, so the deck stays a part of
its own after preprocessing. Build units: about 2 long (the sailboat's mast makes it taller).
"""

from __future__ import annotations

import numpy as np

from training.data.generator.assembly import ShapeBuilder
from training.data.generator.mesh import Mesh, compose, concatenate, rotation, translation
from training.data.generator.outlines import ccw, chaikin, rounded_rect
from training.data.generator.primitives import (
    bent_path,
    box,
    capsule,
    ellipsoid,
    extrude,
    frustum,
    loft,
    plate,
    rod,
    sweep,
)

LABELS = ("hull", "deck", "cabin", "mast", "sail", "engine", "funnel", "cargo", "seat", "oar")


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _u_section(vee: float, wall: float, n: int = 9) -> tuple[np.ndarray, np.ndarray]:
    """A thick U cross-section (u = y, v = z): outer bottom curve of depth 1 and half-width 1,
    inner curve offset by ``wall``, open at the top (y = 0). ``vee`` < 1 makes it V-shaped.

    Returns the section (outer curve, then the inner one backwards) and its triangulation as a
    strip between the two curves (ear clipping would meet the collinear points at the top).
    """
    t = np.linspace(0.0, np.pi, n)
    outer = np.stack([-(np.abs(np.sin(t)) ** (1.0 / vee)), np.cos(t)], 1)
    inner = np.stack([-(1 - wall) * np.abs(np.sin(t[::-1])) ** (1.0 / vee), (1 - wall) * np.cos(t[::-1])], 1)
    i = np.arange(n - 1)
    j, j1 = 2 * n - 1 - i, 2 * n - 2 - i  # inner partners of outer points i and i + 1
    strip = np.concatenate([np.stack([i, i + 1, j1], 1), np.stack([i, j1, j], 1)])
    return np.concatenate([outer, inner]), strip


def hull_shell(
    length: float, beam: np.ndarray, depth: np.ndarray, sheer: np.ndarray, vee: float, wall: float
) -> tuple[Mesh, np.ndarray, np.ndarray]:
    """An open hull: a thick U section lofted along x over stations from stern to bow.

    Args:
        beam, depth, sheer: (m,) half-width, depth and gunwale height at evenly spaced stations
            from the stern (x = -length/2) to the bow (x = +length/2).
    Returns:
        the mesh, the station x coordinates and the inner half-width at each station.
    """
    xs = np.linspace(-length / 2, length / 2, len(beam))
    section, strip = _u_section(vee, wall)
    mesh = loft(
        section,
        xs,
        np.stack([sheer, np.zeros_like(sheer)], 1),
        np.stack([depth, beam], 1),
        axis="x",
        cap=strip,
    )
    return mesh, xs, beam * (1 - wall)


def _deck_outline(xs: np.ndarray, half: np.ndarray, inset: float) -> np.ndarray:
    """Plan outline (x, z) inside the gunwale, from the inner half-widths per station."""
    h = np.maximum(half - inset, 0.01)
    right = np.stack([xs, h], 1)
    left = np.stack([xs[::-1], -h[::-1]], 1)
    return ccw(np.concatenate([right, left]))


def _decked_hull(
    b: ShapeBuilder,
    length: float,
    beam: np.ndarray,
    depth: np.ndarray,
    sheer: np.ndarray,
    vee: float,
    wall: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Adds a ``hull_shell`` (arguments as there) and a flush deck plate inside its gunwale; returns the
    station x coordinates and the inner half-width at each station."""
    hull, xs, inner = hull_shell(length, beam, depth, sheer, vee, wall)
    b.add(hull, "hull")
    dt = 0.025
    b.add(plate(_deck_outline(xs, inner, 0.0), dt), "deck", [translation(0, -dt / 2 - 0.005, 0)])
    return xs, inner


def _profile(m: int, stern: float, mid: float, bow: float, power: float = 1.5) -> np.ndarray:
    """A smooth fore-aft profile: ``stern`` at the stern, ``mid`` around 40 %, ``bow`` at the bow."""
    s = np.linspace(0.0, 1.0, m)
    aft = stern + (mid - stern) * np.sin(np.clip(s / 0.4, 0, 1) * 0.5 * np.pi)
    fore = bow + (mid - bow) * (1 - np.clip((s - 0.4) / 0.6, 0, 1) ** power)
    return np.where(s <= 0.4, aft, fore)


def sailboat(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Sailing yacht: hull with fin keel and rudder, deck, coachroof cabin, mast, main and jib."""
    L, W, D = _u(rng, 1.296, 2.104), _u(rng, 0.189, 0.331), _u(rng, 0.137, 0.243)
    m = 9
    beam = _profile(m, 0.75 * W, W, 0.02)
    depth = _profile(m, 0.6 * D, D, 0.35 * D)
    sheer = np.linspace(0.0, 0.04, m)
    xs, inner = _decked_hull(b, L, beam, depth, sheer, 1.2, 0.12)
    kl, kd = _u(rng, 0.3, 0.45), _u(rng, 0.3, 0.45)
    keel = chaikin(np.array([[kl / 2, 0.05], [-kl / 2, 0.05], [-kl / 3, -kd], [kl / 3, -kd]]), 1)
    b.add(extrude(keel, 0.03, 0.005), "hull", [translation(_u(rng, -0.05, 0.1), -0.9 * D, 0)])
    b.add(
        extrude(np.array([[0.05, 0.0], [-0.05, 0.0], [-0.04, -0.12], [0.02, -0.12]]), 0.015),
        "hull",
        [translation(-L / 2 + 0.12, -0.5 * D, 0)],
    )
    cl, ch = _u(rng, 0.4, 0.6), _u(rng, 0.1, 0.15)
    xc = _u(rng, -0.2, 0.0)
    cabin = chaikin(np.array([[cl / 2, -0.01], [cl / 2 - 0.08, ch], [-cl / 2, ch], [-cl / 2, -0.01]]), 1)
    b.add(extrude(cabin, 1.4 * W * 0.7, 0.02), "cabin", [translation(xc, 0.0, 0)])
    b.add(
        frustum(0.025, 0.02, 0.03, 10),
        "cabin",
        [translation(xc - cl / 2 + 0.07, ch - 0.01, sz * (0.7 * W - 0.05)) for sz in (1, -1)],
    )  # winches
    stanchions = [
        translation(x, 0.0, sz * (float(np.interp(x, xs, inner)) - 0.015))
        for x in np.linspace(-0.3 * L, 0.25 * L, 4)
        for sz in (1, -1)
    ]
    b.add(rod([0, -0.01, 0], [0, 0.09, 0], 0.005, segments=6), "deck", stanchions)
    hm, xm = _u(rng, 1.2, 1.6), xc + cl / 2 - 0.04
    b.add(rod([xm, -0.02, 0], [xm, hm, 0], _u(rng, 0.012, 0.018), segments=8), "mast")
    boom_y, main_l = ch + _u(rng, 0.06, 0.12), _u(rng, 0.5, 0.7)
    main = np.array([[-0.005, boom_y], [-0.005, hm - 0.05], [-main_l, boom_y + 0.02]])
    b.add(extrude(main, 0.01), "sail", [translation(xm, 0, 0)])
    bow_x = L / 2 - 0.08
    jib = np.array([[bow_x, 0.08], [xm + 0.02, 0.85 * hm], [xm + 0.02, 0.12]])
    b.add(extrude(jib, 0.01), "sail")


def motorboat(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Motor cruiser: deep-V hull, deck, cabin with windscreen, bow rail on posts, outboard engine."""
    L, W, D = _u(rng, 1.384, 2.216), _u(rng, 0.258, 0.442), _u(rng, 0.171, 0.309)
    m = 9
    beam = _profile(m, 0.9 * W, W, 0.03, 2.0)
    depth = _profile(m, 0.8 * D, D, 0.5 * D)
    sheer = np.linspace(0.0, 0.08, m)
    xs, inner = _decked_hull(b, L, beam, depth, sheer, 0.7, 0.1)
    cl, ch = _u(rng, 0.5, 0.75), _u(rng, 0.18, 0.26)
    xc = _u(rng, -0.25, -0.05)
    side = chaikin(
        np.array([[cl / 2, -0.01], [cl / 2 - 0.15, ch], [-cl / 2 + 0.05, ch], [-cl / 2, -0.01]]), 1
    )
    cw = 1.5 * W
    b.add(extrude(side, cw, 0.03), "cabin", [translation(xc, 0, 0)])
    shield = np.array(
        [
            [cl / 2 + 0.005, 0.03],
            [cl / 2 - 0.145, ch + 0.005],
            [cl / 2 - 0.17, ch + 0.005],
            [cl / 2 - 0.02, 0.03],
        ]
    )
    b.add(extrude(shield, cw - 0.06), "cabin", [translation(xc, 0, 0)])
    # Bow rail: one bent tube around the foredeck at rail height, on short posts.
    hr = _u(rng, 0.08, 0.12)
    x0 = xc + cl / 2 + 0.05
    k = np.searchsorted(xs, x0)
    pts = [[x0, hr, inner[k] - 0.03]] + [
        [x, hr + sheer[i], max(inner[i] - 0.03, 0.0)]
        for i, x in enumerate(xs)
        if x > x0 + 0.05 and x < L / 2 - 0.1
    ]
    pts = pts + [[L / 2 - 0.06, hr + sheer[-1], 0.0]] + [[p[0], p[1], -p[2]] for p in pts[::-1]]
    rail = sweep(
        np.array([[0.008, 0.0], [0.0, 0.008], [-0.008, 0.0], [0.0, -0.008]]),
        bent_path(np.array(pts), 0.05, 2),
    )
    b.add(rail, "deck")
    post = rod([0, -0.01, 0], [0, hr + 0.01, 0], 0.006, segments=6)
    b.add(post, "deck", [translation(p[0], p[1] - hr, p[2]) for p in pts[:: max(1, len(pts) // 6)]])
    # Outboard engine on the transom: cowling block and leg.
    eh = _u(rng, 0.14, 0.2)
    b.add(
        plate(rounded_rect(0.14, 0.12, 0.04), eh, 0.02),
        "engine",
        [translation(-L / 2 - 0.05, 0.04 + eh / 2, 0)],
    )
    b.add(box(0.05, 0.35, 0.03), "engine", [translation(-L / 2 - 0.05, 0.04 - 0.17, 0)])


def ship(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Cargo ship: long blunt hull, deck, container stacks, two-tier bridge, funnel and mast."""
    L, W, D = _u(rng, 1.66, 2.34), _u(rng, 0.155, 0.265), _u(rng, 0.12, 0.22)
    m = 11
    beam = _profile(m, 0.95 * W, W, 0.05, 4.0)
    depth = _profile(m, 0.9 * D, D, 0.7 * D, 4.0)
    sheer = np.concatenate([np.zeros(m - 2), [0.02, 0.05]])
    _, inner = _decked_hull(b, L, beam, depth, sheer, 3.0, 0.08)
    # Bridge at the stern, in two tiers.
    xb, bl = -L / 2 + _u(rng, 0.15, 0.22), _u(rng, 0.18, 0.26)
    t1, t2 = _u(rng, 0.14, 0.2), _u(rng, 0.1, 0.14)
    b.add(box(bl, t1, 1.7 * W), "cabin", [translation(xb, t1 / 2 - 0.01, 0)])
    b.add(box(bl * 0.7, t2, 1.9 * W), "cabin", [translation(xb + 0.02, t1 + t2 / 2 - 0.015, 0)])
    b.add(
        loft(
            rounded_rect(1.0, 1.0, 0.3, 2),
            np.array([0.0, 0.22]),
            np.zeros((2, 2)),
            np.array([[0.1, 0.08], [0.09, 0.07]]),
            axis="y",
        ),
        "funnel",
        [translation(xb - bl / 2 - 0.02, t1 - 0.03, 0)],
    )
    b.add(
        rod([xb + 0.04, t1 + t2 - 0.03, 0], [xb + 0.04, t1 + t2 + _u(rng, 0.2, 0.3), 0], 0.01, segments=6),
        "mast",
    )
    # Containers: identical boxes in rows and stacks between the bridge and the bow.
    cl_, ch_, cw_ = _u(rng, 0.22, 0.28), _u(rng, 0.08, 0.1), _u(rng, 0.11, 0.14)
    rows = max(1, int((2 * inner.max() - 0.02) // cw_))
    cols = int(rng.integers(3, 5))
    stacks = int(rng.integers(1, 3))
    x0 = xb + bl / 2 + 0.04
    places = [
        translation(x0 + cl_ * (c + 0.5) + 0.01 * c, ch_ * (s + 0.5) - 0.005, cw_ * (r - (rows - 1) / 2))
        for c in range(cols)
        for r in range(rows)
        for s in range(stacks)
    ]
    b.add(box(cl_, ch_, cw_ - 0.006), "cargo", places)


def rowboat(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Rowing boat: double-ended open hull, plank seats across it, two oars resting in oarlocks."""
    L, W, D = _u(rng, 1.384, 2.216), _u(rng, 0.242, 0.398), _u(rng, 0.172, 0.288)
    m = 11
    s = np.linspace(-1, 1, m)
    beam = np.maximum(W * (1 - np.abs(s) ** 2.2), 0.03)
    depth = D * (1 - 0.4 * s**2)
    sheer = 0.08 * s**2
    hull, xs, inner = hull_shell(L, beam, depth, sheer, 1.3, 0.08)
    b.add(hull, "hull")
    n = int(rng.integers(2, 4))
    sw, st = _u(rng, 0.1, 0.14), 0.025
    seat_x = np.linspace(-0.25 * L, 0.25 * L, n)
    sy = -_u(rng, 0.04, 0.07)  # well above the bottom, so a seat stays a part of its own
    # Seats touch the inner walls: their length follows the width where they sit.
    for x in seat_x:
        half = float(np.interp(x, xs, inner)) * (1 - 0.2 * (-sy / D))
        b.add(plate(rounded_rect(sw, 2 * half + 0.01, 0.01), st, 0.004), "seat", [translation(x, sy, 0)])
    ol = _u(rng, 1.0, 1.3)
    blade = ellipsoid(0.12, 0.008, 0.045, 10, 4).transformed(translation(-ol / 2 + 0.1, 0, 0))
    shaft = capsule(ol - 0.15, 0.012, 8, 2).transformed(
        compose(rotation("z", -0.5 * np.pi), translation(0, -ol / 2 + 0.15, 0))
    )
    oar = concatenate([shaft, blade])
    xo = float(seat_x[len(seat_x) // 2]) + 0.05
    zo = float(np.interp(xo, xs, beam))
    ang = _u(rng, 0.2, 0.5)
    b.add(
        oar,
        "oar",
        [
            compose(
                translation(xo, 0.02 + np.interp(xo, xs, sheer), sz * zo),
                rotation("y", sz * (0.5 * np.pi - ang)),
            )
            for sz in (1, -1)
        ],
    )
    b.add(
        frustum(0.012, 0.012, 0.05, 8),
        "hull",
        [translation(xo, float(np.interp(xo, xs, sheer)) - 0.02, sz * zo) for sz in (1, -1)],
    )


STYLES = {"sailboat": sailboat, "motorboat": motorboat, "ship": ship, "rowboat": rowboat}
