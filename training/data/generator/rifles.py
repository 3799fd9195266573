"""Rifles: bolt-action hunting rifle (one-piece stock, scope), assault rifle (curved magazine,
pistol grip), lever-action carbine (tube magazine, lever loop), sniper rifle (heavy barrel,
big scope, bipod) and pump shotgun (tube magazine, sliding forend).

Labels (no ShapeNet part benchmark category): barrel, stock, body (the receiver), magazine,
scope, grip, trigger, bipod. Rules used throughout: the butt stock and whatever the support
hand holds in front of the trigger (forend, handguard, pump) is stock; only a separate pistol
grip is grip; the trigger guard and the lever loop are trigger; sights, bands and muzzle devices
are barrel; scope mounts are scope. Some styles lack some parts (no scope, no magazine, no
grip). Frame: muzzle towards +x, up +y, the gun lying flat in the xy plane (width along z).
Build units: about 2 long, bore axis at y = 0.
"""

from __future__ import annotations

import numpy as np

from training.data.generator.assembly import ShapeBuilder
from training.data.generator.mesh import Mesh, compose, rotation, translation
from training.data.generator.outlines import chaikin, ellipse, rounded_rect
from training.data.generator.primitives import box, lathe, rod, side_panel, sweep, torus

LABELS = ("barrel", "stock", "body", "magazine", "scope", "grip", "trigger", "bipod")


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def _along_x(mesh: Mesh) -> Mesh:
    """Turn a lathe built along +y so that its axis runs along +x."""
    return mesh.transformed(rotation("z", -0.5 * np.pi))


def _barrel(b: ShapeBuilder, x0: float, x1: float, r0: float, r1: float, y: float = 0.0) -> None:
    b.add(rod([x0, y, 0], [x1, y, 0], r0, r1, 12), "barrel")


def _butt(
    rng: np.random.Generator,
    b: ShapeBuilder,
    x_front: float,
    y_top: float,
    y_bottom: float,
    x_end: float,
    pistol: bool,
    thickness: float,
) -> None:
    """A butt stock from the receiver (x_front, between y_bottom and y_top) back to x_end."""
    drop, hb = _u(rng, 0.02, 0.09), _u(rng, 0.2, 0.3)
    heel = y_top - drop
    wrist = x_front - _u(rng, 0.08, 0.14)
    if pistol:
        # Wrist swelling into a built-in pistol grip below the front of the stock.
        bottom = [
            [x_front - 0.02, y_bottom - 0.08],
            [wrist - 0.03, y_bottom - 0.1],
            [wrist - 0.1, y_bottom - 0.04],
        ]
    else:
        bottom = [[x_front - 0.01, y_bottom], [wrist - 0.05, y_bottom - 0.01]]
    pts = np.array(
        [
            [x_front, y_top],
            [wrist, y_top - 0.02],
            [wrist - 0.12, heel + 0.01],
            [x_end, heel],
            [x_end, heel - hb],
            [x_end + 0.3 * (x_front - x_end), y_bottom - 0.1 - 0.4 * hb * _u(rng, 0.6, 1.0)],
            *bottom[::-1],
        ]
    )
    b.add(side_panel(chaikin(pts, 2), thickness, 0.008), "stock")


def _trigger(b: ShapeBuilder, x: float, y: float, guard: bool = True) -> None:
    """Trigger blade hanging from y at x, and a guard loop around it."""
    b.add(box(0.012, 0.06, 0.01).transformed(rotation("z", 0.25)), "trigger", [translation(x, y - 0.02, 0)])
    if guard:
        ring = torus(0.04, 0.006, 14, 6).transformed(rotation("x", 0.5 * np.pi))
        b.add(ring, "trigger", [translation(x - 0.005, y - 0.02, 0)])


def _scope(
    rng: np.random.Generator, b: ShapeBuilder, x0: float, x1: float, y: float, r: float, y_mount: float
) -> None:
    """Tube with objective and eyepiece bells along x at height y, two rings down to y_mount."""
    bell, ln = r * _u(rng, 1.3, 1.9), x1 - x0
    prof = np.array(
        [
            [r * 1.3, 0.0],
            [r * 1.3, 0.1 * ln],
            [r, 0.2 * ln],
            [r, 0.7 * ln],
            [bell, 0.85 * ln],
            [bell, ln],
        ]
    )
    b.add(_along_x(lathe(prof, 14)), "scope", [translation(x0, y, 0)])
    h = y - y_mount
    mount = box(0.03, h, 2.2 * r)
    b.add(mount, "scope", [translation(x0 + f * ln, y_mount + h / 2, 0) for f in (0.3, 0.62)])


def hunting(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Bolt-action hunting rifle: one-piece wooden stock with forend, round receiver, scope."""
    xr0, xr1 = -_u(rng, 0.38, 0.48), -_u(rng, 0.0, 0.1)
    rr = _u(rng, 0.03, 0.04)
    xf = _u(rng, 0.2, 0.45)
    x_end = -1.0 * _u(rng, 0.9, 1.1)
    t = _u(rng, 0.055, 0.075)
    # Stock top runs just inside the receiver and barrel, the forend ends at xf.
    pts = np.array(
        [
            [xf, -0.015],
            [xf + 0.01, -0.06],
            [xr1, -0.085],
            [xr0 + 0.1, -0.1],
            [xr0, -0.16 * _u(rng, 0.8, 1.2)],
            [xr0 - 0.12, -0.11],
            [xr0 - 0.2, -0.16],
            [x_end, -0.32 * _u(rng, 0.85, 1.15)],
            [x_end, -0.08],
            [xr0 - 0.15, -0.05],
            [xr0 - 0.05, -0.05],
            [xr0, -0.015],
        ]
    )
    b.add(side_panel(chaikin(pts, 2), t, 0.008), "stock")
    b.add(rod([xr0, 0, 0], [xr1, 0, 0], rr, rr, 12), "body")
    knob = _knob()
    bx = xr0 + 0.06
    b.add(rod([bx, 0.0, 0.0], [bx - 0.03, -0.03, 0.09], 0.008, segments=8), "body")
    b.add(knob, "body", [translation(bx - 0.03, -0.03, 0.09)])
    _barrel(b, xr1 - 0.02, _u(rng, 0.9, 1.05), rr * 0.65, rr * _u(rng, 0.4, 0.5))
    _trigger(b, xr0 + 0.08, -0.1)
    if rng.random() < 0.5:
        b.add(box(0.14, 0.015, 0.05), "magazine", [translation(0.5 * (xr0 + xr1), -0.09, 0)])
    if rng.random() < 0.8:
        _scope(
            rng,
            b,
            xr0 - 0.05,
            xr1 + _u(rng, 0.1, 0.2),
            rr + _u(rng, 0.05, 0.08),
            _u(rng, 0.018, 0.024),
            rr - 0.01,
        )
    else:
        b.add(box(0.03, 0.04, 0.012), "barrel", [translation(0.9, 0.03, 0)])
    # Scope base screws on top of the receiver.
    b.bolts(np.array([[xr0 + 0.05, rr, 0.0], [xr1 - 0.05, rr, 0.0]]), "body", 0.01, 0.01)


def _knob() -> Mesh:
    """The round knob of a bolt handle."""
    return lathe(
        np.stack(
            [
                0.018 * np.cos(np.linspace(-0.5 * np.pi, 0.5 * np.pi, 6)),
                0.018 * np.sin(np.linspace(-0.5 * np.pi, 0.5 * np.pi, 6)),
            ],
            1,
        ),
        10,
    )


def assault(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Assault rifle: box receiver, handguard, curved box magazine, pistol grip, fixed stock."""
    lr, xr1 = _u(rng, 0.38, 0.5), _u(rng, -0.02, 0.08)
    xr0 = xr1 - lr
    ur = _u(rng, 0.07, 0.09)
    lw = lr * _u(rng, 0.7, 0.85)
    yu, yd = 0.01 + ur / 2, 0.01 - ur / 2
    receiver = np.array(
        [
            [xr1, yu],
            [xr0, yu],
            [xr0, yd - 0.065],
            [xr0 + lw + 0.02, yd - 0.065],
            [xr0 + lw + 0.04, yd],
            [xr1, yd],
        ]
    )
    b.add(side_panel(receiver, 0.06, 0.006), "body")
    yl = 0.01 - ur / 2 - 0.065  # bottom of the lower receiver
    # Handguard (stock) and barrel with a muzzle device and a front sight.
    xh = xr1 + _u(rng, 0.3, 0.5)
    hr = _u(rng, 0.035, 0.05)
    b.add(rod([xr1 - 0.01, 0, 0], [xh, 0, 0], hr, hr * 0.9, 10), "stock")
    xm = xh + _u(rng, 0.3, 0.5)
    _barrel(b, xr1 - 0.02, xm, 0.017, 0.015)
    b.add(rod([xm - 0.08, 0, 0], [xm + 0.02, 0, 0], 0.024, segments=10), "barrel")
    b.add(box(0.03, 0.1, 0.02), "barrel", [translation(xh + 0.04, 0.04, 0)])
    # Curved magazine swept down and forward from inside the lower receiver.
    lm, k = _u(rng, 0.25, 0.36), _u(rng, 0.04, 0.14)
    s = np.linspace(0, 1, 7)
    xmag = xr1 - lw * _u(rng, 0.1, 0.3) - 0.12
    path = np.stack([xmag + k * s**2, yl + 0.03 - lm * s, np.zeros_like(s)], 1)
    b.add(sweep(rounded_rect(0.03, 0.1, 0.005, 2), path, up=np.array([0.0, 0.0, 1.0])), "magazine")
    # Pistol grip raked back under the rear of the lower receiver.
    xg, hg, rake = xr0 + _u(rng, 0.08, 0.14), _u(rng, 0.18, 0.25), _u(rng, 0.06, 0.12)
    grip = np.array(
        [
            [xg + 0.035, yl + 0.02],
            [xg + 0.035 - rake, yl - hg],
            [xg - 0.04 - rake, yl - hg],
            [xg - 0.035, yl + 0.02],
        ]
    )
    b.add(side_panel(chaikin(grip, 1), 0.045, 0.006), "grip")
    _trigger(b, xg + 0.07, yl + 0.01, guard=False)
    b.add(box(0.12, 0.01, 0.03), "trigger", [translation(xg + 0.09, yl - 0.05, 0)])
    b.add(box(0.01, 0.06, 0.03), "trigger", [translation(xg + 0.145, yl - 0.02, 0)])
    # Fixed or skeletal stock behind the receiver.
    x_end = -1.0 * _u(rng, 0.9, 1.1)
    hb = _u(rng, 0.18, 0.28)
    pts = np.array(
        [
            [xr0 + 0.02, 0.04],
            [x_end, 0.03],
            [x_end, 0.03 - hb],
            [x_end + 0.15, 0.03 - hb],
            [xr0 + 0.02, -0.04],
        ]
    )
    b.add(side_panel(chaikin(pts, 1), 0.05, 0.006), "stock")
    if rng.random() < 0.5:
        # A carry handle with a rear sight, or a short optic on a rail.
        b.add(box(0.2, 0.05, 0.02), "body", [translation(xr1 - lr / 2, 0.01 + ur / 2 + 0.02, 0)])
    else:
        _scope(rng, b, xr1 - lr * 0.7, xr1 - 0.05, 0.01 + ur / 2 + 0.06, 0.02, 0.01 + ur / 2 - 0.01)
    # Takedown pins through the lower receiver.
    pins = np.array([[xr0 + 0.04, yl + 0.03, 0.03], [xr0 + lw - 0.02, yl + 0.03, 0.03]])
    b.bolts(pins, "body", 0.008, 0.012, (0, 0, 1))


def lever(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Lever-action carbine: straight-grip stock, flat receiver, tube magazine, lever loop."""
    xr0, xr1 = -_u(rng, 0.42, 0.5), -_u(rng, 0.1, 0.2)
    yb = -_u(rng, 0.09, 0.12)
    rec = np.array(
        [[xr1, 0.035], [xr1, yb + 0.02], [xr1 - 0.03, yb], [xr0, yb], [xr0, 0.045], [xr0 + 0.05, 0.05]]
    )
    b.add(side_panel(chaikin(rec, 1), 0.05, 0.006), "body")
    b.add(box(0.04, 0.04, 0.012).transformed(rotation("z", 0.5)), "body", [translation(xr0 + 0.02, 0.05, 0)])
    _butt(rng, b, xr0 + 0.01, 0.02, yb + 0.02, -1.0 * _u(rng, 0.9, 1.05), False, _u(rng, 0.045, 0.06))
    xm = _u(rng, 0.85, 1.0)
    _barrel(b, xr1 - 0.02, xm, 0.02, 0.017)
    ym, rm = -_u(rng, 0.055, 0.065), 0.016
    xt = xm - _u(rng, 0.0, 0.25)
    b.add(rod([xr1 - 0.02, ym, 0], [xt, ym, 0], rm, segments=10), "magazine")
    xf = xr1 + _u(rng, 0.25, 0.4)
    b.add(rod([xr1 - 0.01, -0.035, 0], [xf, -0.035, 0], 0.045, 0.04, 10), "stock")
    # Barrel bands around barrel and tube.
    band = box(0.02, 0.1, 0.05)
    b.add(band, "barrel", [translation(x, -0.03, 0) for x in (xf + 0.04, xt - 0.05)])
    b.add(box(0.03, 0.04, 0.012), "barrel", [translation(xm - 0.04, 0.03, 0)])
    # Lever loop under the wrist, trigger inside it.
    xl = xr0 + _u(rng, 0.08, 0.12)
    drop = _u(rng, 0.08, 0.12)
    loop = np.array(
        [
            [xl + 0.12, yb + 0.01, 0],
            [xl + 0.1, yb - drop, 0],
            [xl - 0.12, yb - drop, 0],
            [xl - 0.16, yb - 0.02, 0],
        ]
    )
    b.add(sweep(ellipse(0.008, 0.01, 8), loop, up=np.array([0.0, 0.0, 1.0])), "trigger")
    _trigger(b, xl + 0.03, yb + 0.005, guard=False)
    if rng.random() < 0.3:
        _scope(rng, b, xr0 - 0.05, xr1 + 0.15, 0.11, 0.018, 0.03)
    b.bolts(np.array([[xr0 + 0.06, -0.02, 0.025], [xr1 - 0.06, -0.02, 0.025]]), "body", 0.01, 0.01, (0, 0, 1))


def sniper(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Sniper rifle: heavy barrel with muzzle brake, chassis stock with cheek rest, box magazine,
    pistol grip, big scope and a folding bipod."""
    xr0, xr1 = -_u(rng, 0.4, 0.5), -_u(rng, 0.0, 0.08)
    rr = _u(rng, 0.035, 0.045)
    b.add(rod([xr0, 0, 0], [xr1, 0, 0], rr, segments=12), "body")
    xm = _u(rng, 0.9, 1.05)
    _barrel(b, xr1 - 0.02, xm - 0.08, 0.032, 0.026)
    b.add(box(0.1, 0.05, 0.05), "barrel", [translation(xm - 0.05, 0, 0)])
    xf = xr1 + _u(rng, 0.3, 0.5)
    fh = _u(rng, 0.06, 0.08)
    y_low = -rr - fh + 0.01
    x_end = xr0 - _u(rng, 0.55, 0.65)
    # One chassis stock from the forend tip to the butt, with a raised cheek rest.
    pts = np.array(
        [
            [xf, -rr + 0.01],
            [xr0 - 0.05, -rr + 0.01],
            [x_end + 0.3, 0.02],
            [x_end + 0.05, 0.02],
            [x_end, -0.28],
            [x_end + 0.17, -0.3],
            [xr0 - 0.2, y_low],
            [xf, y_low],
        ]
    )
    b.add(side_panel(chaikin(pts, 1), 0.055, 0.006), "stock")
    mh = _u(rng, 0.1, 0.16)
    b.add(box(0.11, mh, 0.045), "magazine", [translation(xr1 - 0.12, y_low - mh / 2 + 0.03, 0)])
    xg, hg = xr0 + 0.06, _u(rng, 0.18, 0.24)
    grip = np.array(
        [
            [xg + 0.04, y_low + 0.02],
            [xg - 0.04, y_low - hg],
            [xg - 0.11, y_low - hg],
            [xg - 0.04, y_low + 0.02],
        ]
    )
    b.add(side_panel(chaikin(grip, 1), 0.045, 0.006), "grip")
    _trigger(b, xg + 0.08, y_low + 0.01)
    _scope(
        rng,
        b,
        xr0 - 0.1,
        xr1 + _u(rng, 0.15, 0.25),
        rr + _u(rng, 0.07, 0.09),
        _u(rng, 0.024, 0.03),
        rr - 0.01,
    )
    # Bipod: a clamp under the forend tip and two splayed legs.
    xb, lb, splay = xf - 0.06, _u(rng, 0.28, 0.38), _u(rng, 0.25, 0.45)
    b.add(box(0.05, 0.04, 0.08), "bipod", [translation(xb, y_low - 0.01, 0)])
    leg = rod([0, 0, 0], [0.06, -lb, 0], 0.012, 0.01, 8)
    top = translation(xb, y_low - 0.01, 0)
    b.add(leg, "bipod", [compose(top, rotation("x", splay)), compose(top, rotation("x", -splay))])


def shotgun(rng: np.random.Generator, b: ShapeBuilder) -> None:
    """Pump shotgun: boxy receiver, long barrel over a tube magazine, ribbed sliding forend."""
    xr0, xr1 = -_u(rng, 0.45, 0.55), -_u(rng, 0.1, 0.2)
    yb = -_u(rng, 0.1, 0.13)
    rec = np.array(
        [
            [xr1, 0.03],
            [xr1, yb],
            [xr0 + 0.04, yb],
            [xr0, yb + 0.05],
            [xr0, 0.03],
            [xr0 + 0.1, 0.05],
            [xr1 - 0.05, 0.05],
        ]
    )
    b.add(side_panel(chaikin(rec, 1), 0.055, 0.006), "body")
    _butt(rng, b, xr0 + 0.01, 0.03, yb + 0.03, -1.0 * _u(rng, 0.9, 1.05), rng.random() < 0.4, 0.055)
    xm = _u(rng, 0.9, 1.05)
    rb = _u(rng, 0.022, 0.028)
    _barrel(b, xr1 - 0.02, xm, rb, rb)
    if rng.random() < 0.5:
        b.add(box(xm - xr1, 0.012, 0.012), "barrel", [translation(0.5 * (xm + xr1), rb + 0.004, 0)])
    ym = -rb - 0.025
    xt = xm - _u(rng, 0.15, 0.4)
    b.add(rod([xr1 - 0.02, ym, 0], [xt, ym, 0], 0.02, segments=10), "magazine")
    b.add(box(0.03, 0.09, 0.05), "barrel", [translation(xt - 0.01, -0.03, 0)])
    # Pump: a ribbed lathe along x around the tube.
    x0, lp, pr = xr1 + _u(rng, 0.05, 0.15), _u(rng, 0.25, 0.35), _u(rng, 0.04, 0.05)
    ribs = [[pr * (1.0 if k % 2 else 0.9), lp * k / 8] for k in range(9)]
    b.add(
        _along_x(lathe(np.array([[0.8 * pr, 0.0], *ribs, [0.8 * pr, lp]]), 12)),
        "stock",
        [translation(x0, ym + 0.01, 0)],
    )
    _trigger(b, xr0 + 0.12, yb + 0.01)
    b.bolts(
        np.array([[xr0 + 0.08, yb + 0.04, 0.0275], [xr1 - 0.05, yb + 0.04, 0.0275]]),
        "body",
        0.01,
        0.01,
        (0, 0, 1),
    )


STYLES = {"hunting": hunting, "assault": assault, "lever": lever, "sniper": sniper, "shotgun": shotgun}
