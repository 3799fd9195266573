"""Equation 1 against direct evaluations of the mixture density, and the triplet hinge (Equation 2)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.special import logsumexp
from scipy.stats import norm

from training.losses import (
    component_log_density,
    mixture_nll,
    placement_loss,
    relaxed_wta_pull,
    triplet_hinge,
    triplet_loss,
    wta_winners,
)


def _random_mixture(rng: np.random.Generator, b: int, k: int, d: int, spread: float):
    logits = rng.normal(size=(b, k))
    weights = np.exp(logits) / np.exp(logits).sum(1, keepdims=True)
    means = rng.normal(scale=spread, size=(b, k, d))
    sigmas = rng.uniform(0.01, 0.05, size=(b, k, d))
    return weights, means, sigmas


def _torch_nll(y, weights, means, sigmas) -> np.ndarray:
    return mixture_nll(torch.tensor(y, dtype=torch.float64), torch.log(torch.tensor(weights)),
                       torch.tensor(means), torch.log(torch.tensor(sigmas))).numpy()


def _direct_density_nll(y, weights, means, sigmas) -> np.ndarray:
    """-log sum_k phi_k prod_d N(y_d | mu, sigma): the density itself, multiplied out in float64."""
    dens = norm.pdf(y[:, None, :], loc=means, scale=sigmas).prod(axis=2)     # (B, K)
    with np.errstate(divide="ignore"):
        return -np.log((weights * dens).sum(axis=1))


def _scipy_logsumexp_nll(y, weights, means, sigmas) -> np.ndarray:
    """Reference in log space through scipy's norm.logpdf and logsumexp (not our code path)."""
    log_comp = norm.logpdf(y[:, None, :], loc=means, scale=sigmas).sum(axis=2) + np.log(weights)
    return -logsumexp(log_comp, axis=1)


def test_matches_the_direct_mixture_density_near_the_means():
    rng = np.random.default_rng(0)
    b, k, d = 6, 4, 5
    weights, means, sigmas = _random_mixture(rng, b, k, d, spread=0.05)
    # Points close to one of the means: the plain density is representable in float64.
    pick = rng.integers(0, k, size=b)
    y = means[np.arange(b), pick] + rng.normal(scale=0.02, size=(b, d))
    direct = _direct_density_nll(y, weights, means, sigmas)
    assert np.all(np.isfinite(direct))
    np.testing.assert_allclose(_torch_nll(y, weights, means, sigmas), direct, rtol=1e-9, atol=1e-9)


def test_large_distances_stay_finite_where_the_naive_density_underflows():
    rng = np.random.default_rng(1)
    b, k, d = 5, 8, 50
    weights, means, sigmas = _random_mixture(rng, b, k, d, spread=1.0)
    y = rng.normal(scale=3.0, size=(b, d))          # hundreds of sigmas from every mean
    naive = _direct_density_nll(y, weights, means, sigmas)
    assert np.all(np.isinf(naive)), "the case must be one where exp underflows"
    ours = _torch_nll(y, weights, means, sigmas)
    ref = _scipy_logsumexp_nll(y, weights, means, sigmas)
    assert np.all(np.isfinite(ours))
    assert ref.min() > 1e4                         # far beyond what exp can represent
    np.testing.assert_allclose(ours, ref, rtol=1e-10)


def test_float32_large_distance_gradients_are_finite():
    rng = np.random.default_rng(2)
    weights, means, sigmas = _random_mixture(rng, 4, 8, 50, spread=1.0)
    y = torch.tensor(rng.normal(scale=5.0, size=(4, 50)), dtype=torch.float32, requires_grad=True)
    mu = torch.tensor(means, dtype=torch.float32, requires_grad=True)
    e = mixture_nll(y, torch.log(torch.tensor(weights, dtype=torch.float32)), mu,
                    torch.log(torch.tensor(sigmas, dtype=torch.float32)))
    e.sum().backward()
    assert torch.isfinite(e).all()
    assert y.grad is not None and torch.isfinite(y.grad).all() and y.grad.abs().sum() > 0
    assert mu.grad is not None and torch.isfinite(mu.grad).all()


def test_single_mode_reduces_to_the_gaussian_negative_log_likelihood():
    y = np.array([[0.1, -0.2]])
    means = np.array([[[0.0, 0.0]]])
    sigmas = np.array([[[0.05, 0.02]]])
    expected = -(norm.logpdf(0.1, 0, 0.05) + norm.logpdf(-0.2, 0, 0.02))
    np.testing.assert_allclose(_torch_nll(y, np.ones((1, 1)), means, sigmas), [expected], rtol=1e-12)


def test_triplet_hinge_values():
    e_pos = torch.tensor([0.0, 5.0, -20.0, 3.0])
    e_neg = torch.tensor([0.0, 20.0, -15.0, 13.0])
    # m + E(X,Y) - E(X,Z), clipped at zero: 10, 0 (beyond the margin), 5, 0 (exactly at it)
    np.testing.assert_allclose(triplet_hinge(e_pos, e_neg, 10.0).numpy(), [10.0, 0.0, 5.0, 0.0])


def test_triplet_loss_pushes_the_positive_in_and_the_negative_out():
    rng = np.random.default_rng(3)
    weights, means, sigmas = _random_mixture(rng, 3, 2, 4, spread=0.1)
    y = torch.tensor(means[:, 0] + 0.01, dtype=torch.float32, requires_grad=True)
    z = torch.tensor(means[:, 0] + 0.012, dtype=torch.float32, requires_grad=True)
    loss, e_pos, e_neg = triplet_loss(y, z, torch.log(torch.tensor(weights, dtype=torch.float32)),
                                      torch.tensor(means, dtype=torch.float32),
                                      torch.log(torch.tensor(sigmas, dtype=torch.float32)), margin=10.0)
    assert loss.item() > 0 and e_pos.shape == (3,) and e_neg.shape == (3,)
    loss.backward()
    assert y.grad is not None and z.grad is not None
    step = 1e-5
    mix = (torch.log(torch.tensor(weights, dtype=torch.float32)), torch.tensor(means, dtype=torch.float32),
           torch.log(torch.tensor(sigmas, dtype=torch.float32)))
    with torch.no_grad():
        e_pos2 = mixture_nll(y - step * y.grad, *mix)
        e_neg2 = mixture_nll(z - step * z.grad, *mix)
    assert (e_pos2 < e_pos.detach()).all()
    assert (e_neg2 > e_neg.detach()).all()


def test_triplet_loss_is_zero_beyond_the_margin():
    means = torch.zeros(1, 1, 2)
    log_s = torch.log(torch.full((1, 1, 2), 0.05))
    y = torch.zeros(1, 2)
    z = torch.ones(1, 2)            # 20 sigmas away: E(X,Z) - E(X,Y) = 400 > m
    loss, e_pos, e_neg = triplet_loss(y, z, torch.zeros(1, 1), means, log_s, margin=10.0)
    assert loss.item() == 0.0
    assert (e_neg - e_pos).item() == pytest.approx(400.0, rel=1e-5)


def test_placement_loss_is_the_mean_squared_distance():
    pred = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]])
    target = torch.tensor([[0.0, 0.0, 1.0], [1.0, -1.0, 1.0]])
    assert placement_loss(pred, target).item() == pytest.approx((1.0 + 4.0) / 2)


def test_relaxed_wta_pull_weights_the_nearest_mode():
    means = torch.tensor([[[0.0, 0.0], [1.0, 1.0], [5.0, 5.0]]])
    log_s = torch.log(torch.full((1, 3, 2), 0.5))
    y = torch.tensor([[0.9, 1.1]])
    per_mode = -component_log_density(y, means, log_s)[0]
    got = relaxed_wta_pull(y, means, log_s, epsilon=0.1)
    expected = 0.9 * per_mode[1] + 0.05 * (per_mode[0] + per_mode[2])
    assert got.item() == pytest.approx(expected.item(), rel=1e-6)
    # epsilon 0: the nearest mode alone, and the mixture weights play no part.
    assert relaxed_wta_pull(y, means, log_s, 0.0).item() == pytest.approx(per_mode[1].item(), rel=1e-6)


def test_evolving_wta_pulls_the_nearest_modes_then_narrows_to_one():
    means = torch.tensor([[[0.0, 0.0], [1.0, 1.0], [5.0, 5.0]]])
    log_s = torch.log(torch.full((1, 3, 2), 0.5))
    y = torch.tensor([[0.9, 1.1]])
    per_mode = -component_log_density(y, means, log_s)[0]
    # Two winners share 1 - epsilon; the far mode keeps epsilon.
    got = relaxed_wta_pull(y, means, log_s, epsilon=0.1, winners=2)
    expected = 0.45 * (per_mode[1] + per_mode[0]) + 0.1 * per_mode[2]
    assert got.item() == pytest.approx(expected.item(), rel=1e-6)
    # Every mode a winner: the plain mean, whatever epsilon.
    assert relaxed_wta_pull(y, means, log_s, 0.1, winners=3).item() == pytest.approx(per_mode.mean().item())
    # The schedule: K modes at the start, one from the end of the anneal on, one throughout without it.
    assert [wta_winners(s, 1000, 8, 0.5) for s in (0, 250, 500, 900)] == [8, 4, 1, 1]
    assert wta_winners(0, 1000, 8, 0.0) == 1


def test_matched_modes_give_a_query_s_complements_distinct_modes():
    """Two complements both nearest to mode 0: WTA would pull mode 0 onto both, the matching
    gives the second to the next-best mode; a third query's single complement keeps its best."""
    from training.losses import matched_modes

    nll = torch.tensor([[1.0, 5.0, 9.0],     # query 0, complement a: best mode 0
                        [2.0, 3.0, 9.0],     # query 0, complement b: best mode 0 too
                        [9.0, 1.0, 2.0]])    # query 1: best mode 1
    owner = torch.tensor([0, 0, 1])
    assert matched_modes(nll, owner, 2).tolist() == [0, 1, 1]
    # More complements than modes: matched in rounds, every complement gets a mode.
    many = torch.rand(5, 2)
    got = matched_modes(many, torch.zeros(5, dtype=torch.int64), 1)
    assert got.shape == (5,) and sorted(got[:2].tolist()) == [0, 1]
