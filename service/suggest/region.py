"""A spot where the caller wants a part: "suggest for this spot" (the paper's rough placements).

A region is a ball (a point the user clicked and a radius) or an axis-aligned box (a box the
user dragged), given in the caller's frame. A suggestion is *in* the region when its placed
box (h's translation, the fitted scale applied) reaches into it: for a ball, the box comes
within ``radius`` of the point; for a box, the two boxes overlap. Boxes, not centres: a click
on the underside of a seat means "a leg here", and a leg's centre lies half a leg below the
seat while its box reaches the spot.

The engine ranks a larger candidate set than k for a region query, places all of it with h,
and keeps the parts in the region (``service.suggest.engine``); ``gap`` also says how far the nearest
placed part missed when none is in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.errors import InputError
from service.geometry.frames import Frame


@dataclass(frozen=True)
class Region:
    """A ball (``center``, ``radius``) or a box (``box_min``, ``box_max``), exactly one of them.

    Build it with ``Region.ball`` or ``Region.box``, which check the values.

    Shapes:
        center, box_min, box_max: (3,) float64 or None.
    """

    center: np.ndarray | None = None
    radius: float | None = None
    box_min: np.ndarray | None = None
    box_max: np.ndarray | None = None

    @classmethod
    def ball(cls, center: np.ndarray, radius: float) -> Region:
        """The points within ``radius`` of ``center``; ``InputError`` for non-finite values or radius <= 0."""
        c = np.asarray(center, dtype=np.float64)
        if c.shape != (3,) or not np.all(np.isfinite(c)):
            raise InputError("invalid_region", f"region.point must be 3 finite numbers, found {c.tolist()}")
        if not (np.isfinite(radius) and radius > 0):
            raise InputError("invalid_region", f"region.radius must be a finite number > 0, found {radius}")
        return cls(center=c, radius=float(radius))

    @classmethod
    def box(cls, box_min: np.ndarray, box_max: np.ndarray) -> Region:
        """The box between two corners; ``InputError`` when a corner is not finite or min > max."""
        lo, hi = np.asarray(box_min, dtype=np.float64), np.asarray(box_max, dtype=np.float64)
        if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise InputError("invalid_region", "region.min and region.max must be 3 finite numbers each")
        bad = [f"{axis}: {a:g} > {b:g}" for axis, a, b in zip("xyz", lo, hi, strict=True) if a > b]
        if bad:
            raise InputError("invalid_region", "region.min must not exceed region.max on any axis ("
                             + ", ".join(bad) + ")")
        return cls(box_min=lo, box_max=hi)

    @property
    def is_ball(self) -> bool:
        return self.center is not None

    def in_frame(self, frame: Frame) -> Region:
        """The same region in the canonical frame, given the caller's ``frame``.

        ``InputError`` when the frame makes it non-finite (a tiny frame radius).
        """
        with np.errstate(over="ignore", invalid="ignore"):
            if self.center is not None and self.radius is not None:
                c = frame.to_canonical(self.center[None]).astype(np.float64)[0]
                r = self.radius / frame.radius
                if np.all(np.isfinite(c)) and np.isfinite(r) and r > 0:
                    return Region(center=c, radius=float(r))
            elif self.box_min is not None and self.box_max is not None:
                a = frame.to_canonical(np.stack([self.box_min, self.box_max])).astype(np.float64)
                if np.all(np.isfinite(a)):
                    # The frames' rotations are signed permutations: the box stays axis-aligned.
                    return Region(box_min=a.min(axis=0), box_max=a.max(axis=0))
        raise InputError("invalid_region", "the region is not finite in the model's frame; check the "
                         "frame's center and radius")

    def size(self) -> float:
        """The region's radius (a ball) or half its diagonal (a box), in its frame's units."""
        if self.radius is not None:
            return self.radius
        assert self.box_min is not None and self.box_max is not None
        return float(np.linalg.norm(self.box_max - self.box_min) / 2)

    def gap(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """How far each box stays from the region: 0 when it reaches into it.

        Shapes:
            lo, hi: (P, 3) boxes in the region's frame -> (P,) float64 >= 0.
        """
        lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
        assert lo.shape == hi.shape and lo.ndim == 2 and lo.shape[1] == 3, (
            f"boxes must be (P, 3) each, found {lo.shape} and {hi.shape}")
        if self.center is not None and self.radius is not None:
            # Distance from the point to the box (0 inside), less the ball's radius.
            outside = np.maximum(np.maximum(lo - self.center, self.center - hi), 0.0)
            return np.maximum(np.linalg.norm(outside, axis=1) - self.radius, 0.0)
        assert self.box_min is not None and self.box_max is not None
        apart = np.maximum(np.maximum(lo - self.box_max, self.box_min - hi), 0.0)
        return np.linalg.norm(apart, axis=1)
