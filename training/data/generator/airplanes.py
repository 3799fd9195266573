"""Airplanes: airliner (swept low wing, podded engines), fighter (delta wing, twin fins,
intakes and nozzles), light propeller plane (strut-braced high wing, propeller) and glider
(long slender wing, T-tail).

Labels follow the ShapeNet part benchmark: body, wing, tail, engine. Frame: nose towards +x,
up +y, span along z. Build units: about 2 long. Wings and horizontal tails are single pieces
spanning both sides (symmetric in themselves), as in many 3D Warehouse models.
"""

from __future__ import annotations

import numpy as np

from training.data.generator.assembly import ShapeBuilder
from training.data.generator.mesh import Mesh, compose, rotation, translation
from training.data.generator.outlines import chaikin, ellipse, naca_airfoil, superellipse
from training.data.generator.primitives import ellipsoid, extrude, lathe, loft, rod

LABELS = ("body", "wing", "tail", "engine")
_AIRFOIL = naca_airfoil(0.12, 7)
# The airfoil with its leading edge towards +x (chord runs from 0 at the LE to -1 at the TE).
_AIRFOIL_FWD = _AIRFOIL * [-1.0, 1.0]


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def fuselage(
    stations: np.ndarray,
    radii: np.ndarray,
    lift: np.ndarray,
    section: np.ndarray,
    width: np.ndarray | None = None,
) -> Mesh:
    """A loft along x of ``section`` (unit size, (y, z)) with per-station radius and centre height."""
    w = radii if width is None else width
    return loft(
        section, stations, np.stack([lift, np.zeros_like(lift)], 1), np.stack([radii, w], 1), axis="x"
    )


def wing(
    x_le: float,
    y: float,
    root: float,
    tip: float,
    span: float,
    sweep: float,
    dihedral: float,
    thickness: float = 1.0,
) -> Mesh:
    """A wing spanning z in [-span/2, span/2]: leading edge at ``x_le`` at the root, swept back by
    ``sweep`` (x shift at the tip), linear taper, dihedral rise at the tip."""
    z = np.linspace(-span / 2, span / 2, 5)
    f = np.abs(z) / (span / 2)
    chord = root + (tip - root) * f
    centers = np.stack([x_le - sweep * f, y + dihedral * f], 1)
    return loft(_AIRFOIL_FWD, z, centers, np.stack([chord, chord * thickness], 1), axis="z")


def fin(x_le: float, y0: float, root: float, tip: float, height: float, sweep: float) -> Mesh:
    """A vertical fin from y0 up by ``height``, symmetric about its own z = 0 plane."""
    ys = np.linspace(y0, y0 + height, 3)
    f = (ys - y0) / height
    chord = root + (tip - root) * f
    sec = _AIRFOIL_FWD[:, ::-1]  # (u, v) = (thickness -> z, chord -> x) for a loft along y
    centers = np.stack([np.zeros(3), x_le - sweep * f], 1)
    return loft(sec, ys, centers, np.stack([chord, chord], 1), axis="y")


def _along_x(mesh: Mesh) -> Mesh:
    """Turn a lathe built along +y so that its axis runs along +x."""
    return mesh.transformed(rotation("z", -0.5 * np.pi))


def _engine_pod(nr: float, nl: float) -> Mesh:
    """A nacelle along x, intake (open-looking lip) at x = 0 and exhaust cone towards -x."""
    prof = np.array([[0.8 * nr, 0.0], [nr, 0.08 * nl], [nr, 0.7 * nl], [0.55 * nr, nl], [0.0, nl]])
    return _along_x(lathe(prof, 14)).transformed(rotation("y", np.pi))


def airliner(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Tube fuselage in two sections, swept low wing, podded engines, conventional tail."""
    L, R = _u(rng, 1.8, 2.0), _u(rng, 0.075, 0.11)
    xs = L / 2 - np.array([0.0, 0.02, 0.06, 0.12, 0.2, 0.5, 0.72, 0.85, 0.95, 1.0]) * L
    r = R * np.array([0.12, 0.5, 0.78, 0.94, 1.0, 1.0, 0.95, 0.7, 0.4, 0.2])
    lift = R * np.array([-0.3, -0.2, -0.1, -0.03, 0.0, 0.0, 0.05, 0.25, 0.5, 0.6])
    circle = ellipse(1.0, 1.0, 16)
    cut = 5
    b.add(fuselage(xs[: cut + 1], r[: cut + 1], lift[: cut + 1], circle), "body")
    b.add(fuselage(xs[cut:], r[cut:], lift[cut:], circle), "body")
    b.add(ellipsoid(0.04, 0.02, 0.6 * R, 10, 4), "body", [translation(xs[2] - 0.02, lift[2] + 0.6 * r[2], 0)])
    span, root = _u(rng, 1.384, 2.216), _u(rng, 0.3, 0.42)
    x_wing, sweep, dihedral = _u(rng, 0.05, 0.2), _u(rng, 0.25, 0.45), _u(rng, 0.05, 0.1)
    y_wing = -0.45 * R
    b.add(wing(x_wing, y_wing, root, root * _u(rng, 0.25, 0.4), span, sweep, dihedral), "wing")
    hs_span, hs_root = span * _u(rng, 0.3, 0.4), root * _u(rng, 0.45, 0.6)
    b.add(
        wing(-L / 2 + 0.04 + hs_root, lift[-2], hs_root, hs_root * 0.45, hs_span, hs_root * 0.6, 0.02), "tail"
    )
    fr = _u(rng, 0.25, 0.35)
    b.add(
        fin(
            -L / 2 + 0.02 + fr,
            lift[-2] + 0.2 * R,
            fr,
            0.12,
            _u(rng, 0.2, 0.32) + 0.2 * R,
            _u(rng, 0.15, 0.25),
        ),
        "tail",
    )
    # Engines: identical nacelles touching the wing's lower surface, 2 or 4.
    nr, nl = _u(rng, 0.045, 0.065), _u(rng, 0.2, 0.3)
    places = []
    for f in [0.33] if rng.random() < 0.6 else [0.27, 0.55]:
        x_le = x_wing - sweep * f
        y = y_wing + dihedral * f - nr * 0.9
        places += [translation(x_le + 0.35 * nl, y, sz * f * span / 2) for sz in (1, -1)]
    b.add(_engine_pod(nr, nl), "engine", places)


def fighter(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Flat fuselage with bubble canopy, delta wing, twin fins, side intakes, one or two nozzles."""
    L, R = _u(rng, 1.8, 2.0), _u(rng, 0.1, 0.13)
    xs = L / 2 - np.array([0.0, 0.05, 0.15, 0.3, 0.45, 0.7, 0.9, 1.0]) * L
    r = R * np.array([0.05, 0.35, 0.65, 0.85, 0.9, 0.9, 0.85, 0.8])
    w = R * np.array([0.05, 0.4, 0.75, 1.0, 1.45, 1.55, 1.5, 1.4])
    lift = R * np.array([0.1, 0.05, 0.1, 0.1, 0.0, 0.0, 0.05, 0.05])
    b.add(fuselage(xs, r, lift, superellipse(1.0, 1.0, 2.6, 16), w), "body")
    cl = _u(rng, 0.25, 0.35)
    b.add(
        ellipsoid(cl / 2, 0.5 * R + 0.04, 0.5 * R, 14, 6),
        "body",
        [translation(xs[2] - cl / 2, lift[2] + 0.55 * R, 0)],
    )
    span, root = _u(rng, 0.856, 1.544), _u(rng, 0.7, 0.95)
    b.add(
        wing(
            -L / 2 + 0.05 + root,
            0.0,
            root,
            root * _u(rng, 0.1, 0.2),
            span,
            root * _u(rng, 0.7, 0.9),
            -0.02,
            0.6,
        ),
        "wing",
    )
    fz, fr = _u(rng, 0.4, 0.7) * R * 1.5, _u(rng, 0.25, 0.32)
    fin_mesh = fin(-L / 2 + 0.02 + fr, 0.8 * R - 0.02, fr, 0.08, _u(rng, 0.25, 0.35), _u(rng, 0.15, 0.22))
    b.add(fin_mesh, "tail", [translation(0, 0, fz), translation(0, 0, -fz)])
    ht = _u(rng, 0.18, 0.25)
    b.add(wing(-L / 2 + ht, 0.0, ht, ht * 0.4, _u(rng, 0.55, 0.75), ht * 0.5, 0.0, 0.7), "tail")
    twin = rng.random() < 0.5
    nr = (0.55 if twin else 0.8) * R
    nozzle = _along_x(lathe(np.array([[nr, 0.0], [nr * 0.95, 0.1], [nr * 0.8, 0.14]]), 14)).transformed(
        rotation("y", np.pi)
    )
    zn = [nr * 1.05, -nr * 1.05] if twin else [0.0]
    b.add(nozzle, "engine", [translation(-L / 2 + 0.02, lift[-1], z) for z in zn])
    il = _u(rng, 0.35, 0.5)
    intake = loft(
        superellipse(1.0, 1.0, 3.0, 12),
        np.array([-il, 0.0]),
        np.zeros((2, 2)),
        np.array([[0.45 * R, 0.3 * R], [0.55 * R, 0.35 * R]]),
        axis="x",
    )
    xi = xs[3] + _u(rng, -0.08, 0.0)
    b.add(intake, "engine", [translation(xi, -0.1 * R, R), translation(xi, -0.1 * R, -R)])


def propeller(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Light aircraft: boxy fuselage, strut-braced high wing, cowling with a propeller, wheel pants;
    some are tri-motors with two more engines under the wing."""
    L, R = _u(rng, 1.4, 1.7), _u(rng, 0.1, 0.13)
    xs = L / 2 - np.array([0.0, 0.12, 0.3, 0.5, 0.75, 1.0]) * L
    r = R * np.array([0.8, 1.0, 1.05, 0.85, 0.5, 0.25])
    lift = R * np.array([-0.1, 0.0, 0.05, 0.1, 0.3, 0.45])
    sec = superellipse(1.0, 1.0, 3.2, 16)
    b.add(fuselage(xs[1:], r[1:], lift[1:], sec, 0.85 * r[1:]), "body")
    grow = np.array([0.85, 1.01])
    b.add(
        fuselage(np.array([xs[0] + 0.02, xs[1] - 0.02]), r[:2] * grow, lift[:2], sec, 0.85 * r[:2] * grow),
        "engine",
    )
    b.add(
        _along_x(lathe(np.array([[0.35 * R, 0.0], [0.2 * R, 0.06], [0.0, 0.1]]), 12)),
        "engine",
        [translation(xs[0] + 0.02, lift[0], 0)],
    )
    bl = _u(rng, 0.26, 0.36)
    blade = extrude(chaikin(np.array([[0.0, -0.025], [bl, -0.02], [bl, 0.02], [0.0, 0.03]]), 1), 0.012)
    nb = int(rng.choice([2, 3]))
    hub = translation(xs[0] + 0.05, lift[0], 0)
    # The blade lies in the plane of the disc (y, z): turn its length from +x to +y, spin about x.
    b.add(
        blade.transformed(rotation("z", 0.5 * np.pi)),
        "engine",
        [compose(hub, rotation("x", 2 * np.pi * k / nb + 0.3)) for k in range(nb)],
    )
    span, chord = _u(rng, 1.472, 2.328), _u(rng, 0.24, 0.32)
    x_w = xs[1] - _u(rng, 0.05, 0.15)
    y_w = lift[2] + r[2] * 0.95
    b.add(wing(x_w, y_w, chord, chord * _u(rng, 0.85, 1.0), span, 0.0, 0.02), "wing")
    zs = span * _u(rng, 0.25, 0.32)
    strut = rod([0, lift[2] - 0.6 * R, 0.7 * R], [0, y_w, zs], 0.01, segments=8)
    at = translation(x_w - chord * 0.4, 0, 0)
    b.add(strut, "wing", [at, compose(at, rotation("y", np.pi))])
    if rng.random() < 0.35:
        # Tri-motor: a pair of nacelles hung under the wing, as in ShapeNet's underwing engines.
        nr, nl = 0.55 * R, _u(rng, 0.22, 0.3)
        zn = span * _u(rng, 0.14, 0.2)
        pods = [translation(x_w + 0.06, y_w - 0.7 * nr, sz * zn) for sz in (1, -1)]
        b.add(_engine_pod(nr, nl), "engine", pods)
    hs_span, hs_chord = _u(rng, 0.5, 0.7), _u(rng, 0.14, 0.2)
    b.add(wing(-L / 2 + hs_chord - 0.02, lift[-1], hs_chord, hs_chord * 0.7, hs_span, 0.03, 0.0), "tail")
    b.add(fin(-L / 2 + 0.22, lift[-1], 0.24, 0.1, _u(rng, 0.2, 0.28), 0.12), "tail")
    # Wheel pants under the fuselage: small, they merge into it.
    pants = ellipsoid(0.07, 0.04, 0.025, 12, 6)
    b.add(pants, "body", [translation(xs[2], lift[2] - 0.85 * r[2] - 0.03, sz * 0.5 * R) for sz in (1, -1)])


def glider(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Sailplane: slim pod-and-boom fuselage, very long straight wing, T-tail, canopy."""
    L, R = _u(rng, 1.2, 1.5), _u(rng, 0.055, 0.075)
    xs = L / 2 - np.array([0.0, 0.05, 0.15, 0.3, 0.45, 0.7, 1.0]) * L
    r = R * np.array([0.15, 0.6, 0.95, 1.0, 0.6, 0.4, 0.3])
    lift = R * np.array([-0.2, -0.1, 0.0, 0.0, 0.15, 0.25, 0.3])
    b.add(fuselage(xs, r, lift, ellipse(1.0, 1.0, 14)), "body")
    b.add(ellipsoid(0.16, 0.5 * R + 0.03, 0.55 * R, 12, 5), "body", [translation(xs[2] - 0.05, 0.6 * R, 0)])
    span, root = _u(rng, 1.9, 2.0), _u(rng, 0.12, 0.17)
    x_le, dihedral = xs[3] + root * 0.6, _u(rng, 0.03, 0.08)
    b.add(wing(x_le, 0.5 * R, root, root * 0.45, span, 0.04, dihedral), "wing")
    # Aileron hinges: identical pins through the wing near its trailing edge.
    hinges = [
        [x_le - 0.04 * f - 0.8 * root * (1 - 0.55 * f), 0.5 * R + dihedral * f, sz * f * span / 2]
        for f in (0.55, 0.8)
        for sz in (1, -1)
    ]
    b.bolts(np.array(hinges), "wing", 0.008, 0.03)
    fh = _u(rng, 0.18, 0.26)
    b.add(fin(-L / 2 + 0.19, lift[-1], 0.18, 0.11, fh, 0.06), "tail")
    b.add(wing(-L / 2 + 0.13, lift[-1] + fh - 0.01, 0.1, 0.06, _u(rng, 0.35, 0.45), 0.03, 0.0), "tail")


STYLES = {"airliner": airliner, "fighter": fighter, "propeller": propeller, "glider": glider}
