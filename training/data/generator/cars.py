"""Cars: sedan, SUV (roof rails, spare wheel), sports coupe (long hood, spoiler) and pickup
(cab and cargo bed).

Labels follow the ShapeNet part benchmark: body, wheel, hood, roof. Frame: front towards +x, up
+y, width along z. The lower body is a side profile with wheel arches extruded across the car;
hood, cabin (roof) and trunk are blocks on top of it, so each stays a part of its own after
preprocessing. Build units: about 2 long.
"""

from __future__ import annotations

import numpy as np

from training.data.generator.assembly import ShapeBuilder
from training.data.generator.mesh import Mesh, compose, rotation, translation
from training.data.generator.outlines import chaikin, rounded_rect
from training.data.generator.primitives import box, ellipsoid, extrude, frustum, lathe, plate

LABELS = ("body", "wheel", "hood", "roof")


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _side_profile(
    L: float,
    y_bot: float,
    y_top: float,
    arches: list[float],
    arch_r: float,
    axle_y: float,
    nose: float,
    tail: float,
) -> np.ndarray:
    """Side outline (x, y) of the lower body with wheel arches cut around the axles at ``arches``.

    ``nose`` / ``tail`` round the front / rear top corners by that much.
    """
    pts = [[-L / 2, y_bot]]
    for x in sorted(arches):
        t = np.linspace(np.pi, 0.0, 7)
        dy = np.sqrt(max(arch_r**2 - (axle_y - y_bot) ** 2, 1e-6))
        pts.append([x - dy, y_bot])
        pts += [[x + arch_r * np.cos(a), axle_y + arch_r * np.sin(a)] for a in t[1:-1]]
        pts.append([x + dy, y_bot])
    pts += [
        [L / 2, y_bot],
        [L / 2, y_top - nose],
        [L / 2 - nose, y_top],
        [-L / 2 + tail, y_top],
        [-L / 2, y_top - tail],
    ]
    return np.array(pts)


def _wheel(rw: float, ww: float) -> tuple[Mesh, Mesh, Mesh, list[np.ndarray]]:
    """Tyre (a revolved rounded rectangle), rim disc inside it and one lug nut with its
    placements on the rim's outer (+z) face; axis along z, centre at the origin."""
    to_z = rotation("x", 0.5 * np.pi)
    section = rounded_rect(0.38 * rw, ww, 0.3 * ww, 1) + np.array([0.81 * rw, 0.0])
    tyre = lathe(section, 16, closed=True).transformed(to_z)
    rim = lathe(
        np.array(
            [
                [0.0, -0.3 * ww],
                [0.64 * rw, -0.35 * ww],
                [0.64 * rw, 0.35 * ww],
                [0.25 * rw, 0.3 * ww],
                [0.2 * rw, 0.4 * ww],
                [0.0, 0.4 * ww],
            ]
        ),
        16,
    ).transformed(to_z)
    nut = frustum(0.035 * rw + 0.006, 0.02 * rw + 0.004, 0.02, 6).transformed(to_z)
    nuts = [
        translation(0.32 * rw * np.cos(a), 0.32 * rw * np.sin(a), 0.3 * ww)
        for a in np.arange(5) * 0.4 * np.pi
    ]
    return tyre, rim, nut, nuts


def _add_wheels(
    b: ShapeBuilder, rw: float, ww: float, xs: list[float], z: float
) -> list[tuple[int, list[np.ndarray]]]:
    """Four identical wheels, rims facing outwards; returns (key, local placements) per geometry
    so more instances (a spare wheel) can be placed."""
    tyre, rim, nut, nuts = _wheel(rw, ww)
    places = [
        compose(translation(x, rw, sz * z), rotation("y", 0.0 if sz > 0 else np.pi))
        for x in xs
        for sz in (1, -1)
    ]
    parts = [(tyre, [np.eye(4)]), (rim, [np.eye(4)]), (nut, nuts)]
    return [(b.add(m, "wheel", [compose(p, q) for p in places for q in local]), local) for m, local in parts]


def _block(outline_xy: np.ndarray, width: float, bevel: float) -> Mesh:
    return extrude(chaikin(outline_xy, 1), width, bevel)


def _hood(
    b: ShapeBuilder,
    L: float,
    W: float,
    yb: float,
    hh: float,
    x_ws: float,
    nose: tuple[float, float, float],
    inset: float = 0.04,
    bevel: float = 0.02,
) -> None:
    """Hood block on the lower body (top at ``yb``), from the front back to the windscreen foot at
    ``x_ws``, where it stands ``hh`` high.

    ``nose``: how far its foot and its top front corner stand back from the car's front, and that
    corner's height as a share of ``hh``; ``inset``: how much narrower than the body (``W``) it is.
    """
    foot, top, rise = nose
    outline = np.array(
        [[L / 2 - foot, yb - 0.03], [L / 2 - top, yb + rise * hh], [x_ws, yb + hh], [x_ws, yb - 0.03]]
    )
    b.add(_block(outline, W - inset, bevel), "hood")


def _cabin(
    b: ShapeBuilder,
    W: float,
    yb: float,
    ch: float,
    x_ws: float,
    roof: tuple[float, float],
    back: float,
    inset: float,
    bevel: float,
) -> None:
    """Cabin block (label roof) on the lower body (top at ``yb``): from the windscreen foot at ``x_ws``
    up to a flat roof ``ch`` high between the x of ``roof`` (front, back), down to its rear foot at
    ``back``; ``inset`` narrower than the body (``W``)."""
    outline = np.array([[x_ws + 0.02, yb - 0.02], [roof[0], yb + ch], [roof[1], yb + ch], [back, yb - 0.02]])
    b.add(_block(outline, W - inset, bevel), "roof")


def _lights(b: ShapeBuilder, x: float, y: float, z: float) -> None:
    b.add(ellipsoid(0.02, 0.03, 0.06, 10, 4), "body", [translation(x, y, z), translation(x, y, -z)])


def sedan(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Three-box sedan: lower body, hood, cabin with side windows, trunk, four wheels."""
    L, W = _u(rng, 1.572, 2.228), _u(rng, 0.654, 0.946)
    rw, ww = _u(rng, 0.15, 0.18), _u(rng, 0.1, 0.13)
    xf, xr = L / 2 - _u(rng, 0.3, 0.36), -L / 2 + _u(rng, 0.3, 0.38)
    yb = 2 * rw + _u(rng, 0.06, 0.12)
    body = _side_profile(L, 0.45 * rw, yb, [xf, xr], rw + 0.02, rw, 0.08, 0.06)
    b.add(extrude(chaikin(body, 1), W, 0.03), "body")
    hh, x_ws = _u(rng, 0.085, 0.12), _u(rng, 0.1, 0.25)
    _hood(b, L, W, yb, hh, x_ws, (0.03, 0.06, 0.6))
    ch, cl = _u(rng, 0.24, 0.32), _u(rng, 0.75, 0.95)
    x_rear = x_ws - cl
    _cabin(b, W, yb, ch, x_ws, (x_ws - 0.22, x_rear + 0.2), x_rear - 0.02, 0.08, 0.06)
    win = np.array(
        [
            [x_ws - 0.06, yb + 0.04],
            [x_ws - 0.24, yb + ch - 0.05],
            [x_rear + 0.22, yb + ch - 0.05],
            [x_rear + 0.06, yb + 0.04],
        ]
    )
    b.add(extrude(win, 0.012), "roof", [translation(0, 0, W / 2 - 0.04), translation(0, 0, -W / 2 + 0.04)])
    b.add(
        _block(
            np.array(
                [
                    [x_rear + 0.02, yb - 0.03],
                    [x_rear + 0.02, yb + 0.9 * hh],
                    [-L / 2 + 0.05, yb + 0.8 * hh],
                    [-L / 2 + 0.03, yb - 0.03],
                ]
            ),
            W - 0.04,
            0.02,
        ),
        "body",
    )
    _add_wheels(b, rw, ww, [xf, xr], W / 2 - ww / 2 + 0.005)
    _lights(b, L / 2 - 0.01, yb - 0.06, W / 2 - 0.1)
    b.add(
        box(0.05, 0.07, W + 0.02),
        "body",
        [translation(L / 2, 0.45 * rw + 0.05, 0), translation(-L / 2, 0.45 * rw + 0.05, 0)],
    )


def suv(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Tall box: high lower body, short hood, long cabin to the rear, roof rails, spare wheel."""
    L, W = _u(rng, 1.484, 2.116), _u(rng, 0.698, 1.002)
    rw, ww = _u(rng, 0.18, 0.22), _u(rng, 0.12, 0.15)
    xf, xr = L / 2 - _u(rng, 0.28, 0.33), -L / 2 + _u(rng, 0.28, 0.33)
    yb = 2 * rw + _u(rng, 0.12, 0.2)
    body = _side_profile(L, 0.55 * rw, yb, [xf, xr], rw + 0.025, rw, 0.06, 0.03)
    b.add(extrude(chaikin(body, 1), W, 0.03), "body")
    hh, x_ws = _u(rng, 0.085, 0.12), L / 2 - _u(rng, 0.4, 0.5)
    _hood(b, L, W, yb, hh, x_ws, (0.03, 0.04, 0.7))
    ch = _u(rng, 0.3, 0.4)
    x_rear = -L / 2 + 0.02
    _cabin(b, W, yb, ch, x_ws, (x_ws - 0.18, x_rear + 0.04), x_rear, 0.06, 0.05)
    rail = box(L * 0.55, 0.025, 0.03)
    y_rail = yb + ch + 0.045
    b.add(rail, "roof", [translation(x_ws - 0.18 - L * 0.3, y_rail, sz * (W / 2 - 0.12)) for sz in (1, -1)])
    foot = box(0.04, 0.05, 0.03)
    b.add(
        foot,
        "roof",
        [
            translation(x_ws - 0.18 - L * 0.3 + sx * L * 0.25, yb + ch + 0.015, sz * (W / 2 - 0.12))
            for sx in (1, -1)
            for sz in (1, -1)
        ],
    )
    keys = _add_wheels(b, rw, ww, [xf, xr], W / 2 - ww / 2 + 0.005)
    # Spare wheel on the tailgate, rim facing backwards: more instances of the same geometry.
    spare = compose(translation(-L / 2 - 0.5 * ww + 0.01, yb + 0.02, 0), rotation("y", -0.5 * np.pi))
    for key, local in keys:
        b.place(key, [compose(spare, q) for q in local])
    _lights(b, L / 2 - 0.01, yb - 0.05, W / 2 - 0.1)
    b.add(box(0.08, 0.1, W + 0.04), "body", [translation(L / 2, 0.55 * rw + 0.06, 0)])


def sports(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Low coupe: wedge lower body, long hood, small fastback cabin, rear spoiler on posts."""
    L, W = _u(rng, 1.619, 2.231), _u(rng, 0.742, 1.058)
    rw, ww = _u(rng, 0.15, 0.17), _u(rng, 0.13, 0.16)
    xf, xr = L / 2 - _u(rng, 0.32, 0.38), -L / 2 + _u(rng, 0.3, 0.35)
    yb = 2 * rw + _u(rng, 0.02, 0.06)
    body = _side_profile(L, 0.4 * rw, yb, [xf, xr], rw + 0.02, rw, 0.12, 0.04)
    b.add(extrude(chaikin(body, 1), W, 0.04), "body")
    hh, x_ws = _u(rng, 0.085, 0.11), _u(rng, -0.05, 0.1)
    _hood(b, L, W, yb, hh, x_ws, (0.05, 0.1, 0.3), inset=0.06, bevel=0.025)
    ch, cl = _u(rng, 0.18, 0.24), _u(rng, 0.8, 1.0)
    x_rear = x_ws - cl
    _cabin(b, W, yb, ch, x_ws, (x_ws - 0.3, x_ws - 0.5), x_rear, 0.14, 0.07)
    sp_y = yb + _u(rng, 0.12, 0.18)
    sp_x = -L / 2 + 0.12
    b.add(plate(rounded_rect(0.16, W - 0.04, 0.02), 0.025, 0.006), "body", [translation(sp_x, sp_y, 0)])
    post = box(0.05, sp_y - yb + 0.02, 0.025)
    b.add(post, "body", [translation(sp_x, (sp_y + yb) / 2 - 0.01, sz * (W / 2 - 0.15)) for sz in (1, -1)])
    _add_wheels(b, rw, ww, [xf, xr], W / 2 - ww / 2 + 0.005)
    _lights(b, L / 2 - 0.03, yb - 0.07, W / 2 - 0.12)


def pickup(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Pickup truck: lower body, hood, short cab, open cargo bed (two side walls and a tailgate)."""
    L, W = _u(rng, 1.666, 2.234), _u(rng, 0.699, 0.981)
    rw, ww = _u(rng, 0.18, 0.21), _u(rng, 0.12, 0.15)
    xf, xr = L / 2 - _u(rng, 0.3, 0.35), -L / 2 + _u(rng, 0.35, 0.42)
    yb = 2 * rw + _u(rng, 0.08, 0.14)
    body = _side_profile(L, 0.5 * rw, yb, [xf, xr], rw + 0.025, rw, 0.06, 0.02)
    b.add(extrude(chaikin(body, 1), W, 0.03), "body")
    hh, x_ws = _u(rng, 0.085, 0.12), L / 2 - _u(rng, 0.45, 0.55)
    _hood(b, L, W, yb, hh, x_ws, (0.03, 0.04, 0.7))
    ch, cl = _u(rng, 0.28, 0.36), _u(rng, 0.45, 0.6)
    x_rear = x_ws - cl
    _cabin(b, W, yb, ch, x_ws, (x_ws - 0.15, x_rear + 0.03), x_rear, 0.06, 0.04)
    bed_l, wall_h, wall_t = x_rear - (-L / 2) - 0.02, _u(rng, 0.14, 0.22), _u(rng, 0.03, 0.05)
    x_bed = (x_rear - L / 2) / 2
    b.add(
        box(bed_l, wall_h, wall_t),
        "body",
        [translation(x_bed, yb + wall_h / 2 - 0.01, sz * (W / 2 - wall_t / 2)) for sz in (1, -1)],
    )
    b.add(
        box(wall_t, wall_h, W - 2 * wall_t + 0.01),
        "body",
        [translation(-L / 2 + wall_t / 2, yb + wall_h / 2 - 0.01, 0)],
    )
    _add_wheels(b, rw, ww, [xf, xr], W / 2 - ww / 2 + 0.005)
    _lights(b, L / 2 - 0.01, yb - 0.05, W / 2 - 0.1)


STYLES = {"sedan": sedan, "suv": suv, "sports": sports, "pickup": pickup}
