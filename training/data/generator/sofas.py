"""Sofas: classic (rolled arms, seat and back cushions, turned legs), modern (box arms, one
bench cushion, tubular sled legs) and curved (a seat on an arc with a swept back).

Labels: seat (the base frame), cushion, back, arm, leg. Build units: about 2 long.
"""

from __future__ import annotations

import numpy as np

from training.data.generator.assembly import ShapeBuilder
from training.data.generator.mesh import compose, rotation, translation
from training.data.generator.outlines import chaikin, ellipse, rounded_rect
from training.data.generator.primitives import (
    bent_path,
    extrude,
    frustum,
    lathe,
    plate,
    side_panel,
    sweep,
)

LABELS = ("seat", "back", "arm", "leg", "cushion")


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _corners(x: float, z: float) -> list[np.ndarray]:
    return [translation(sx * x, 0, sz * z) for sx in (1, -1) for sz in (1, -1)]


def classic(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Rolled-arm sofa: base, n seat cushions, back slab with n back cushions, turned legs."""
    n = int(rng.integers(2, 4))
    L, D = _u(rng, 1.466, 2.434), _u(rng, 0.692, 1.108)
    hl, hb, ct = _u(rng, 0.14, 0.22), _u(rng, 0.38, 0.46), _u(rng, 0.1, 0.15)
    at, bt = _u(rng, 0.16, 0.24), _u(rng, 0.16, 0.24)
    leg = lathe(np.array([[0.03, 0.0], [0.045, 0.35 * hl], [0.04, 0.75 * hl], [0.055, hl + 0.02]]), 12)
    b.add(leg, "leg", _corners(D / 2 - 0.07, L / 2 - 0.07))
    b.add(plate(rounded_rect(D, L, 0.04), hb - hl, 0.02), "seat", [translation(0, (hb + hl) / 2, 0)])
    inner = L - 2 * at
    cw, cd = inner / n, D - bt - 0.01
    cushion = plate(rounded_rect(cd, cw - 0.01, 0.05), ct, 0.035)
    b.add(
        cushion,
        "cushion",
        [translation(D / 2 - cd / 2, hb + ct / 2 - 0.01, -inner / 2 + cw * (k + 0.5)) for k in range(n)],
    )
    top = hb + _u(rng, 0.4, 0.55)
    back = side_panel(rounded_rect(bt, top - hl, 0.05), L, 0.03).transformed(
        translation(-D / 2 + bt / 2, (top + hl) / 2, 0)
    )
    b.add(back, "back")
    bc_h, bc_t = top - hb - ct - 0.02, _u(rng, 0.12, 0.18)
    bcush = plate(rounded_rect(bc_t, cw - 0.01, 0.05), bc_h, 0.035)
    lean = _u(rng, 0.08, 0.2)
    b.add(
        bcush,
        "cushion",
        [
            compose(
                translation(
                    -D / 2 + bt + bc_t / 2 - 0.02, hb + ct + bc_h / 2 - 0.02, -inner / 2 + cw * (k + 0.5)
                ),
                rotation("z", lean),
            )
            for k in range(n)
        ],
    )
    ha, roll = hb + ct + _u(rng, 0.1, 0.2), _u(rng, 0.05, 0.09)
    x0, x1 = -D / 2 + bt * 0.5, D / 2 + 0.02
    prof = np.array(
        [
            [x1, hl],
            [x1, ha - 0.6 * roll],
            [x1 - 0.2 * roll, ha + 0.4 * roll],
            [x1 - 1.5 * roll, ha + roll],
            [x0, ha + roll * 0.8],
            [x0, hl],
        ]
    )
    arm = side_panel(chaikin(prof, 2), at, 0.03)
    b.add(arm, "arm", [translation(0, 0, L / 2 - at / 2), translation(0, 0, -L / 2 + at / 2)])


def modern(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Low boxy sofa: thin base, one long bench cushion, low back, box arms, two sled legs."""
    L, D = _u(rng, 1.554, 2.546), _u(rng, 0.695, 1.055)
    hl, ct = _u(rng, 0.15, 0.25), _u(rng, 0.12, 0.18)
    bh = _u(rng, 0.12, 0.18)
    hb = hl + bh
    at, bt = _u(rng, 0.1, 0.16), _u(rng, 0.12, 0.2)
    rt = _u(rng, 0.012, 0.02)
    # Sled leg: a closed-looking U of tube under each end (runner on the floor, two uprights).
    zs = L / 2 - at / 2
    sled = bent_path(
        np.array(
            [
                [D / 2 - 0.06, hl + 0.02, 0],
                [D / 2 - 0.06, rt, 0],
                [-D / 2 + 0.06, rt, 0],
                [-D / 2 + 0.06, hl + 0.02, 0],
            ]
        ),
        0.05,
        4,
    )
    b.add(
        sweep(ellipse(rt, rt, 10), sled, up=np.array([0.0, 0.0, 1.0])),
        "leg",
        [translation(0, 0, zs - 0.05), translation(0, 0, -zs + 0.05)],
    )
    b.add(plate(rounded_rect(D, L, 0.01), bh, 0.01), "seat", [translation(0, hl + bh / 2, 0)])
    cd = D - bt
    b.add(
        plate(rounded_rect(cd, L - 2 * at - 0.01, 0.03), ct, 0.025),
        "cushion",
        [translation(D / 2 - cd / 2, hb + ct / 2 - 0.01, 0)],
    )
    top = hb + ct + _u(rng, 0.2, 0.35)
    b.add(
        plate(rounded_rect(bt, L, 0.02), top - hl, 0.015),
        "back",
        [translation(-D / 2 + bt / 2, (top + hl) / 2, 0)],
    )
    ha = hb + ct + _u(rng, 0.05, 0.15)
    b.add(
        plate(rounded_rect(D, at, 0.02), ha - hl, 0.015),
        "arm",
        [translation(0, (ha + hl) / 2, L / 2 - at / 2), translation(0, (ha + hl) / 2, -L / 2 + at / 2)],
    )
    b.bolts(
        np.array([[sx * (D / 2 - 0.06), hl + 0.005, sz * (zs - 0.05)] for sx in (1, -1) for sz in (1, -1)]),
        "leg",
        0.022,
        0.012,
        direction=(0, -1, 0),
    )


def curved(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Curved sofa: seat and cushion are sectors of a ring, the back a band swept along the arc,
    arms close both ends, short legs underneath."""
    R = _u(rng, 1.05, 1.7)  # radius of the back arc, centre in front of the sofa (+x)
    half = float(np.arcsin(min(_u(rng, 0.85, 1.05) / R, 0.93)))  # half opening: chord about 2
    D, hl, bh, ct = _u(rng, 0.75, 0.9), _u(rng, 0.12, 0.2), _u(rng, 0.15, 0.22), _u(rng, 0.1, 0.15)
    bt = _u(rng, 0.14, 0.2)
    hb = hl + bh
    k = 20
    ang = np.linspace(-half, half, k)

    def ring(r0: float, r1: float, a0: float, a1: float) -> np.ndarray:
        a = np.linspace(a0, a1, k)
        outer = np.stack([-r1 * np.cos(a), r1 * np.sin(a)], 1)
        inner = np.stack([-r0 * np.cos(a[::-1]), r0 * np.sin(a[::-1])], 1)
        return np.concatenate([outer, inner])

    # Plates are outlines in (x, z); the arc centre is at the origin, the sofa at x ~ -R.
    seat = plate(ring(R - D, R, -half, half), bh, 0.015).transformed(translation(0, hl + bh / 2, 0))
    b.add(seat, "seat")
    cush = plate(ring(R - D + 0.02, R - bt, -half + 0.06, half - 0.06), ct, 0.03)
    b.add(cush, "cushion", [translation(0, hb + ct / 2 - 0.01, 0)])
    top = hb + ct + _u(rng, 0.25, 0.4)
    path = np.stack([-(R - bt / 2) * np.cos(ang), np.zeros(k), (R - bt / 2) * np.sin(ang)], 1)
    band = sweep(rounded_rect(top - hl, bt, 0.03, 2), path, up=np.array([0.0, 1.0, 0.0]))
    b.add(band, "back", [translation(0, (top + hl) / 2, 0)])
    ha, aw = hb + ct + _u(rng, 0.08, 0.18), _u(rng, 0.1, 0.16)
    arm = extrude(rounded_rect(D, ha - hl, 0.03), aw, 0.015)  # outline (x, y), thickness along z
    # Rotating about y by -a carries the arm from angle 0 to the end of the arc at angle a.
    b.add(
        arm,
        "arm",
        [compose(rotation("y", -a), translation(-(R - D / 2), (ha + hl) / 2, 0)) for a in (half, -half)],
    )
    leg = frustum(0.035, 0.045, hl + 0.02, 12)
    spots = [(R - 0.1, a) for a in np.linspace(-half + 0.05, half - 0.05, 3)] + [
        (R - D + 0.1, a) for a in (-half + 0.05, half - 0.05)
    ]
    b.add(leg, "leg", [translation(-r * np.cos(a), 0, r * np.sin(a)) for r, a in spots])


STYLES = {"classic": classic, "modern": modern, "curved": curved}
