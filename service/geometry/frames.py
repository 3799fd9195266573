"""The caller's coordinate frame and the canonical frame the networks work in.

Canonical frame: y up, front +x, the complete object centred at its bounding-box centre and
scaled to unit radius. A caller may instead give the ``center`` and ``radius`` of its own frame
(the complete object's centre and radius in caller units) and its ``up_axis``; then

    canonical = R (p - center) / radius          caller = radius R^T q + center

with R the rotation taking the caller's up axis to +y (identity for "y"; for "z" the usual
z-up to y-up turn about +x: (x, y, z) -> (x, z, -y)). Catalog parts are stored in canonical
units, so a caller draws a part at ``scale * rotation @ v + translation`` with ``scale = radius``
and ``rotation = R^T``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

UpAxis = Literal["y", "z"]

_ROTATIONS: dict[str, np.ndarray] = {
    "y": np.eye(3),
    "z": np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]),
}


@dataclass(frozen=True)
class Frame:
    """A caller's frame: where the complete object's centre is, its radius, and which axis is up.

    Shapes:
        center: (3,) float64.
    """

    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    radius: float = 1.0
    up_axis: UpAxis = "y"

    def __post_init__(self) -> None:
        c = np.asarray(self.center, dtype=np.float64)
        assert c.shape == (3,) and np.all(np.isfinite(c)), f"center must be 3 finite numbers, found {c}"
        assert np.isfinite(self.radius) and self.radius > 0, f"radius must be > 0, found {self.radius}"
        assert self.up_axis in _ROTATIONS, f"up_axis must be 'y' or 'z', found {self.up_axis!r}"
        object.__setattr__(self, "center", c)

    @property
    def is_canonical(self) -> bool:
        return self.up_axis == "y" and self.radius == 1.0 and not np.any(self.center)

    @property
    def rotation(self) -> np.ndarray:
        """R: (3, 3), turns caller axes into canonical axes."""
        return _ROTATIONS[self.up_axis]

    @property
    def part_rotation(self) -> np.ndarray:
        """R^T: (3, 3), turns a canonical part's vertices into the caller's axes."""
        return _ROTATIONS[self.up_axis].T

    def to_canonical(self, points: np.ndarray) -> np.ndarray:
        """Caller points to the canonical frame: (N, 3) -> (N, 3) float32."""
        if self.is_canonical:
            return np.asarray(points, dtype=np.float32)
        # Out-of-range values become inf (or NaN); callers check finiteness.
        with np.errstate(over="ignore", invalid="ignore"):
            q = (np.asarray(points, dtype=np.float64) - self.center) / self.radius
            return (q @ self.rotation.T).astype(np.float32)

    def from_canonical(self, points: np.ndarray) -> np.ndarray:
        """Canonical positions to the caller's frame: (N, 3) -> (N, 3) float64."""
        q = np.asarray(points, dtype=np.float64)
        return self.radius * (q @ self.rotation) + self.center

    def box_from_canonical(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned canonical boxes to the caller's frame (rotations here keep them aligned).

        Shapes:
            lo, hi: (M, 3) -> (M, 3), (M, 3) float64.
        """
        a, b = self.from_canonical(lo), self.from_canonical(hi)
        return np.minimum(a, b), np.maximum(a, b)
