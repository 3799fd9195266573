"""Chairs: straight (slat-back dining chair), armchair (upholstered), swivel office chair, stool
and cantilever (tubular steel) chair.

Labels follow the ShapeNet part benchmark: back, seat, leg, arm. Build units: the chair is
about 1.7 tall, so after normalisation sizes are close to the final ones.
"""

from __future__ import annotations

import numpy as np

from training.data.generator.assembly import ShapeBuilder
from training.data.generator.mesh import Mesh, compose, rotation, scaling, translation
from training.data.generator.outlines import chaikin, ellipse, rounded_rect, superellipse
from training.data.generator.primitives import (
    bent_path,
    capsule,
    curved_plank,
    ellipsoid,
    frustum,
    lathe,
    loft,
    plate,
    rod,
    side_panel,
    sweep,
    torus,
)

LABELS = ("back", "seat", "leg", "arm")
_SQUARE = np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]])


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _square_leg(height: float, bottom: float, top: float) -> Mesh:
    """A square leg tapering from ``bottom`` to ``top`` width, from y = 0 to y = height."""
    return loft(
        _SQUARE, np.array([0.0, height]), np.zeros((2, 2)), np.array([[bottom] * 2, [top] * 2]), axis="y"
    )


def _corners(x: float, z: float) -> list[np.ndarray]:
    return [translation(sx * x, 0, sz * z) for sx in (1, -1) for sz in (1, -1)]


def straight(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Dining chair: four tapered square legs, side stretchers, slatted back with a curved rail."""
    hs, d, w, t = _u(rng, 0.651, 0.999), _u(rng, 0.651, 0.999), _u(rng, 0.648, 1.052), _u(rng, 0.06, 0.09)
    lb, lt = _u(rng, 0.05, 0.07), _u(rng, 0.07, 0.095)
    inset = lt / 2 + _u(rng, 0.01, 0.04)
    lx, lz = d / 2 - inset, w / 2 - inset
    b.add(plate(rounded_rect(d, w, _u(rng, 0.02, 0.08)), t, 0.012), "seat", [translation(0, hs - t / 2, 0)])
    b.add(plate(rounded_rect(d - 0.08, w - 0.08, 0.05), 0.04), "seat", [translation(0, hs - 0.005, 0)])
    b.add(_square_leg(hs - t + 0.01, lb, lt), "leg", _corners(lx, lz))
    b.add(
        frustum(lb * 0.45, lb * 0.45, 0.02),
        "leg",
        [compose(m, translation(0, -0.01, 0)) for m in _corners(lx, lz)],
    )
    ys = _u(rng, 0.15, 0.3)
    sr = _u(rng, 0.014, 0.022)
    b.add(
        rod([lx, ys, 0], [-lx, ys, 0], sr, segments=10),
        "leg",
        [translation(0, 0, lz), translation(0, 0, -lz)],
    )
    b.bolts(
        np.array([[sx * lx, hs + 0.005, sz * lz] for sx in (1, -1) for sz in (1, -1)]), "seat", 0.014, 0.012
    )
    # Back, built at the seat's rear edge and reclined about z.
    hb, recline = _u(rng, 0.7, 0.95), _u(rng, 0.05, 0.2)
    pr, zp = _u(rng, 0.022, 0.035), lz
    rail_h, rail_t, bulge = _u(rng, 0.1, 0.18), _u(rng, 0.03, 0.045), _u(rng, 0.0, 0.07)
    span = 2 * zp + 2 * pr
    T = compose(translation(-lx, hs, 0), rotation("z", recline))
    b.add(
        rod([0, -0.8 * t, 0], [0, hb, 0], pr, segments=10),
        "back",
        [compose(T, translation(0, 0, zp)), compose(T, translation(0, 0, -zp))],
    )
    b.add(
        curved_plank(span, bulge, rail_h, rail_t, corner=0.01),
        "back",
        [compose(T, translation(0, hb - rail_h / 2, 0))],
    )
    n = int(rng.integers(2, 6))
    sw, st = _u(rng, 0.035, 0.07), _u(rng, 0.015, 0.025)
    height = hb - rail_h + 0.02
    slat = plate(rounded_rect(st, sw, 0.005), height).transformed(translation(0, height / 2 - 0.01, 0))
    zs = np.linspace(-zp, zp, n + 2)[1:-1]
    b.add(slat, "back", [compose(T, translation(-bulge * (1 - (2 * z / span) ** 2), 0, z)) for z in zs])


def armchair(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Upholstered club chair: thick base and cushion, padded reclined back, solid rolled arms."""
    hl, hs = _u(rng, 0.2, 0.3), _u(rng, 0.7, 0.85)
    W, D, at, bt = _u(rng, 0.95, 1.55), _u(rng, 0.783, 1.167), _u(rng, 0.14, 0.24), _u(rng, 0.15, 0.25)
    ct = _u(rng, 0.1, 0.16)
    base_top = hs - ct
    leg = lathe(np.array([[0.035, 0.0], [0.05, 0.3 * hl], [0.045, 0.8 * hl], [0.06, hl + 0.02]]), 12)
    b.add(leg, "leg", _corners(D / 2 - 0.08, W / 2 - 0.08))
    b.add(
        plate(rounded_rect(D, W, 0.05), base_top - hl, 0.03), "seat", [translation(0, (base_top + hl) / 2, 0)]
    )
    cd = D - bt - 0.02
    b.add(
        plate(rounded_rect(cd, W - 2 * at - 0.01, 0.06), ct + 0.02, 0.035),
        "seat",
        [translation(D / 2 - cd / 2, base_top + ct / 2 - 0.01, 0)],
    )
    hb, recline = _u(rng, 0.55, 0.8), _u(rng, 0.05, 0.18)
    back_h = hs + hb - hl
    back = plate(rounded_rect(bt, W, 0.06), back_h, 0.04).transformed(translation(0, back_h / 2, 0))
    T = compose(translation(-D / 2 + bt / 2 + 0.02, hl, 0), rotation("z", recline))
    b.add(back, "back", [T])
    tufts = np.array(
        [
            [bt / 2 + 0.005, y, z]
            for y in np.linspace(hs - hl + 0.15, back_h - 0.12, 2)
            for z in np.linspace(-W / 2 + at + 0.1, W / 2 - at - 0.1, 3)
        ]
    )
    b.bolts(tufts, "back", 0.02, 0.02, direction=(1.0, 0.0, 0.0), frame=T)
    ha = hs + _u(rng, 0.12, 0.25)
    roll = _u(rng, 0.04, 0.09)
    x0, x1 = -D / 2 + bt * 0.6, D / 2
    prof = np.array(
        [
            [x1, hl],
            [x1, ha - roll],
            [x1 - roll * 0.3, ha],
            [x1 - 2 * roll, ha + roll * 0.6],
            [x0 + 0.05, ha + roll * 0.5],
            [x0, ha],
            [x0, hl],
        ]
    )
    arm = side_panel(chaikin(prof, 2), at, 0.025)
    b.add(arm, "arm", [translation(0, 0, W / 2 - at / 2), translation(0, 0, -W / 2 + at / 2)])


def swivel(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Office chair: five-star base on casters, gas-lift column, cushion seat, curved back on a
    bar, and (usually) T-shaped armrests."""
    rc, R = _u(rng, 0.035, 0.048), _u(rng, 0.5, 0.62)
    hs, d, w, st = _u(rng, 0.651, 0.999), _u(rng, 0.624, 0.976), _u(rng, 0.651, 0.999), _u(rng, 0.08, 0.12)
    cr = _u(rng, 0.03, 0.042)
    y_out, y_in = 2 * rc + 0.02, 2 * rc + _u(rng, 0.06, 0.1)
    spoke = loft(
        rounded_rect(1.0, 1.0, 0.25, 2),
        np.array([0.0, R]),
        np.array([[y_in, 0.0], [y_out, 0.0]]),
        np.array([[0.07, 0.09], [0.045, 0.06]]),
        axis="x",
    )
    phase = _u(rng, 0, 2 * np.pi)
    spin = [rotation("y", phase + 2 * np.pi * k / 5) for k in range(5)]
    b.add(spoke, "leg", spin)
    caster = ellipsoid(rc, rc, 0.7 * rc, 12, 6)
    b.add(caster, "leg", [compose(s, translation(R - 0.03, rc, 0)) for s in spin])
    b.add(rod([R - 0.03, rc, 0], [R - 0.03, y_out + 0.02, 0], 0.012, segments=8), "leg", spin)
    col_top = hs - st + 0.01
    b.add(rod([0, y_in - 0.05, 0], [0, col_top, 0], cr, segments=14), "leg")
    b.add(frustum(cr + 0.03, cr + 0.03, 0.1, 14), "leg", [translation(0, y_in - 0.06, 0)])
    b.add(frustum(cr + 0.02, cr + 0.012, 0.45 * (col_top - y_in), 14), "leg", [translation(0, y_in, 0)])
    b.add(
        plate(superellipse(d / 2, w / 2, _u(rng, 3.0, 5.0), 28), st, 0.03),
        "seat",
        [translation(0, hs - st / 2, 0)],
    )
    b.add(plate(rounded_rect(0.12, 0.1, 0.01), 0.035), "seat", [translation(0, hs - st - 0.012, 0)])
    # Back: a band curved about a vertical axis in front of it, reclined, held by a bent bar.
    bh, bw, bt = _u(rng, 0.55, 0.8), _u(rng, 0.6, 0.8), _u(rng, 0.05, 0.08)
    gap, recline, bulge = _u(rng, 0.08, 0.16), _u(rng, 0.05, 0.2), _u(rng, 0.06, 0.14)
    xb = -d / 2 + 0.02
    T = compose(translation(xb, hs + gap, 0), rotation("z", recline))
    b.add(curved_plank(bw, bulge, bh, bt, n=11, corner=0.02), "back", [compose(T, translation(0, bh / 2, 0))])
    p_back = (T @ np.array([-bulge - bt / 2 + 0.01, 0.3 * bh, 0, 1.0]))[:3]
    bar = bent_path(np.array([[-0.05 * d, hs - 0.7 * st, 0], [p_back[0], hs - 0.7 * st, 0], p_back]), 0.08)
    b.add(sweep(rounded_rect(0.025, 0.07, 0.008, 2), bar), "back")
    if rng.random() < 0.75:
        ah, ax, pl = _u(rng, 0.2, 0.3), _u(rng, -0.12, 0.0), _u(rng, 0.25, 0.34)
        za = w / 2 + 0.03
        path = bent_path(np.array([[0, 0, za - 0.12], [0, 0, za], [0, ah, za]]), 0.05)
        post = sweep(rounded_rect(0.06, 0.025, 0.008, 2), path)
        base = translation(ax, hs - 0.6 * st, 0)
        b.add(post, "arm", [base, compose(base, rotation("y", np.pi))])
        b.add(
            # A capsule along x, squashed to a pad 0.045 high and 0.09 wide.
            capsule(pl - 0.09, 0.045, 12, 3).transformed(
                compose(
                    scaling(1.0, 0.5, 1.0), rotation("z", -0.5 * np.pi), translation(0, -(pl - 0.09) / 2, 0)
                )
            ),
            "arm",
            [translation(ax, hs - 0.6 * st + ah + 0.01, za), translation(ax, hs - 0.6 * st + ah + 0.01, -za)],
        )


def stool(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Bar stool: round seat, three or four splayed legs and a foot ring."""
    hs, rs, st = _u(rng, 0.85, 1.65), _u(rng, 0.239, 0.441), _u(rng, 0.06, 0.1)
    n = int(rng.integers(3, 5))
    rt, rb, lr = rs * _u(rng, 0.45, 0.6), rs * _u(rng, 0.85, 1.15), _u(rng, 0.025, 0.04)
    top = hs - st + 0.01
    b.add(plate(ellipse(rs, rs, 24), st, 0.012), "seat", [translation(0, hs - st / 2, 0)])
    b.add(plate(ellipse(rs - 0.03, rs - 0.03, 24), 0.03), "seat", [translation(0, hs + 0.005, 0)])
    phase = _u(rng, 0, 2 * np.pi)
    spin = [rotation("y", phase + 2 * np.pi * k / n) for k in range(n)]
    b.add(rod([rb, 0, 0], [rt, top, 0], lr, 0.9 * lr, 10), "leg", spin)
    b.bolts(
        np.array(
            [[rt * np.cos(a), hs - st - 0.003, -rt * np.sin(a)] for a in phase + 2 * np.pi * np.arange(n) / n]
        ),
        "seat",
        0.013,
        0.012,
        direction=(0, -1, 0),
    )
    yr = _u(rng, 0.25, 0.4) * top
    ring = torus(rb + (rt - rb) * yr / top, _u(rng, 0.014, 0.022), 24, 8)
    b.add(ring, "leg", [translation(0, yr, 0)])


def cantilever(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Tubular steel cantilever chair: two bent side frames, seat panel and a curved back."""
    hs, d, w = _u(rng, 0.652, 0.978), _u(rng, 0.626, 0.944), _u(rng, 0.651, 0.999)
    rt, st = _u(rng, 0.016, 0.025), _u(rng, 0.035, 0.06)
    hb, recline = _u(rng, 0.6, 0.85), _u(rng, 0.08, 0.2)
    zf = w / 2 - 0.04
    ys = hs - st - rt + 0.005
    frame = bent_path(
        np.array(
            [
                [-d / 2 + 0.02, ys, 0],
                [d / 2 - 0.06, ys, 0],
                [d / 2 + _u(rng, 0.0, 0.08), rt, 0],
                [-d / 2 + _u(rng, 0.0, 0.15), rt, 0],
            ]
        ),
        _u(rng, 0.06, 0.12),
        5,
    )
    tube = ellipse(rt, rt, 10)
    b.add(
        sweep(tube, frame, up=np.array([0.0, 0.0, 1.0])),
        "leg",
        [translation(0, 0, zf), translation(0, 0, -zf)],
    )
    top = np.array([-d / 2 + 0.02 - hb * np.sin(recline), ys + hb * np.cos(recline), 0])
    upright = bent_path(np.array([[-d / 2 + 0.12, ys, 0], [-d / 2 + 0.02, ys, 0], top]), 0.06, 4)
    b.add(
        sweep(tube, upright, up=np.array([0.0, 0.0, 1.0])),
        "back",
        [translation(0, 0, zf), translation(0, 0, -zf)],
    )
    b.add(plate(rounded_rect(d - 0.04, w, 0.04), st, 0.01), "seat", [translation(0, hs - st / 2, 0)])
    bh = _u(rng, 0.22, 0.4)
    T = compose(translation(*top), rotation("z", recline), translation(rt, -bh / 2 - 0.02, 0))
    th = _u(rng, 0.02, 0.035)
    b.add(curved_plank(w + 0.02, _u(rng, 0.02, 0.08), bh, th, corner=0.01), "back", [T])
    b.bolts(
        np.array([[th / 2, 0.0, z] for z in (zf, -zf)]), "back", 0.012, 0.01, direction=(1, 0, 0), frame=T
    )


STYLES = {
    "straight": straight,
    "armchair": armchair,
    "swivel": swivel,
    "stool": stool,
    "cantilever": cantilever,
}
