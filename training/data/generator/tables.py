"""Tables: dining table (four legs and aprons, sometimes low stretchers), pedestal table,
trestle table and coffee table with a lower shelf.

Labels follow the ShapeNet part benchmark: top, leg, support. Rule used throughout: what
reaches the floor is a leg; horizontal structure below the top (aprons, stretchers, shelves,
spiders) is support. Build units: a table is about 1.6-2 long.
"""

from __future__ import annotations

import numpy as np

from training.data.generator.assembly import ShapeBuilder
from training.data.generator.mesh import compose, rotation, translation
from training.data.generator.outlines import chaikin, ellipse, rounded_rect, superellipse
from training.data.generator.primitives import box, frustum, lathe, loft, panel, plate, sweep

LABELS = ("top", "leg", "support")
_SQUARE = np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]])


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _corners(x: float, z: float) -> list[np.ndarray]:
    return [translation(sx * x, 0, sz * z) for sx in (1, -1) for sz in (1, -1)]


def _plank_top(b: ShapeBuilder, length: float, depth: float, t: float, y: float, planks: int) -> None:
    """A rectangular top, either one slab or ``planks`` identical boards side by side along z."""
    if planks <= 1:
        b.add(plate(rounded_rect(length, depth, 0.03), t, 0.01), "top", [translation(0, y, 0)])
        return
    w = depth / planks
    board = plate(rounded_rect(length, w + 0.002, 0.008), t, 0.006)
    b.add(board, "top", [translation(0, y, -depth / 2 + w * (k + 0.5)) for k in range(planks)])


def dining(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Four tapered square legs under a rectangular top, joined by aprons, with corner blocks."""
    L, D, H, t = _u(rng, 1.293, 2.157), _u(rng, 0.689, 1.161), _u(rng, 0.626, 0.944), _u(rng, 0.04, 0.07)
    lt, lb = _u(rng, 0.07, 0.1), _u(rng, 0.045, 0.07)
    inset = _u(rng, 0.06, 0.14)
    lx, lz = L / 2 - inset, D / 2 - inset
    planks = int(rng.choice([1, 1, 3, 4, 5]))
    _plank_top(b, L, D, t, H - t / 2, planks)
    leg = loft(
        _SQUARE, np.array([0.0, H - t + 0.01]), np.zeros((2, 2)), np.array([[lb, lb], [lt, lt]]), axis="y"
    )
    b.add(leg, "leg", _corners(lx, lz))
    b.add(
        frustum(0.4 * lb, 0.4 * lb, 0.02),
        "leg",
        [compose(m, translation(0, -0.01, 0)) for m in _corners(lx, lz)],
    )
    ah, at = _u(rng, 0.08, 0.14), _u(rng, 0.02, 0.03)
    ya = H - t - ah / 2 + 0.005
    b.add(
        box(2 * lx, ah, at),
        "support",
        [translation(0, ya, lz - lt / 2 + at / 2 + 0.005), translation(0, ya, -lz + lt / 2 - at / 2 - 0.005)],
    )
    b.add(
        box(at, ah, 2 * lz),
        "support",
        [translation(lx - lt / 2 + at / 2 + 0.005, ya, 0), translation(-lx + lt / 2 - at / 2 - 0.005, ya, 0)],
    )
    if rng.random() < 0.4:
        # Low stretchers between the legs (support, like the aprons), sometimes an H with a cross bar.
        ys, sh = _u(rng, 0.12, 0.28) * H, _u(rng, 0.03, 0.05)
        b.add(box(2 * lx, sh, 0.6 * lb), "support", [translation(0, ys, lz), translation(0, ys, -lz)])
        if rng.random() < 0.5:
            b.add(box(0.6 * lb, sh, 2 * lz), "support", [translation(0, ys, 0)])


def pedestal(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Round or oval top on a turned column, arched feet radiating from its foot, a cross spider."""
    a = _u(rng, 0.601, 1.049)
    c = a * float(rng.choice([1.0, 1.0, _u(rng, 0.65, 0.85)]))
    H, t = _u(rng, 0.626, 0.944), _u(rng, 0.04, 0.07)
    b.add(plate(ellipse(a, c, 32), t, 0.015), "top", [translation(0, H - t / 2, 0)])
    cr = _u(rng, 0.06, 0.1)
    y0, y1 = _u(rng, 0.08, 0.14), H - t + 0.01
    bulb = _u(rng, 1.2, 1.7)
    prof = np.array(
        [
            [cr * 1.3, y0 - 0.02],
            [cr, y0 + 0.08],
            [cr * bulb, y0 + 0.3 * (y1 - y0)],
            [cr * 0.8, y0 + 0.55 * (y1 - y0)],
            [cr * 0.9, y1 - 0.1],
            [cr * 1.2, y1 - 0.04],
            [cr * 1.1, y1],
        ]
    )
    b.add(lathe(prof, 16), "leg")
    n = int(rng.choice([3, 4]))
    reach, fh = _u(rng, 0.35, 0.5) * min(a, c) / 0.7, _u(rng, 0.04, 0.06)
    arch = np.array([[0.0, y0 + 0.02, 0.0], [0.45 * reach, y0 * 0.6, 0.0], [reach, fh / 2, 0.0]])
    foot = sweep(rounded_rect(fh, 0.06, 0.01, 2), arch, up=np.array([0.0, 1.0, 0.0]))
    phase = _u(rng, 0, np.pi)
    b.add(foot, "leg", [rotation("y", phase + 2 * np.pi * k / n) for k in range(n)])
    b.add(
        frustum(0.03, 0.025, 0.02, 10),
        "leg",
        [
            compose(rotation("y", phase + 2 * np.pi * k / n), translation(reach - 0.04, -0.01, 0))
            for k in range(n)
        ],
    )
    sh = _u(rng, 0.07, 0.1)
    arm = box(1.3 * min(a, c), sh, 0.05)
    at = translation(0, H - t - sh / 2 + 0.005, 0)
    b.add(arm, "support", [at, compose(at, rotation("y", 0.5 * np.pi))])


def trestle(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Plank top on two shaped end frames standing on feet, tied by a long stretcher."""
    L, D, H, t = _u(rng, 1.384, 2.216), _u(rng, 0.645, 1.105), _u(rng, 0.626, 0.944), _u(rng, 0.05, 0.08)
    _plank_top(b, L, D, t, H - t / 2, int(rng.choice([1, 3, 4])))
    ex = L / 2 - _u(rng, 0.18, 0.3)
    fh, fw = _u(rng, 0.06, 0.1), _u(rng, 0.08, 0.12)
    et = _u(rng, 0.06, 0.09)
    # End frame: an hourglass outline in (z, y), symmetric in z, from the feet to under the top.
    ww, wn = 0.5 * D * _u(rng, 0.55, 0.8), 0.5 * D * _u(rng, 0.15, 0.28)
    y0, y1 = fh - 0.01, H - t + 0.01
    ym = 0.5 * (y0 + y1)
    half = np.array([[ww, y0], [wn, ym - 0.1], [wn, ym + 0.1], [ww, y1]])
    outline = np.concatenate([half, half[::-1] * [-1, 1]])
    end = panel(chaikin(outline, 1), et, 0.008)
    b.add(end, "leg", [translation(ex, 0, 0), translation(-ex, 0, 0)])
    foot = box(fw, fh, 0.92 * D)
    b.add(foot, "leg", [translation(ex, fh / 2, 0), translation(-ex, fh / 2, 0)])
    sh = _u(rng, 0.08, 0.14)
    b.add(box(2 * ex + et, sh, _u(rng, 0.04, 0.06)), "support", [translation(0, ym, 0)])
    b.bolts(
        np.array([[sx * ex + 0.5 * et + 0.004, ym, 0] for sx in (1, -1)]),
        "support",
        0.02,
        0.015,
        direction=(1, 0, 0),
    )


def coffee(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Low table: soft-rectangle top on four round legs, a lower shelf pierced by the legs."""
    L, D, H, t = _u(rng, 1.29, 2.21), _u(rng, 0.592, 1.208), _u(rng, 0.387, 0.663), _u(rng, 0.05, 0.08)
    b.add(
        plate(superellipse(L / 2, D / 2, _u(rng, 3.0, 6.0), 32), t, 0.015),
        "top",
        [translation(0, H - t / 2, 0)],
    )
    lr = _u(rng, 0.03, 0.05)
    lx, lz = L / 2 - _u(rng, 0.12, 0.22), D / 2 - _u(rng, 0.1, 0.16)
    b.add(frustum(lr * 0.8, lr, H - t + 0.01, 12), "leg", _corners(lx, lz))
    b.add(
        frustum(lr * 0.9, lr * 0.9, 0.02, 12),
        "leg",
        [compose(m, translation(0, -0.01, 0)) for m in _corners(lx, lz)],
    )
    ys, st = _u(rng, 0.1, 0.2), _u(rng, 0.03, 0.04)
    b.add(plate(rounded_rect(2 * lx + lr, 2 * lz + lr, 0.02), st, 0.005), "support", [translation(0, ys, 0)])


STYLES = {"dining": dining, "pedestal": pedestal, "trestle": trestle, "coffee": coffee}
