"""Percentiles and summaries of latency samples."""

from __future__ import annotations

import numpy as np
import pytest

from bench.stats import percentile, summarize_seconds


def test_percentile_interpolates_between_ranks() -> None:
    assert percentile([4.0, 1.0, 3.0, 2.0], 50) == 2.5
    assert percentile(np.arange(101.0), 99) == 99.0
    assert percentile(np.arange(11.0), 95) == pytest.approx(9.5)
    assert percentile([7.0], 99) == 7.0


def test_percentile_rejects_empty_and_out_of_range() -> None:
    with pytest.raises(ValueError, match="non-empty"):
        percentile([], 50)
    with pytest.raises(ValueError, match=r"\[0, 100\]"):
        percentile([1.0], 101)


def test_summary_is_in_milliseconds() -> None:
    s = summarize_seconds([0.001] * 98 + [0.010, 0.020])
    assert s["n"] == 100
    assert s["p50_ms"] == pytest.approx(1.0)
    assert s["min_ms"] == pytest.approx(1.0)
    assert s["max_ms"] == pytest.approx(20.0)
    assert s["mean_ms"] == pytest.approx((98 * 1 + 10 + 20) / 100)
    assert 10.0 < s["p99_ms"] < 20.0  # between the two slow samples, interpolated
    with pytest.raises(ValueError, match="no latency samples"):
        summarize_seconds([])
