"""Axis-aligned boxes: the one overlap measure that assembly (stacked parts, same job) and the
evaluation (placed-box fit, stacked runs) share (pure numpy)."""

from __future__ import annotations

import numpy as np


def box_iou(lo: np.ndarray, hi: np.ndarray, los: np.ndarray, his: np.ndarray) -> np.ndarray:
    """Intersection over union of one axis-aligned box with each of many.

    NaN where the union has no volume (two flat boxes): no overlap can be measured there, and
    every comparison with a threshold is false.

    Shapes:
        lo, hi: (3,); los, his: (P, 3) -> (P,) float64.
    """
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    los = np.asarray(los, dtype=np.float64).reshape(-1, 3)
    his = np.asarray(his, dtype=np.float64).reshape(-1, 3)
    inter = np.prod(np.clip(np.minimum(hi, his) - np.maximum(lo, los), 0, None), axis=1)
    union = np.prod(hi - lo) + np.prod(his - los, axis=1) - inter
    out = np.full(len(union), np.nan)
    np.divide(inter, union, out=out, where=union > 0)
    return out
