"""Summaries of latency samples: the percentiles every benchmark reports, in milliseconds."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def percentile(samples: Sequence[float] | np.ndarray, q: float) -> float:
    """The ``q``-th percentile (0-100) of the samples, linearly interpolated between ranks.

    Linear interpolation (numpy's default) so that p50 of an even count is the midpoint of the
    two middle samples; with N samples, p99 needs N >= 100 to be more than the maximum's
    neighbour, which is why the benchmarks' repetition counts are in the hundreds.
    """
    a = np.asarray(samples, dtype=np.float64)
    if a.ndim != 1 or len(a) == 0:
        raise ValueError(f"percentile needs a non-empty 1-D sequence of samples, found shape {a.shape}")
    if not 0.0 <= q <= 100.0:
        raise ValueError(f"percentile q must lie in [0, 100], found {q}")
    return float(np.percentile(a, q))


def summarize_seconds(samples: Sequence[float] | np.ndarray) -> dict[str, float]:
    """Count, mean, min, p50, p90, p99 and max of durations given in seconds, reported in ms."""
    a = np.asarray(samples, dtype=np.float64) * 1000.0
    if a.ndim != 1 or len(a) == 0:
        raise ValueError(f"no latency samples to summarise (shape {a.shape})")
    return {
        "n": len(a),
        "mean_ms": float(a.mean()),
        "min_ms": float(a.min()),
        "p50_ms": percentile(a, 50),
        "p90_ms": percentile(a, 90),
        "p99_ms": percentile(a, 99),
        "max_ms": float(a.max()),
    }
