"""The spread of the suggestion order (``preferences.spread_order``), compiled (numba).

``spread_order`` decides, part after part of the list, whether a part lies within a few of its
mode's standard deviations of a part shown before it. Written with numpy in windows it cost
0.2-0.3 ms a call for the benchmark query (two calls a request, about a fifth of the engine's
2.5 ms): a few dozen numpy calls on arrays of a few thousand numbers each. Here each part is
compared with the shown parts one by one and stops at the first that is too near.

Same answers as the numpy version, bit for bit: each distance is the mean of squared z-scores
summed in the order numpy's ``mean`` sums a row (its pairwise summation: eight running sums over
runs of eight, then the rest; halves above 128 terms), so a part exactly at the limit is judged
the same way (``tests/service/test_spread_kernel.py`` compares the two sums bit for bit).

Plain arrays only; ``preferences`` owns what the order means.
"""

from __future__ import annotations

import numpy as np
from numba import njit

# numpy's pairwise summation: rows up to this long are summed in eight running sums.
_BLOCK = 128


@njit(cache=True, nogil=True, inline="always")
def _block_sum(a: np.ndarray, lo: int, n: int) -> float:  # pragma: no cover - compiled
    """numpy's sum of a row of at most ``_BLOCK`` numbers: eight running sums, then the rest."""
    if n < 8:
        res = 0.0
        for i in range(n):
            res += a[lo + i]
        return res
    r0, r1, r2, r3 = a[lo], a[lo + 1], a[lo + 2], a[lo + 3]
    r4, r5, r6, r7 = a[lo + 4], a[lo + 5], a[lo + 6], a[lo + 7]
    i = 8
    end = n - n % 8
    while i < end:
        r0 += a[lo + i]
        r1 += a[lo + i + 1]
        r2 += a[lo + i + 2]
        r3 += a[lo + i + 3]
        r4 += a[lo + i + 4]
        r5 += a[lo + i + 5]
        r6 += a[lo + i + 6]
        r7 += a[lo + i + 7]
        i += 8
    res = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True, nogil=True)
def pairwise_sum(a: np.ndarray, lo: int, n: int) -> float:  # pragma: no cover - compiled
    """Sum of ``a[lo:lo + n]`` in the order numpy's ``add.reduce`` sums a contiguous row: rows
    longer than ``_BLOCK`` are split in halves (the first a multiple of 8) and their sums added.

    The halves are walked with a stack of their own, not by recursion: numba's cache loaded a
    recursive version that crashed the process (a segmentation fault on the second run).
    """
    if n <= _BLOCK:
        return _block_sum(a, lo, n)
    # Frames: a range (start, length), how far it is (0: new, 1: left half summed, 2: both), and
    # its left half's sum. 64 frames: a range halves at each level.
    starts, lengths = np.empty(64, np.int64), np.empty(64, np.int64)
    stage, left = np.zeros(64, np.int64), np.zeros(64)
    top, starts[0], lengths[0] = 0, lo, n
    ret = 0.0
    while top >= 0:
        m = lengths[top]
        if m <= _BLOCK:
            ret = _block_sum(a, starts[top], m)
            top -= 1
            continue
        half = m // 2
        half -= half % 8
        if stage[top] == 0:            # sum the left half first
            stage[top] = 1
            top += 1
            starts[top], lengths[top], stage[top] = starts[top - 1], half, 0
        elif stage[top] == 1:          # the left half's sum is in ret: sum the right half
            left[top] = ret
            stage[top] = 2
            top += 1
            starts[top], lengths[top], stage[top] = starts[top - 1] + half, m - half, 0
        else:                          # both: this range's sum, handed to its parent
            ret = left[top] + ret
            top -= 1
    return ret


@njit(cache=True, nogil=True)
def spread(embeddings: np.ndarray, modes: np.ndarray, inverse: np.ndarray, first: int, k: int,
           limit: float, shown: np.ndarray) -> tuple[int, int]:  # pragma: no cover - compiled
    """Choose the parts shown: after the first ``first`` (shown as they are), each part in turn
    unless the mean of its squared z-scores to a part shown before it, in its mode's inverse
    standard deviations, is below ``limit`` (or not a number), until ``k`` are shown.

    Shapes:
        embeddings: (C, D); modes: (C,) int64; inverse: (K, D) float64 (1 / sigma);
        shown: (max(first, k),) int64, filled with the shown positions in order ->
        (how many were shown, the first position not looked at).
    """
    n, d = embeddings.shape
    z2 = np.empty(d)
    count = 0
    for j in range(first):
        shown[count] = j
        count += 1
    i = first
    while i < n and count < k:
        apart = True
        m = modes[i]
        for s in range(count):
            p = shown[s]
            for c in range(d):
                z = (np.float64(embeddings[i, c]) - np.float64(embeddings[p, c])) * inverse[m, c]
                z2[c] = z * z
            if not pairwise_sum(z2, 0, d) / d >= limit:
                apart = False
                break
        if apart:
            shown[count] = i
            count += 1
        i += 1
    return count, i


def warm() -> None:
    """Compile (or load from numba's cache) ``spread`` for the embeddings' types the engine and
    the catalog hold (float32, and float64 for callers that pass their own); the Docker image
    runs it at build time (``python -m service.suggest.spread_kernel``)."""
    inverse = np.ones((1, 4))
    for dtype in (np.float32, np.float64):
        spread(np.zeros((3, 4), dtype), np.zeros(3, np.int64), inverse, 1, 2, 1.0, np.zeros(2, np.int64))


if __name__ == "__main__":
    warm()
