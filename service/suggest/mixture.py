"""Exact log-likelihood of embeddings under g's Gaussian mixture (paper, Section 5.3, Eq. 1).

    log P(y | X) = log sum_k phi_k N(y | mu_k, diag(sigma_k^2))

computed with log-sum-exp over the modes so that sharp modes (sigma up to 0.05 in the paper)
do not underflow. The quadratic form is expanded into matrix products, so scoring C candidates
against K modes costs two (C, D) x (D, K) products instead of a (C, K, D) temporary.
"""

from __future__ import annotations

import numpy as np

_LOG_2PI = float(np.log(2.0 * np.pi))
# Smallest weight a mode can contribute; keeps log(phi) finite for modes g switched off.
_MIN_WEIGHT = 1e-30


def component_log_densities(y: np.ndarray, weights: np.ndarray, means: np.ndarray,
                            sigmas: np.ndarray) -> np.ndarray:
    """``log phi_k + log N(y_c | mu_k, sigma_k^2)`` for every candidate c and mode k.

    Shapes:
        y: (C, D) candidate embeddings.
        weights: (K,), means: (K, D), sigmas: (K, D) one query's mixture.
        returns: (C, K) float64.
    """
    assert y.ndim == 2 and means.ndim == 2 and y.shape[1] == means.shape[1], (
        f"expected y (C, D) and means (K, D), found {y.shape} and {means.shape}")
    assert sigmas.shape == means.shape and weights.shape == (means.shape[0],), (
        f"expected weights (K,) and sigmas {means.shape}, found {weights.shape} and {sigmas.shape}")
    y = y.astype(np.float64, copy=False)
    mu = means.astype(np.float64, copy=False)
    inv_var = 1.0 / np.square(sigmas.astype(np.float64, copy=False))  # (K, D)
    # sum_d (y_d - mu_kd)^2 / s_kd^2 = y^2 . iv_k - 2 y . (mu_k iv_k) + mu_k^2 . iv_k
    quad = (np.square(y) @ inv_var.T) - 2.0 * (y @ (mu * inv_var).T) + np.sum(mu * mu * inv_var, axis=1)
    quad = np.maximum(quad, 0.0)  # the expansion can dip below zero by rounding
    D = y.shape[1]
    log_norm = -0.5 * D * _LOG_2PI - np.sum(np.log(sigmas.astype(np.float64, copy=False)), axis=1)  # (K,)
    log_w = np.log(np.maximum(weights.astype(np.float64, copy=False), _MIN_WEIGHT))
    return log_w + log_norm - 0.5 * quad


def logsumexp_rows(a: np.ndarray) -> np.ndarray:
    """``log sum_k exp(a[:, k])`` row by row, stable for very negative entries.

    Shapes:
        a: (C, K) -> (C,).
    """
    m = a.max(axis=1, keepdims=True)
    return (m + np.log(np.exp(a - m).sum(axis=1, keepdims=True)))[:, 0]


def mixture_log_likelihood(y: np.ndarray, weights: np.ndarray, means: np.ndarray,
                           sigmas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Score candidates under one query's mixture and name the mode that explains each best.

    Shapes:
        y: (C, D); weights: (K,); means, sigmas: (K, D).
        returns: log-likelihoods (C,) float64 and best modes (C,) int64.
    """
    comp = component_log_densities(y, weights, means, sigmas)
    return logsumexp_rows(comp), comp.argmax(axis=1)


def sigma_distances(y: np.ndarray, means: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    """Root-mean-square distance of each embedding to each mode's mean, in that mode's standard
    deviations (1 = a typical draw from the mode; the unit of the assembly's and the service's
    "within so many sigmas" rules).

    Shapes:
        y (C, D), means (K, D), sigmas (K, D) -> (C, K) float64.
    """
    return _rms((np.asarray(y, np.float64)[:, None, :] - means[None]) / sigmas[None])   # (C, K, D)


def paired_sigma_distances(y: np.ndarray, means: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    """``sigma_distances`` of each embedding to one mode only, its own: row c of ``means`` and
    ``sigmas`` (the same numbers as that column of ``sigma_distances``, without the others').

    Shapes:
        y, means, sigmas (C, D) -> (C,) float64.
    """
    return _rms((np.asarray(y, np.float64) - means) / sigmas)


def _rms(z: np.ndarray) -> np.ndarray:
    """Root mean square over the last axis (z-scores to sigma distances)."""
    return np.sqrt(np.mean(z * z, axis=-1))
