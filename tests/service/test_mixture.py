"""The mixture log-likelihood against a direct evaluation with scipy."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import multivariate_normal

from service.suggest.mixture import (
    component_log_densities,
    logsumexp_rows,
    mixture_log_likelihood,
    paired_sigma_distances,
    sigma_distances,
)


def _mixture(rng: np.random.Generator, K: int, D: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    w = rng.random(K)
    return w / w.sum(), rng.normal(size=(K, D)), rng.uniform(0.2, 1.5, size=(K, D))


def test_matches_scipy_on_random_mixtures() -> None:
    rng = np.random.default_rng(0)
    w, mu, sigma = _mixture(rng, K=4, D=6)
    y = rng.normal(size=(30, 6))
    ll, mode = mixture_log_likelihood(y, w, mu, sigma)
    dens = np.stack([w[k] * multivariate_normal(mu[k], np.diag(sigma[k] ** 2)).pdf(y) for k in range(4)],
                    axis=1)
    np.testing.assert_allclose(ll, np.log(dens.sum(axis=1)), rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(mode, dens.argmax(axis=1))


def test_sharp_modes_do_not_underflow() -> None:
    # sigma = 0.05 in 50 dimensions (the paper's cap): densities far below float64's range.
    rng = np.random.default_rng(1)
    w, mu, _ = _mixture(rng, K=3, D=50)
    sigma = np.full((3, 50), 0.05)
    y = mu[1] + rng.normal(scale=2.0, size=(5, 50))
    ll, mode = mixture_log_likelihood(y, w, mu, sigma)
    assert np.all(np.isfinite(ll)) and np.all(ll < -1000)
    comp = component_log_densities(y, w, mu, sigma)
    # The log-sum-exp equals the largest component up to log(K).
    assert np.all(ll >= comp.max(axis=1)) and np.all(ll <= comp.max(axis=1) + np.log(3))
    np.testing.assert_array_equal(mode, comp.argmax(axis=1))


def test_a_mean_scores_higher_than_points_away_from_it() -> None:
    rng = np.random.default_rng(2)
    _, mu, sigma = _mixture(rng, K=2, D=8)
    y = np.stack([mu[0], mu[0] + 3 * sigma[0]])
    ll, mode = mixture_log_likelihood(y, np.array([0.9, 0.1]), mu, sigma)
    assert ll[0] > ll[1] and mode[0] == 0


def test_switched_off_modes_stay_finite() -> None:
    rng = np.random.default_rng(3)
    _, mu, sigma = _mixture(rng, K=3, D=4)
    ll, mode = mixture_log_likelihood(mu, np.array([1.0, 0.0, 0.0]), mu, sigma)
    assert np.all(np.isfinite(ll)) and np.all(mode == 0)


def test_logsumexp_rows() -> None:
    a = np.array([[0.0, 0.0], [-1000.0, -1000.0], [5.0, -np.inf]])
    np.testing.assert_allclose(logsumexp_rows(a), [np.log(2), -1000 + np.log(2), 5.0])


def test_sigma_distances_count_standard_deviations_of_each_mode() -> None:
    means = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    sigmas = np.array([[0.1, 0.1, 0.1], [0.5, 1.0, 2.0]])
    y = np.array([[0.1, -0.1, 0.1], [1.5, 2.0, 3.0], [0.0, 0.0, 0.0]])
    d = sigma_distances(y, means, sigmas)
    assert d.shape == (3, 2)
    assert d[0, 0] == pytest.approx(1.0) and d[1, 1] == pytest.approx(1.0)   # one sigma on every axis
    assert d[2, 0] == 0.0
    assert d[2, 1] == pytest.approx(np.sqrt((4 + 1 + 0.25) / 3))


def test_paired_sigma_distances_are_each_rows_own_column_bit_for_bit() -> None:
    """The service's unfamiliar-query check reads each candidate's distance to its own mode only:
    the same numbers as that column of ``sigma_distances`` (float32 embeddings and g's outputs, as
    served), so the warning's threshold judges them alike."""
    rng = np.random.default_rng(4)
    for _ in range(50):
        C, K, D = int(rng.integers(1, 120)), int(rng.integers(1, 9)), int(rng.integers(1, 70))
        y = (rng.normal(size=(C, D)) * 10.0 ** rng.uniform(-2, 3)).astype(np.float32)
        means = rng.normal(size=(K, D)).astype(np.float32)
        sigmas = rng.uniform(0.01, 0.3, size=(K, D)).astype(np.float32)
        own = rng.integers(0, K, C)
        full = sigma_distances(y, means, sigmas)[np.arange(C), own]
        assert np.array_equal(paired_sigma_distances(y, means[own], sigmas[own]), full)

