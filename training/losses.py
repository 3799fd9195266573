"""Losses: the mixture negative log-likelihood (Equation 1), the triplet hinge (Equation 2) and
the placement regression.

Equation 1 is evaluated in the log-sum-exp form of the paper's Appendix: with 50 dimensions and
sigmas of at most 0.05, the density of an embedding a few units from every mean is far below the
smallest float (exp(-1e4)), so a direct ``log(sum(phi * N))`` would return ``inf``. Note the
Appendix prints ``- log sigma`` inside the sum over dimensions; the Gaussian's normaliser gives
``+ log sigma`` there (``-log N = (y - mu)^2 / (2 sigma^2) + log sigma + log(2 pi) / 2``), which
is what is implemented.
"""

from __future__ import annotations

import math

import torch


def component_log_density(y: torch.Tensor, means: torch.Tensor, log_sigmas: torch.Tensor) -> torch.Tensor:
    """Log density of ``y`` under each diagonal Gaussian of a mixture.

    Shapes:
        y (B, D), means (B, K, D), log_sigmas (B, K, D) -> (B, K).
    """
    d = y.shape[-1]
    z = (y.unsqueeze(1) - means) * torch.exp(-log_sigmas)             # (B, K, D)
    return -(0.5 * z.square() + log_sigmas).sum(dim=-1) - 0.5 * d * math.log(2.0 * math.pi)


def mixture_nll(y: torch.Tensor, log_weights: torch.Tensor, means: torch.Tensor,
                log_sigmas: torch.Tensor) -> torch.Tensor:
    """E(X, Y) of Equation 1: ``-log sum_k phi_k N(y | mu_k, sigma_k^2)``, one value per row.

    ``torch.logsumexp`` subtracts the per-row maximum before exponentiating (the Appendix's
    trick), so rows whose every component density underflows still get a finite value and
    gradient.

    Shapes:
        y (B, D), log_weights (B, K), means (B, K, D), log_sigmas (B, K, D) -> (B,).
    """
    return -torch.logsumexp(log_weights + component_log_density(y, means, log_sigmas), dim=1)


def relaxed_wta_pull(y: torch.Tensor, means: torch.Tensor, log_sigmas: torch.Tensor,
                     epsilon: float, winners: int = 1) -> torch.Tensor:
    """Pull the Gaussians nearest to each positive onto it (relaxed winner-takes-all).

    The per-mode negative log density of ``y`` is averaged with weight ``(1 - epsilon) /
    winners`` on each of the ``winners`` best modes and ``epsilon / (K - winners)`` on the
    others. Unlike the mixture NLL it ignores the mixture weights, so it cannot win by moving
    all weight to one central mode. ``winners > 1`` is the evolving winner-takes-all of Makansi
    et al. (CVPR 2019): starting with every mode pulled and narrowing to one keeps all modes
    near the data, where plain WTA leaves the modes that never win far away for good.

    Shapes:
        y (B, D), means (B, K, D), log_sigmas (B, K, D) -> (B,).
    """
    nll = -component_log_density(y, means, log_sigmas)                 # (B, K)
    k = nll.shape[1]
    top = min(max(winners, 1), k)
    if top == k:
        return nll.mean(dim=1)
    best = nll.topk(top, dim=1, largest=False).indices                  # (B, top)
    w = torch.full_like(nll, epsilon / (k - top)).scatter(1, best, (1.0 - epsilon) / top)
    return (w * nll).sum(dim=1)


def wta_winners(step: int, steps: int, n_modes: int, anneal: float) -> int:
    """How many modes the evolving winner-takes-all pulls at ``step``: from K down to 1 over
    the first ``anneal`` share of the run (1 throughout when ``anneal`` is 0)."""
    if anneal <= 0:
        return 1
    progress = min(step / (anneal * steps), 1.0)
    return max(1, round(n_modes - (n_modes - 1) * progress))


def triplet_hinge(e_pos: torch.Tensor, e_neg: torch.Tensor, margin: float | torch.Tensor) -> torch.Tensor:
    """Equation 2 per triplet: ``max(m + E(X, Y) - E(X, Z), 0)``.

    Shapes:
        e_pos (B,), e_neg (B,), margin () or (B,) -> (B,).
    """
    return torch.clamp(margin + e_pos - e_neg, min=0.0)


def triplet_loss(y_emb: torch.Tensor, z_emb: torch.Tensor, log_weights: torch.Tensor, means: torch.Tensor,
                 log_sigmas: torch.Tensor, margin: float | torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Mean triplet hinge over a batch, plus the per-triplet energies (for logging and accuracy).

    Shapes:
        y_emb (B, D), z_emb (B, D), mixture as in ``mixture_nll``, margin () or (B,)
        -> loss (), e_pos (B,), e_neg (B,).
    """
    e_pos = mixture_nll(y_emb, log_weights, means, log_sigmas)
    e_neg = mixture_nll(z_emb, log_weights, means, log_sigmas)
    return triplet_hinge(e_pos, e_neg, margin).mean(), e_pos, e_neg


def placement_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared error of predicted translations (squared distance, averaged over the batch).

    Shapes:
        pred (B, 3), target (B, 3) -> ().
    """
    return (pred - target).square().sum(dim=1).mean()


def matched_modes(nll: torch.Tensor, owner: torch.Tensor, n_queries: int) -> torch.Tensor:
    """Each query's complements matched one-to-one to modes, by least total per-mode NLL.

    The set version of winner-takes-all: where WTA lets one central mode win every complement
    of a query (and the others die), the matching gives a query's different complements
    different modes (Hungarian assignment per query; a query with more complements than modes
    reuses modes in rounds).

    Shapes:
        nll (M, K) per-mode NLL of every complement, owner (M,) its query -> (M,) int64 mode.
    """
    from scipy.optimize import linear_sum_assignment

    cost = nll.detach().cpu().numpy()
    rows_of = owner.cpu().numpy()
    out = torch.empty(len(cost), dtype=torch.int64)
    k = cost.shape[1]
    for q in range(n_queries):
        rows = (rows_of == q).nonzero()[0]
        for start in range(0, len(rows), k):     # rounds of at most K complements
            chunk = rows[start:start + k]
            r, c = linear_sum_assignment(cost[chunk])
            out[torch.as_tensor(chunk[r])] = torch.as_tensor(c, dtype=torch.int64)
    return out.to(nll.device)
