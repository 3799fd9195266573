"""Guitars: acoustic (figure-eight hollow body, sound hole), double-cutaway electric,
single-cutaway electric and flying V.

Labels follow the ShapeNet part benchmark: head, neck, body. Frame: the guitar stands upright
(neck up, +y), strings facing +x, width along z. Fretboard, frets, bridge, pickups, knobs,
pickguard and tuning pegs are separate small or overlaid pieces, as in 3D Warehouse models.
Build units: about 2 tall.
"""

from __future__ import annotations

import numpy as np

from training.data.generator.assembly import ShapeBuilder
from training.data.generator.mesh import compose, rotation, translation
from training.data.generator.outlines import ccw, chaikin, rounded_rect
from training.data.generator.primitives import box, frustum, loft, panel, torus

LABELS = ("head", "neck", "body")


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _symmetric(half: np.ndarray) -> np.ndarray:
    """A closed outline (z, y) symmetric about z = 0 from its right half (z >= 0), listed from
    the bottom point on the axis to the top point on the axis."""
    half = np.asarray(half, float)
    left = half[::-1] * [-1.0, 1.0]
    return ccw(np.concatenate([half, left[1:-1]]))


def _acoustic_outline(lb: float, r1: float, r2: float, waist: float) -> np.ndarray:
    """Figure-eight body: lower bout radius r1, upper bout r2, narrowed to ``waist`` between."""
    y = 0.5 * lb * (1 - np.cos(np.linspace(0, np.pi, 17)))
    c1, c2 = r1, lb - r2
    w1 = np.sqrt(np.clip(r1**2 - (y - c1) ** 2, 0, None))
    w2 = np.sqrt(np.clip(r2**2 - (y - c2) ** 2, 0, None))
    w = np.maximum(np.maximum(w1, w2), np.where((y > c1) & (y < c2), waist, 0.0))
    return chaikin(_symmetric(np.stack([w, y], 1)), 1)


def _neck(
    b: ShapeBuilder,
    rng: np.random.Generator,
    y0: float,
    y1: float,
    x_front: float,
    w0: float,
    w1: float,
    heel: float = 0.0,
) -> None:
    """D-section neck from y0 to y1 with its flat front at x_front, fretboard overlay and frets.

    ``heel`` > 0: the neck's lowest ``heel`` length is a separate piece labelled body (the part
    of the neck set into the body, which ShapeNet labels as body in some guitars).
    """
    t = np.linspace(0, np.pi, 7)
    d_shape = np.concatenate([[[0.5, 0.0]], np.stack([0.5 * np.cos(t), -np.sin(t)], 1)[1:-1], [[-0.5, 0.0]]])
    depth = _u(rng, 0.03, 0.04)
    ym = y0 + heel
    wm = w0 + (w1 - w0) * heel / (y1 - y0)
    # loft along y: section (u, v) -> (z, x); flat side (v = 0) at the front.
    for lo, hi, wlo, whi, label in ((y0, ym, w0, wm, "body"), (ym, y1, wm, w1, "neck")):
        if hi - lo <= 1e-9:
            continue
        neck = loft(
            d_shape,
            np.array([lo, hi]),
            np.array([[0.0, x_front - 0.006]] * 2),
            np.array([[wlo, depth], [whi, depth]]),
            axis="y",
        )
        b.add(neck, label)
    fb = loft(
        rounded_rect(1.0, 1.0, 0.0),
        np.array([y0 + 0.02, y1]),
        np.array([[0.0, x_front]] * 2),
        np.array([[w0, 0.012], [w1, 0.012]]),
        axis="y",
    )
    b.add(fb, "neck")
    n = int(rng.integers(12, 19))
    ys = y1 - (y1 - y0) * (1 - 2.0 ** (-np.arange(1, n + 1) / 12.0)) * 1.9
    fret = box(0.004, 0.004, 1.0)
    places = [
        compose(
            translation(x_front + 0.007, y, 0),
            np.diag([1.0, 1.0, w0 + (w1 - w0) * (y - y0) / (y1 - y0), 1.0]),
        )
        for y in ys
        if y > y0 + 0.03
    ]
    # Frets differ in length: each is its own geometry (not instances), like real exported models.
    for p in places:
        b.add(fret.transformed(p), "neck")


def _head(
    b: ShapeBuilder,
    outline_zy: np.ndarray,
    y0: float,
    x_front: float,
    tilt: float,
    pegs: list[tuple[float, float]],
    thickness: float,
) -> None:
    """Headstock from y0 up, tilted back by ``tilt``; pegs (z, y-from-y0) on its back face."""
    T = compose(translation(x_front - thickness / 2 - 0.006, y0, 0), rotation("z", tilt))
    b.add(panel(outline_zy, thickness, 0.004), "head", [T])
    peg = frustum(0.012, 0.01, 0.04, 8).transformed(rotation("z", 0.5 * np.pi))  # pointing -x
    b.add(peg, "head", [compose(T, translation(-thickness / 2 + 0.005, y, z)) for z, y in pegs])
    b.add(
        frustum(0.008, 0.008, 0.02, 8).transformed(rotation("z", -0.5 * np.pi)),
        "head",
        [compose(T, translation(thickness / 2 - 0.005, y, z)) for z, y in pegs],
    )


def acoustic(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Acoustic: deep figure-eight body with sound hole ring and bridge, 3+3 headstock."""
    lb, r1 = _u(rng, 0.695, 1.055), _u(rng, 0.28, 0.34)
    r2, depth = r1 * _u(rng, 0.72, 0.82), _u(rng, 0.16, 0.22)
    outline = _acoustic_outline(lb, r1, r2, r2 * _u(rng, 0.75, 0.85))
    b.add(panel(outline, depth, 0.01), "body")
    front = depth / 2
    yh = lb - r2 * _u(rng, 0.9, 1.1)
    b.add(
        torus(_u(rng, 0.07, 0.09), 0.008, 20, 6).transformed(rotation("z", 0.5 * np.pi)),
        "body",
        [translation(front, yh, 0)],
    )
    b.add(box(0.02, 0.04, 0.18), "body", [translation(front + 0.005, r1 * _u(rng, 0.7, 0.9), 0)])
    ln = _u(rng, 0.65, 0.78)
    _neck(b, rng, lb - 0.06, lb + ln, front + 0.012, 0.085, 0.07)
    lh, wh = _u(rng, 0.24, 0.3), _u(rng, 0.08, 0.095)
    head = _symmetric(
        np.array(
            [
                [0.0, -0.01],
                [0.04, -0.01],
                [wh * 0.55, 0.3 * lh],
                [wh * 0.6, 0.92 * lh],
                [wh * 0.3, lh],
                [0.0, 0.97 * lh],
            ]
        )
    )
    pegs = [(s * wh * 0.5, f * lh) for s in (1, -1) for f in (0.35, 0.55, 0.75)]
    _head(b, head, lb + ln - 0.01, front + 0.012, _u(rng, 0.15, 0.3), pegs, 0.03)


def _electric_parts(
    b: ShapeBuilder,
    rng: np.random.Generator,
    front: float,
    y_bridge: float,
    y_neck_pickup: float,
    knob_z: float,
) -> None:
    """Bridge, two pickups and three knobs: small pieces that merge into the body."""
    b.add(box(0.02, 0.05, 0.12), "body", [translation(front + 0.008, y_bridge, 0)])
    b.add(
        box(0.016, 0.04, 0.1),
        "body",
        [translation(front + 0.006, y, 0) for y in (y_bridge + 0.07, y_neck_pickup)],
    )
    b.add(
        frustum(0.018, 0.016, 0.025, 10).transformed(rotation("z", -0.5 * np.pi)),
        "body",
        [translation(front - 0.005, y_bridge - 0.06 * k, knob_z + 0.02 * k) for k in range(3)],
    )


def double_cut(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Symmetric double-cutaway solid body with two horns, pickguard, 3+3 pointed headstock."""
    lb, W, depth = _u(rng, 0.607, 0.943), _u(rng, 0.416, 0.644), _u(rng, 0.07, 0.1)
    horn = _u(rng, 0.08, 0.16)
    half = np.array(
        [
            [0.0, 0.0],
            [0.3 * W, 0.02],
            [0.5 * W, 0.2 * lb],
            [0.42 * W, 0.5 * lb],
            [0.5 * W, 0.75 * lb],
            [0.36 * W, lb + horn],
            [0.24 * W, lb + horn * 0.8],
            [0.14 * W, 0.85 * lb],
            [0.0, 0.88 * lb],
        ]
    )
    b.add(panel(chaikin(_symmetric(half), 2), depth, 0.012), "body")
    front = depth / 2
    guard = _symmetric(
        np.array(
            [
                [0.0, 0.12 * lb],
                [0.3 * W, 0.3 * lb],
                [0.3 * W, 0.6 * lb],
                [0.12 * W, 0.85 * lb],
                [0.0, 0.86 * lb],
            ]
        )
    )
    b.add(panel(chaikin(guard, 1), 0.006, 0.0), "body", [translation(front, 0, 0)])
    _electric_parts(b, rng, front, 0.25 * lb, 0.65 * lb, 0.3 * W)
    ln = _u(rng, 0.7, 0.8)
    heel = 0.08 * lb if rng.random() < 0.35 else 0.0
    _neck(b, rng, 0.8 * lb, lb + ln, front + 0.012, 0.075, 0.062, heel)
    lh, wh = _u(rng, 0.22, 0.28), _u(rng, 0.08, 0.1)
    head = _symmetric(
        np.array([[0.0, -0.01], [0.035, -0.01], [wh * 0.6, 0.4 * lh], [wh * 0.5, 0.85 * lh], [0.0, lh]])
    )
    pegs = [(s * wh * 0.42, f * lh) for s in (1, -1) for f in (0.3, 0.48, 0.66)]
    _head(b, head, lb + ln - 0.01, front + 0.012, _u(rng, 0.2, 0.3), pegs, 0.028)


def single_cut(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Single-cutaway carved-top body (one horn), raised pickups, rounded 3+3 headstock."""
    lb, W, depth = _u(rng, 0.61, 0.89), _u(rng, 0.435, 0.645), _u(rng, 0.09, 0.12)
    ctrl = np.array(
        [
            [0.0, 0.0],
            [0.35 * W, 0.02],
            [0.5 * W, 0.25 * lb],
            [0.42 * W, 0.55 * lb],
            [0.45 * W, 0.8 * lb],
            [0.3 * W, lb],
            [0.08 * W, 0.98 * lb],
            [-0.06 * W, 0.95 * lb],
            [-0.1 * W, 0.8 * lb],
            [-0.38 * W, 0.85 * lb],
            [-0.42 * W, 0.55 * lb],
            [-0.5 * W, 0.25 * lb],
            [-0.35 * W, 0.02],
        ]
    )
    b.add(panel(chaikin(ccw(ctrl), 2), depth, 0.02), "body")
    front = depth / 2
    _electric_parts(b, rng, front, 0.3 * lb, 0.7 * lb, -0.3 * W)
    ln = _u(rng, 0.62, 0.72)
    heel = 0.1 * lb if rng.random() < 0.35 else 0.0
    _neck(b, rng, 0.85 * lb, lb + ln, front + 0.012, 0.078, 0.066, heel)
    lh, wh = _u(rng, 0.22, 0.27), _u(rng, 0.1, 0.12)
    head = _symmetric(
        np.array(
            [
                [0.0, -0.01],
                [0.036, -0.01],
                [wh * 0.55, 0.5 * lh],
                [wh * 0.5, 0.9 * lh],
                [wh * 0.2, 0.95 * lh],
                [0.0, lh],
            ]
        )
    )
    pegs = [(s * wh * 0.42, f * lh) for s in (1, -1) for f in (0.3, 0.5, 0.7)]
    _head(b, head, lb + ln - 0.01, front + 0.012, _u(rng, 0.2, 0.3), pegs, 0.028)


def flying_v(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Flying V: two wings meeting at the neck, pointed six-in-line headstock."""
    lb, W, depth = _u(rng, 0.651, 0.999), _u(rng, 0.433, 0.687), _u(rng, 0.06, 0.08)
    notch = _u(rng, 0.35, 0.5) * lb
    half = np.array(
        [[0.0, notch], [0.32 * W, 0.0], [0.5 * W, 0.03], [0.2 * W, 0.8 * lb], [0.08 * W, lb], [0.0, lb]]
    )
    b.add(panel(chaikin(_symmetric(half), 1), depth, 0.01), "body")
    front = depth / 2
    _electric_parts(b, rng, front, notch + 0.1, 0.75 * lb, 0.25 * W)
    ln = _u(rng, 0.68, 0.78)
    _neck(b, rng, 0.7 * lb, lb + ln, front + 0.012, 0.072, 0.06)
    lh, wh = _u(rng, 0.26, 0.32), _u(rng, 0.07, 0.09)
    head = ccw(
        np.array(
            [
                [-0.035, -0.01],
                [0.035, -0.01],
                [wh, 0.15 * lh],
                [wh * 0.8, 0.8 * lh],
                [0.0, lh],
                [-wh * 0.4, 0.6 * lh],
            ]
        )
    )
    pegs = [(wh * 0.55, f * lh) for f in np.linspace(0.18, 0.78, 6)]
    _head(b, head, lb + ln - 0.01, front + 0.012, _u(rng, 0.15, 0.25), pegs, 0.026)


STYLES = {"acoustic": acoustic, "double_cut": double_cut, "single_cut": single_cut, "flying_v": flying_v}
