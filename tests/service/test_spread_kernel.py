"""The suggestion order's compiled spread (``service.suggest.spread_kernel``) answers as the numpy
sums it replaced: its distances are numpy's means bit for bit, so a part exactly at the limit is
judged the same way, and its compiled code loads from numba's cache in a new process."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from service.suggest.preferences import spread_order
from service.suggest.spread_kernel import pairwise_sum


def test_pairwise_sum_is_numpys_sum_bit_for_bit() -> None:
    """Lengths around the eight-way unroll and the 128-term halving, at offsets into a row, on
    squares (what the spread sums) of values over ten orders of magnitude."""
    rng = np.random.default_rng(0)
    for n in [*range(0, 40), 63, 64, 65, 127, 128, 129, 130, 255, 256, 257, 300, 1000, 4099]:
        for _ in range(20):
            row = rng.normal(size=n + 7) * 10.0 ** rng.uniform(-5, 5, size=n + 7)
            squares = row * row
            lo = int(rng.integers(0, 8))
            want = np.mean(squares[lo:lo + n]) if n else 0.0
            got = pairwise_sum(squares, lo, n) / n if n else 0.0
            assert got == want, (n, lo, got - want)
    # The same numbers summed one after the other differ often: the order is what is pinned.
    squares = rng.uniform(0, 1, 50) * 10.0 ** rng.uniform(-5, 5, 50)
    assert pairwise_sum(squares, 0, 50) == np.add.reduce(squares)


def test_a_part_exactly_at_the_limit_is_shown_and_one_without_a_distance_waits() -> None:
    """z-scores of exactly 1 in every coordinate: a mean of exactly 1, at a limit of one sigma, is
    far enough (>=); a part whose embedding is not a number has no distance and waits, as the numpy
    version's NaN comparisons made it."""
    sigmas = np.full((1, 4), 0.5)
    emb = np.array([[0, 0, 0, 0], [0.5, 0.5, 0.5, 0.5], [np.nan, 0, 0, 0], [3, 3, 3, 3]], dtype=np.float32)
    modes = np.zeros(4, dtype=np.int64)
    assert spread_order(emb, modes, sigmas, head=1, k=3, min_sigmas=1.0).tolist() == [0, 1, 3, 2]
    assert spread_order(emb, modes, sigmas, head=1, k=3, min_sigmas=1.0001).tolist() == [0, 3, 1, 2]


def test_the_kernel_runs_from_numbas_cache_in_a_new_process(tmp_path: Path) -> None:
    """Compiled in one process, loaded from the cache in the next (a recursive version of the sum
    crashed the second process): both print the same sums of rows past the halving length."""
    script = ("import numpy as np\n"
              "from service.suggest.spread_kernel import pairwise_sum, warm\n"
              "warm()\n"
              "a = np.arange(1, 1001, dtype=np.float64) ** 2 / 7\n"
              "print(repr(pairwise_sum(a, 0, 1000)), repr(pairwise_sum(a, 3, 300)))\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    runs = [subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True,
                           timeout=300) for _ in range(2)]
    for run in runs:
        assert run.returncode == 0, run.stderr[-2000:]
    assert any(tmp_path.rglob("*.nbi")), "the first run cached nothing"
    a = np.arange(1, 1001, dtype=np.float64) ** 2 / 7
    assert runs[0].stdout.split() == runs[1].stdout.split() == [repr(float(np.add.reduce(a))),
                                                               repr(float(np.add.reduce(a[3:303])))]
