"""Whether a partial assembly looks like anything the model was trained on.

g's category head and the distance of the best suggestion from its mode cannot tell a shape of
no known category from a known one: a torus is "watercraft 0.95", a cube "chair 0.95", and both
lie as close to their modes as held-out chairs do. What does tell them apart is g's answer as a
whole: the *descriptor* of a query (its K mixture means, flattened, and the log of its K
weights) lies near the descriptors of training partial assemblies when the query is like them,
and far from all of them when it is not. The check is a nearest-neighbour distance to a bank of
training descriptors, shipped with the model (``familiarity.npz``), against a threshold
calibrated on the bank itself: the ``quantile`` of each bank descriptor's distance to its
nearest neighbour from *another* shape (a new shape of a known kind).

The bank is kept in its principal subspace (``Projection``: the first 64 of 408 components hold
99% of its variance): at full width it was 6.3 MB of float32 that every request streamed from
memory, 0.8 ms of the engine's 3.5; projected it is 1 MB.

Measured through the engine on the 24,000-step model shipped before the current two-stage one
(``docs/training.md``, "Unfamiliar shapes"; the two-stage model warns as often in a like-for-like
count, "A warm restart"):
with the 0.99 quantile, 0.2% of 1,678 held-out lone parts, 0.2% of 648 held-out partial
assemblies and 55% of 33 shapes of no category (balls, spheres, tori, cubes, plates, cylinders,
cones, capsules, helices, noise, box clusters at three sizes) are past the threshold; 79% with the
model shipped before it, whose g told them apart better.
"""

from __future__ import annotations

import numpy as np

# Weight below which log(phi) stops mattering: a dead mode is dead whatever its exact weight.
_MIN_WEIGHT = 1e-6


def mixture_descriptor(weights: np.ndarray, means: np.ndarray) -> np.ndarray:
    """g's answer for each query as one vector: its means flattened, then its log weights.

    Shapes:
        weights: (B, K), means: (B, K, D) -> (B, K * D + K) float32.
    """
    w = np.asarray(weights, dtype=np.float32)
    m = np.asarray(means, dtype=np.float32)
    assert w.ndim == 2 and m.ndim == 3 and m.shape[:2] == w.shape, (
        f"expected weights (B, K) and means (B, K, D), found {w.shape} and {m.shape}")
    log_w = np.log(np.maximum(w, _MIN_WEIGHT))
    return np.ascontiguousarray(np.concatenate([m.reshape(len(m), -1), log_w], axis=1), dtype=np.float32)


class Projection:
    """Descriptors onto the bank's principal subspace: ``(d - mean) @ components.T``.

    Shapes:
        mean: (F,); components: (P, F) orthonormal rows.
    """

    def __init__(self, mean: np.ndarray, components: np.ndarray):
        self.mean = np.ascontiguousarray(mean, dtype=np.float32)
        self.components = np.ascontiguousarray(components, dtype=np.float32)
        if self.components.ndim != 2 or self.mean.shape != (self.components.shape[1],):
            raise ValueError(f"a projection needs mean (F,) and components (P, F), found "
                             f"{self.mean.shape} and {self.components.shape}")

    @classmethod
    def fit(cls, descriptors: np.ndarray, dim: int) -> Projection:
        """The first ``dim`` principal components of ``descriptors`` (B, F)."""
        d = np.asarray(descriptors, dtype=np.float64)
        mean = d.mean(axis=0)
        _, _, vt = np.linalg.svd(d - mean, full_matrices=False)
        return cls(mean, vt[:min(dim, len(vt))])

    def __call__(self, descriptors: np.ndarray) -> np.ndarray:
        """(Q, F) -> (Q, P) float32."""
        return (np.asarray(descriptors, dtype=np.float32) - self.mean) @ self.components.T


def _squared_distances(queries: np.ndarray, bank: np.ndarray, bank_sq: np.ndarray) -> np.ndarray:
    """(Q, F) x (B, F) -> (Q, B) squared L2 distances, clipped at 0 (the expansion rounds)."""
    q = np.asarray(queries, dtype=np.float32)
    d2 = np.einsum("qf,qf->q", q, q)[:, None] - 2.0 * (q @ bank.T) + bank_sq[None]
    return np.maximum(d2, 0.0)


def calibrate_threshold(descriptors: np.ndarray, groups: np.ndarray, quantile: float) -> float:
    """The ``quantile`` of each descriptor's distance to its nearest one of another group.

    ``groups`` are the source shapes: descriptors of one shape are near each other, and what the
    threshold must admit is a new shape of a kind the bank has.

    Shapes:
        descriptors: (B, F); groups: (B,) -> float.
    """
    bank = np.asarray(descriptors, dtype=np.float32)
    groups = np.asarray(groups)
    if len(bank) < 2 or len(np.unique(groups)) < 2:
        raise ValueError("calibration needs descriptors of at least two shapes")
    if not 0 < quantile <= 1:
        raise ValueError(f"quantile must be in (0, 1], found {quantile}")
    sq = np.einsum("bf,bf->b", bank, bank)
    nearest = np.empty(len(bank), dtype=np.float64)
    for start in range(0, len(bank), 1024):  # (1024, B) blocks: bounded memory for large banks
        d2 = _squared_distances(bank[start:start + 1024], bank, sq)
        d2[groups[start:start + 1024, None] == groups[None]] = np.inf
        nearest[start:start + 1024] = np.sqrt(d2.min(axis=1))
    return float(np.quantile(nearest, quantile))


class FamiliarityCheck:
    """Nearest-bank-descriptor distances of queries, and whether they pass the threshold.

    ``descriptors``: the bank, projected when ``projection`` is given (queries are projected
    the same way before their distances are measured).
    """

    def __init__(self, descriptors: np.ndarray, threshold: float, projection: Projection | None = None):
        bank = np.ascontiguousarray(descriptors, dtype=np.float32)
        if bank.ndim != 2 or len(bank) == 0:
            raise ValueError(f"the familiarity bank must be a non-empty (B, F) array, found {bank.shape}")
        if not (np.isfinite(threshold) and threshold > 0):
            raise ValueError(f"the familiarity threshold must be a positive number, found {threshold!r}")
        if projection is not None and projection.components.shape[0] != bank.shape[1]:
            raise ValueError(f"the bank has {bank.shape[1]} columns, the projection "
                             f"{projection.components.shape[0]} components")
        self.bank = bank
        self.threshold = float(threshold)
        self.projection = projection
        self._sq = np.einsum("bf,bf->b", bank, bank)

    @property
    def dim(self) -> int:
        """Width of the descriptors queried (before any projection)."""
        return int(self.bank.shape[1] if self.projection is None else self.projection.mean.shape[0])

    def distances(self, descriptors: np.ndarray) -> np.ndarray:
        """Distance of each query descriptor to its nearest bank descriptor.

        Shapes:
            descriptors: (Q, F) -> (Q,) float64.
        """
        d = np.asarray(descriptors, dtype=np.float32)
        assert d.ndim == 2 and d.shape[1] == self.dim, f"expected (Q, {self.dim}), found {d.shape}"
        if self.projection is not None:
            d = self.projection(d)
        return np.sqrt(_squared_distances(d, self.bank, self._sq).min(axis=1)).astype(np.float64)
