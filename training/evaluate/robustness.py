"""Robustness: Table 1 on queries perturbed the way real collections differ from the generator's.

The held-out queries come from the generator that made the training shapes; shapes nobody here
made differ in proportions, are modelled a little rotated, off centre or off scale, scanned with
noise or holes. Each all-but-one query is answered again after one such perturbation (its
strength about twice the training augmentation's range, ``data.sampling.Augmentation``, so it is
not only what the model has seen), with the category given (pool "category") and without it (pool
"all": the service infers the category), and scored like Table 1. Labels are read to measure only.

Each perturbation is seeded by (seed, query id, perturbation): re-running gives the same points.
"""

from __future__ import annotations

import dataclasses
import zlib
from collections.abc import Callable
from typing import Any

import numpy as np
from tqdm import tqdm

from training.data.sampling import Augmentation, augmentation_transform, punch_hole
from training.evaluate.baselines import Method
from training.evaluate.evaluation import RetrievalSettings, functional_scores
from training.evaluate.protocol import Query, ShapeIndex, candidate_pool, finalize_ranking

_NONE = Augmentation(axis_log_scale=0.0, yaw_degrees=0.0, frame_offset=0.0, frame_log_scale=0.0)


def _affine(ranges: Augmentation) -> Callable[[np.ndarray, np.random.Generator], np.ndarray]:
    """The training augmentation's linear map and offset (``augmentation_transform``), these ranges."""
    def apply(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        A, t = augmentation_transform(rng, 1.0, ranges)
        return (points @ A.T + t).astype(np.float32)
    return apply


def _noise(sigma: float) -> Callable[[np.ndarray, np.random.Generator], np.ndarray]:
    def apply(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return (points + rng.normal(0.0, sigma, points.shape)).astype(np.float32)
    return apply


def _hole(radius: float) -> Callable[[np.ndarray, np.random.Generator], np.ndarray]:
    def apply(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return punch_hole(points, rng, radius).astype(np.float32)
    return apply


# (name, what it does, the perturbation): each about twice the training augmentation's range.
_SINGLE: tuple[tuple[str, str, Callable[[np.ndarray, np.random.Generator], np.ndarray]], ...] = (
    ("proportions", "each axis rescaled by exp(U(-0.4, 0.4))",
     _affine(dataclasses.replace(_NONE, axis_log_scale=0.4))),
    ("rotated", "turned about the up axis by up to 15 degrees",
     _affine(dataclasses.replace(_NONE, yaw_degrees=15.0))),
    ("off frame", "moved by up to 0.1 per axis and rescaled by exp(U(-0.2, 0.2))",
     _affine(dataclasses.replace(_NONE, frame_offset=0.1, frame_log_scale=0.2))),
    ("noisy", "Gaussian noise of sigma 0.02 on every point", _noise(0.02)),
    ("holed", "the points within 0.3 of a random one replaced by others", _hole(0.3)),
)


def _everything(points: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    for _, _, apply in _SINGLE:
        points = apply(points, rng)
    return points


PERTURBATIONS: tuple[tuple[str, str, Callable[[np.ndarray, np.random.Generator], np.ndarray]], ...] = (
    ("as generated", "the held-out query as drawn", lambda points, rng: points),
    *_SINGLE,
    ("all of them", "the five above, one after the other", _everything),
)
POOLS = ("category", "all")


def perturbed(query: Query, name: str, seed: int) -> Query:
    """``query`` with its points perturbed by the named perturbation (seeded by the query and the name).

    Shapes:
        query.points (N, 3) -> the same count, float32.
    """
    apply = next((f for n, _, f in PERTURBATIONS if n == name), None)
    if apply is None:
        raise ValueError(f"unknown perturbation {name!r}; known: {', '.join(n for n, _, _ in PERTURBATIONS)}")
    rng = np.random.default_rng([seed, zlib.crc32(query.qid.encode()), zlib.crc32(name.encode())])
    return dataclasses.replace(query, points=apply(np.asarray(query.points, dtype=np.float32), rng))


def evaluate_robustness(method: Method, queries: list[Query], index: ShapeIndex, settings: RetrievalSettings,
                        seed: int, progress: bool = False) -> list[dict[str, Any]]:
    """Functional AP@k and the in-category share of each all-but-one query under every
    perturbation, with either pool: one record per (query, perturbation, pool)."""
    group = index.catalog.group if settings.collapse_duplicates else None
    k = settings.top_k
    out: list[dict[str, Any]] = []
    for q in tqdm(queries, desc=f"{method.name} robustness", disable=not progress, leave=False):
        pools = {scope: candidate_pool(index, q.shape_id, q.category, scope) for scope in POOLS}
        for name, _, _ in PERTURBATIONS:
            moved = perturbed(q, name, seed)
            for scope, pool in pools.items():
                top = finalize_ranking(method.rank(moved, pool, k), pool, group, k)
                out.append({"qid": q.qid, "category": q.category, "perturbation": name, "pool": scope,
                            **functional_scores(index, q, pool, top, group, k)})
    return out
