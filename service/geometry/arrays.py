"""Small numpy helpers of the geometry readers, shared with contact refinement (pure functions)."""

from __future__ import annotations

import numpy as np


def concat_ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """``arange(s, s + c)`` for every start and count, concatenated (no Python loop).

    Shapes:
        starts (n,), counts (n,) >= 0 -> (sum(counts),) int64.
    """
    counts = np.asarray(counts, dtype=np.int64)
    ends = np.cumsum(counts)
    total = int(ends[-1]) if len(ends) else 0
    return np.repeat(np.asarray(starts, dtype=np.int64) - (ends - counts), counts) + np.arange(total)
