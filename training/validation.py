"""Validation on held-out shapes: triplet accuracy, label precision@k and placement error.

Triplet accuracy plateaus below 1 because a negative drawn from another shape is often a valid
complement too; label precision@k is the main signal: for a held-out partial assembly, rank every
catalog part of *other* shapes by the mixture likelihood and count how many of the top k carry
the label (and category) of one of the query's true complements. Labels are read here only,
never by training.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from service.suggest.mixture import mixture_log_likelihood
from training.data.processed import ProcessedDataset
from training.data.sampling import TripletSampler, sample_assembly, sample_part
from training.losses import mixture_nll
from training.models import PlacementNet, RetrievalPair
from training.split import subset_components


@dataclass
class ValidationSet:
    """Fixed held-out triplets and the catalog their queries are ranked against.

    Shapes:
        X, Y, Z (T, N, 3) float32; translation (T, 3) float32; query_shape (T,) int64 (global
        shape index); relevant (T,) object, each a set of (category, label) pairs of the query's
        true complements; catalog_points (C, N, 3) float32 (every component of the dataset);
        catalog_shape (C,) int64; catalog_key (C,) object, (category, label) per component.
    """

    X: np.ndarray
    Y: np.ndarray
    Z: np.ndarray
    translation: np.ndarray
    query_shape: np.ndarray
    relevant: list[set[tuple[str, str]]]
    catalog_points: np.ndarray
    catalog_shape: np.ndarray
    catalog_key: list[tuple[str, str | None]]


def build_validation_set(ds: ProcessedDataset, test_shapes: np.ndarray, n_triplets: int, n_points: int,
                         seed: int) -> ValidationSet:
    """Draw ``n_triplets`` triplets from the test shapes and sample every component once."""
    rng = np.random.default_rng([seed, 7919])
    test = ds.subset(test_shapes)
    to_global = subset_components(ds, test_shapes)
    sampler = TripletSampler(test, n_points=n_points)
    adj = sampler.adj
    X = np.empty((n_triplets, n_points, 3), np.float32)
    Y = np.empty_like(X)
    Z = np.empty_like(X)
    T = np.empty((n_triplets, 3), np.float32)
    query_shape = np.empty(n_triplets, np.int64)
    relevant: list[set[tuple[str, str]]] = []
    for i in range(n_triplets):
        t = sampler.sample_triplet(rng)
        X[i] = sample_assembly(test, t.query, n_points, rng)
        Y[i] = sample_part(test, t.positive, n_points, rng)
        Z[i] = sample_part(test, t.negative, n_points, rng)
        T[i] = test.translation[t.positive]
        query_shape[i] = int(test_shapes[t.shape])
        complements = set().union(*(adj[c] for c in t.query)) - set(t.query)
        cat = str(ds.shapes[query_shape[i]]["category"])
        labels = {ds.component_label(int(to_global[c])) for c in complements}
        relevant.append({(cat, lab) for lab in labels if lab is not None})
    catalog_points = np.stack([sample_part(ds, c, n_points, rng) for c in range(ds.n_components)])
    catalog_key = [(str(ds.shapes[int(ds.shape_of[c])]["category"]), ds.component_label(c))
                   for c in range(ds.n_components)]
    return ValidationSet(X=X, Y=Y, Z=Z, translation=T, query_shape=query_shape, relevant=relevant,
                         catalog_points=catalog_points, catalog_shape=ds.shape_of.astype(np.int64),
                         catalog_key=catalog_key)


@torch.no_grad()
def _batched(fn: Callable[..., Any], arrays: tuple[np.ndarray, ...], chunk: int = 256) -> list[torch.Tensor]:
    outs: list[list[torch.Tensor]] = []
    n = len(arrays[0])
    for start in range(0, n, chunk):
        res = fn(*(torch.from_numpy(a[start:start + chunk]) for a in arrays))
        res = res if isinstance(res, tuple) else (res,)
        outs.append(list(res))
    return [torch.cat([o[i] for o in outs]) for i in range(len(outs[0]))]


def mixture_nll_matrix(parts: np.ndarray, log_weights: np.ndarray, means: np.ndarray,
                       log_sigmas: np.ndarray) -> np.ndarray:
    """E(X_b, part_c) for every query b and part c, in float64: the service's exact mixture
    log-likelihood (``service.suggest.mixture``, the one owner of the formula), negated.

    Shapes:
        parts (C, D); log_weights (B, K); means, log_sigmas (B, K, D) -> (B, C).
    """
    weights, sigmas = np.exp(log_weights.astype(np.float64)), np.exp(log_sigmas.astype(np.float64))
    return -np.stack([mixture_log_likelihood(parts, weights[b], means[b], sigmas[b])[0]
                      for b in range(means.shape[0])])


def label_precision(nll: np.ndarray, vset: ValidationSet, k: int) -> tuple[float, float, int]:
    """Label precision@k and category precision@k of the ranked catalog, own shape excluded.

    Returns (label precision, category precision, number of queries scored); queries whose
    complements carry no label are skipped.
    """
    label_hits, cat_hits, scored = 0.0, 0.0, 0
    for b in range(nll.shape[0]):
        if not vset.relevant[b]:
            continue
        scores = nll[b].copy()
        scores[vset.catalog_shape == vset.query_shape[b]] = np.inf
        top = np.argpartition(scores, k)[:k]
        cat = next(iter(vset.relevant[b]))[0]
        label_hits += sum(vset.catalog_key[c] in vset.relevant[b] for c in top.tolist()) / k
        cat_hits += sum(vset.catalog_key[c][0] == cat for c in top.tolist()) / k
        scored += 1
    if scored == 0:
        return float("nan"), float("nan"), 0
    return label_hits / scored, cat_hits / scored, scored


@torch.no_grad()
def validate(pair: RetrievalPair | None, placement: PlacementNet | None, vset: ValidationSet, margin: float,
             k: int = 5) -> dict[str, float]:
    """All validation metrics of the current networks (switched to eval mode and back)."""
    metrics: dict[str, float] = {}
    if pair is not None:
        was_training = pair.training
        pair.eval()
        log_w, means, log_s = _batched(pair.g.forward_log, (vset.X,))
        y_emb, z_emb = _batched(pair.f, (vset.Y,))[0], _batched(pair.f, (vset.Z,))[0]
        e_pos = mixture_nll(y_emb, log_w, means, log_s)
        e_neg = mixture_nll(z_emb, log_w, means, log_s)
        metrics["triplet_accuracy"] = float((e_pos < e_neg).float().mean())
        metrics["triplet_loss"] = float(torch.clamp(margin + e_pos - e_neg, min=0).mean())
        catalog = _batched(pair.f, (vset.catalog_points,))[0].numpy()
        nll = np.concatenate([
            mixture_nll_matrix(catalog, log_w[s:s + 64].numpy(), means[s:s + 64].numpy(),
                               log_s[s:s + 64].numpy())
            for s in range(0, len(vset.X), 64)])
        lp, cp, scored = label_precision(nll, vset, k)
        metrics[f"label_precision_at_{k}"] = lp
        metrics[f"category_precision_at_{k}"] = cp
        metrics["precision_queries"] = float(scored)
        metrics["mean_sigma"] = float(torch.exp(log_s).mean())
        # Modes of weight >= 0.05 per query: 1 means the mixture has collapsed.
        metrics["live_modes"] = float((torch.exp(log_w) >= 0.05).sum(dim=1).float().mean())
        pair.train(was_training)
    if placement is not None:
        was_training = placement.training
        placement.eval()
        pred = _batched(placement, (vset.X, vset.Y))[0].numpy()
        err = np.linalg.norm(pred - vset.translation, axis=1)
        metrics["placement_mean_error"] = float(err.mean())
        metrics["placement_median_error"] = float(np.median(err))
        placement.train(was_training)
    return metrics
