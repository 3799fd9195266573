"""Surface area under a per-axis scale: the one estimate the assembly's queries and the training
sampler's mixed queries share (pure numpy)."""

from __future__ import annotations

import numpy as np


def scaled_area(area: float, scale: np.ndarray | None) -> float:
    """The area of a surface of ``area`` scaled about a point by ``scale`` (per axis; None: 1).

    Exact for a uniform scale s (s^2 times the area); for a per-axis scale, the uniform scale of
    the same volume change, (sx sy sz)^(2/3): the true factor depends on how the surface is
    oriented, which only the mesh knows, and both callers only need the share of query points a
    part gets.

    Shapes:
        scale: (3,) or None.
    """
    if scale is None:
        return float(area)
    return float(area) * float(np.prod(np.asarray(scale, dtype=np.float64))) ** (2 / 3)
