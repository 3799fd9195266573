"""Lamps: table lamp (turned base, drum shade), floor torchiere (segmented pole, bowl shade),
architect desk lamp (two arm tubes, cone shade) and pendant (canopy, cord, dome shade).

Labels follow the ShapeNet part benchmark: base, shade, bulb, tube. Build units: about 2 tall
(the desk lamp about 1.6 long). Bulbs are kept large enough (radius >= 0.075) to stay a part.
"""

from __future__ import annotations

import numpy as np

from training.data.generator.assembly import ShapeBuilder
from training.data.generator.mesh import Mesh, compose, rotation, translation
from training.data.generator.primitives import ellipsoid, frustum, lathe, rod, torus

LABELS = ("base", "shade", "bulb", "tube")


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _shell(profile: np.ndarray, thickness: float, segments: int = 20) -> Mesh:
    """A thin surface of revolution: the open profile (r, y) offset inward by ``thickness``."""
    p = np.asarray(profile, float)
    d = np.gradient(p, axis=0)
    normal = np.stack([d[:, 1], -d[:, 0]], 1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    if np.mean(normal[:, 0]) < 0:  # make the offset point towards the axis
        normal = -normal
    inner = p - thickness * normal
    inner[:, 0] = np.maximum(inner[:, 0], 0.005)
    return lathe(np.concatenate([p, inner[::-1]]), segments, closed=True)


def _bulb(radius: float) -> Mesh:
    """A pear-shaped bulb standing on y = 0 (its neck), about 2.3 radii tall."""
    t = np.linspace(-0.5 * np.pi, 0.5 * np.pi, 7)
    head = np.stack([radius * np.cos(t), 1.3 * radius + radius * np.sin(t)], 1)
    return lathe(
        np.concatenate([[[0.0, 0.0], [0.45 * radius, 0.0], [0.5 * radius, 0.35 * radius]], head[1:]]), 14
    )


def table(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Table lamp: turned vase base, short tube, socket, bulb, drum or conical shade."""
    bh, br = _u(rng, 0.422, 0.878), _u(rng, 0.186, 0.384)
    belly = _u(rng, 0.9, 1.3)
    base = lathe(
        np.array(
            [
                [0.75 * br, 0.0],
                [br * belly, 0.35 * bh],
                [0.8 * br, 0.75 * bh],
                [0.25 * br, bh],
                [0.12, bh + 0.02],
            ]
        ),
        18,
    )
    b.add(base, "base")
    b.add(
        frustum(0.75 * br - 0.01, 0.75 * br - 0.01, 0.02, 18), "base", [translation(0, -0.01, 0)]
    )  # felt pad
    tl = _u(rng, 0.12, 0.3)
    tr = _u(rng, 0.02, 0.03)
    b.add(rod([0, bh - 0.02, 0], [0, bh + tl, 0], tr, segments=10), "tube")
    b.add(frustum(0.04, 0.04, 0.08, 12), "tube", [translation(0, bh + tl - 0.02, 0)])  # socket
    r = _u(rng, 0.085, 0.11)
    b.add(_bulb(r), "bulb", [translation(0, bh + tl + 0.05, 0)])
    sh = _u(rng, 0.5, 0.75)
    r_top, r_bot = _u(rng, 0.3, 0.5), _u(rng, 0.5, 0.75)
    y0 = bh + tl + 0.05 + 1.3 * r - 0.45 * sh
    b.add(_shell(np.array([[r_bot, y0], [r_top, y0 + sh]]), 0.015), "shade")
    # Fitter: a wire ring inside the top rim and three spokes down to the socket hold the shade.
    y_top = y0 + sh - 0.01
    b.add(torus(r_top - 0.012, 0.008, 20, 6), "shade", [translation(0, y_top, 0)])
    spoke = rod([0.035, bh + tl + 0.05, 0], [r_top - 0.012, y_top, 0], 0.007, segments=6)
    phase = _u(rng, 0, 2 * np.pi)
    b.add(spoke, "shade", [rotation("y", phase + 2 * np.pi * k / 3) for k in range(3)])


def floor(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Torchiere: heavy disc base, pole of identical screwed segments, uplight bowl and bulb."""
    H = _u(rng, 1.472, 2.328)
    br, bh = _u(rng, 0.22, 0.32), _u(rng, 0.04, 0.07)
    b.add(lathe(np.array([[br, 0.0], [br, bh * 0.6], [0.8 * br, bh], [0.06, bh + 0.02]]), 20), "base")
    n = int(rng.integers(2, 4))
    tr = _u(rng, 0.016, 0.024)
    y0, y1 = bh, H - _u(rng, 0.25, 0.35)
    seg = (y1 - y0) / n
    b.add(
        rod([0, 0, 0], [0, seg + 0.01, 0], tr, segments=10),
        "tube",
        [translation(0, y0 + k * seg, 0) for k in range(n)],
    )
    b.add(
        frustum(tr + 0.008, tr + 0.008, 0.03, 10),
        "tube",
        [translation(0, y0 + k * seg - 0.015, 0) for k in range(1, n)],
    )
    b.add(frustum(0.04, 0.04, 0.08, 12), "tube", [translation(0, y1 - 0.04, 0)])  # socket
    r = _u(rng, 0.08, 0.11)
    b.add(_bulb(r), "bulb", [translation(0, y1 + 0.03, 0)])
    rw, depth = _u(rng, 0.35, 0.5), _u(rng, 0.15, 0.25)
    yb = y1 - 0.03
    t = np.linspace(0.0, 1.0, 7)
    r0 = tr + 0.004  # the bowl sits on the pole
    bowl = np.stack([r0 + (rw - r0) * np.sin(0.5 * np.pi * t), yb + depth * (1 - np.cos(0.5 * np.pi * t))], 1)
    b.add(_shell(bowl, 0.015), "shade")


def desk(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Architect lamp: round base, lower and upper arm tubes with ball joints, cone shade."""
    br, bh = _u(rng, 0.22, 0.3), _u(rng, 0.06, 0.1)
    b.add(lathe(np.array([[br, 0.0], [br, bh * 0.7], [0.85 * br, bh], [0.0, bh]]), 20), "base")
    a1, a2 = _u(rng, 0.7, 0.95), _u(rng, 0.6, 0.85)
    t1, t2 = _u(rng, 0.15, 0.45), _u(rng, 0.9, 1.4)  # tilt of each arm from vertical (radians)
    tr = _u(rng, 0.014, 0.02)
    p0 = np.array([-0.3 * br, bh - 0.01, 0.0])
    p1 = p0 + a1 * np.array([np.sin(t1), np.cos(t1), 0.0])
    p2 = p1 + a2 * np.array([np.sin(t2), np.cos(t2), 0.0])
    b.add(rod(p0, p1, tr, segments=10), "tube")
    b.add(rod(p1, p2, tr, segments=10), "tube")
    b.add(ellipsoid(0.035, 0.035, 0.035, 12, 6), "tube", [translation(*p0), translation(*p1)])
    # Shade: a cone opening downwards-forwards, hung from the end of the upper arm.
    sl, sr = _u(rng, 0.3, 0.45), _u(rng, 0.16, 0.24)
    cone = _shell(np.array([[0.05, sl], [0.4 * sr, 0.6 * sl], [sr, 0.0]]), 0.012)
    aim = _u(rng, 0.4, 1.0)  # rotation of the shade axis away from straight down
    T = compose(translation(*p2), rotation("z", np.pi - aim), translation(0, -sl + 0.01, 0))
    b.add(cone, "shade", [T])
    r = _u(rng, 0.08, 0.1)
    b.add(_bulb(r), "bulb", [compose(T, translation(0, 0.55 * sl, 0), rotation("x", np.pi))])


def pendant(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Pendant lamp: ceiling canopy, long cord, dome shade and a bulb hanging out of it."""
    H = _u(rng, 1.378, 2.322)
    cr, ch = _u(rng, 0.1, 0.16), _u(rng, 0.06, 0.1)
    b.add(lathe(np.array([[0.0, H - ch], [0.6 * cr, H - ch], [cr, H - 0.3 * ch], [cr, H]]), 18), "base")
    # Two screws through the canopy's rim into the ceiling.
    b.bolts(
        np.array([[s * 0.8 * cr, H - 0.6 * ch, 0.0] for s in (1, -1)]),
        "base",
        0.012,
        0.01,
        direction=(1.0, 0.0, 0.0),
    )
    rw, dh = _u(rng, 0.45, 0.7), _u(rng, 0.3, 0.5)
    ys = _u(rng, 0.3, 0.6)  # bottom rim of the shade
    b.add(rod([0, ys + dh - 0.02, 0], [0, H - ch + 0.01, 0], _u(rng, 0.008, 0.014), segments=8), "tube")
    t = np.linspace(0.0, 1.0, 8)
    dome = np.stack([0.04 + (rw - 0.04) * np.sin(0.5 * np.pi * t), ys + dh * np.cos(0.5 * np.pi * t)], 1)
    b.add(_shell(dome, 0.015), "shade")
    r = _u(rng, 0.09, 0.12)
    b.add(frustum(0.035, 0.035, 0.1, 12), "tube", [translation(0, ys + dh - 0.1, 0)])
    b.add(_bulb(r), "bulb", [compose(translation(0, ys + dh - 0.08, 0), rotation("x", np.pi))])


STYLES = {"table": table, "floor": floor, "desk": desk, "pendant": pendant}
