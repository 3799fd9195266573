"""Fixed (not learned) geometric descriptors of point clouds, for the baselines.

The benchmark's baselines need a hand-crafted descriptor where the paper used MVCNN features
(the fixed-embedding ablation) and the global descriptor of Chaudhuri and Koltun 2010 (CK10).
We use classic, documented shape-distribution descriptors computed from surface samples:

* D2 (Osada, Funkhouser, Chazelle, Dobkin 2002, "Shape distributions"): histogram of the
  distance between random pairs of surface points, 32 bins over [0, 2] (the unit-radius frame's
  largest possible distance).
* A3 (same paper): histogram of the angle at the middle point of random point triples, 16 bins
  over [0, pi].
* D1 / radial: histogram of the distance of each point to the centroid, 16 bins over [0, 1.5].
* Angular: histograms of the elevation (angle to the +y up axis) and of the azimuth around y of
  the directions from the centroid, 8 bins each (the frame is canonical, so orientation is
  informative, unlike in Osada's rotation-invariant setting).
* Extents: the axis-aligned bounding-box extents (3) and the square roots of the PCA
  eigenvalues, largest first (3).

Histograms are L1-normalised; nothing is scale-normalised, because all points live in the
unit-radius frame of their shape and a part's size is part of what makes it compatible.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

D2_BINS, D2_RANGE = 32, (0.0, 2.0)
A3_BINS = 16
D1_BINS, D1_RANGE = 16, (0.0, 1.5)
ANGLE_BINS = 8
DESCRIPTOR_DIM = D2_BINS + A3_BINS + D1_BINS + 2 * ANGLE_BINS + 6

DESCRIPTOR_NAME = ("D2 distance histogram (32) + A3 angle histogram (16) + radial D1 histogram (16) + "
                   "elevation/azimuth histograms (8 + 8) + bounding-box extents (3) + PCA extents (3)")


def _histogram(values: np.ndarray, bins: int, lo: float, hi: float) -> np.ndarray:
    h, _ = np.histogram(np.clip(values, lo, hi - 1e-9), bins=bins, range=(lo, hi))
    total = h.sum()
    return (h / total if total else h).astype(np.float64)


def point_descriptor(points: np.ndarray, n_pairs: int = 4096, seed: int = 0) -> np.ndarray:
    """Descriptor of one point cloud (see the module docstring for its blocks).

    Args:
        points: surface samples in the unit-radius frame (centred or not: D2 and A3 do not
            depend on position; radial and angular blocks are taken about the centroid).
        n_pairs: random pairs (and triples) drawn for D2 and A3.
        seed: seed of those draws, so a descriptor is a pure function of its inputs.

    Shapes:
        points (n, 3) -> (DESCRIPTOR_DIM,) float64.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 3:
        raise ValueError(f"a descriptor needs an (n >= 3, 3) point array, got shape {p.shape}")
    rng = np.random.default_rng(seed)
    i, j, k = (rng.integers(0, len(p), size=n_pairs) for _ in range(3))
    d2 = np.linalg.norm(p[i] - p[j], axis=1)
    u, v = p[i] - p[j], p[k] - p[j]
    nu, nv = np.linalg.norm(u, axis=1), np.linalg.norm(v, axis=1)
    ok = (nu > 1e-9) & (nv > 1e-9)
    cos = np.einsum("ij,ij->i", u[ok], v[ok]) / (nu[ok] * nv[ok])
    a3 = np.arccos(np.clip(cos, -1.0, 1.0))
    centroid = p.mean(axis=0)
    rel = p - centroid
    r = np.linalg.norm(rel, axis=1)
    dirs = rel[r > 1e-9] / r[r > 1e-9, None]
    elevation = np.arccos(np.clip(dirs[:, 1], -1.0, 1.0))
    azimuth = np.arctan2(dirs[:, 2], dirs[:, 0])
    extents = p.max(axis=0) - p.min(axis=0)
    eig = np.sort(np.clip(np.linalg.eigvalsh(np.cov(rel.T)), 0.0, None))[::-1]
    return np.concatenate([
        _histogram(d2, D2_BINS, *D2_RANGE),
        _histogram(a3, A3_BINS, 0.0, np.pi),
        _histogram(r, D1_BINS, *D1_RANGE),
        _histogram(elevation, ANGLE_BINS, 0.0, np.pi),
        _histogram(azimuth, ANGLE_BINS, -np.pi, np.pi),
        extents,
        np.sqrt(eig),
    ])


def descriptors(point_sets: np.ndarray | list[np.ndarray], n_pairs: int = 4096, seed: int = 0) -> np.ndarray:
    """``point_descriptor`` of many point clouds, each with the same seed (deterministic).

    Shapes:
        point_sets (P, n, 3) or a list of (n_i, 3) -> (P, DESCRIPTOR_DIM) float64.
    """
    out = np.empty((len(point_sets), DESCRIPTOR_DIM), dtype=np.float64)
    for row, pts in enumerate(point_sets):
        out[row] = point_descriptor(np.asarray(pts, dtype=np.float64), n_pairs=n_pairs, seed=seed)
    return out


@dataclass
class Standardizer:
    """Per-feature z-score with statistics of a reference set; constant features get unit scale.

    Shapes:
        mean (F,), std (F,); transform(x (Q, F)) -> (Q, F).
    """

    mean: np.ndarray
    std: np.ndarray

    @classmethod
    def fit(cls, x: np.ndarray) -> Standardizer:
        x = np.asarray(x, dtype=np.float64)
        std = x.std(axis=0)
        return cls(mean=x.mean(axis=0), std=np.where(std > 1e-12, std, 1.0))

    def transform(self, x: np.ndarray) -> np.ndarray:
        return (np.asarray(x, dtype=np.float64) - self.mean) / self.std


@dataclass
class PCAProjection:
    """PCA of standardised descriptors to ``dim`` dimensions, fitted on a reference set.

    The projection is not whitened (the paper projects MVCNN features with plain PCA); all
    coordinates are multiplied by one ``scale`` so the embedding can be given the spread the
    retrieval network's sigma limits were tuned for.

    Shapes:
        components (dim, F), centre (F,); transform(x (Q, F)) -> (Q, dim) float32.
    """

    standardizer: Standardizer
    centre: np.ndarray
    components: np.ndarray
    scale: float
    explained_variance_ratio: float

    @property
    def dim(self) -> int:
        return int(self.components.shape[0])

    @classmethod
    def fit(cls, x: np.ndarray, dim: int, scale: float = 1.0) -> PCAProjection:
        x = np.asarray(x, dtype=np.float64)
        if dim <= 0:
            raise ValueError(f"PCA dimension must be positive, got {dim}")
        if len(x) < 2:
            raise ValueError(f"PCA needs at least two reference descriptors, got {len(x)}")
        standardizer = Standardizer.fit(x)
        z = standardizer.transform(x)
        centre = z.mean(axis=0)
        _, s, vt = np.linalg.svd(z - centre, full_matrices=False)
        keep = min(dim, vt.shape[0])
        # Fewer features than ``dim`` (or a rank-deficient reference): pad with zero axes so the
        # output always has ``dim`` columns, as the retrieval network expects.
        components = np.zeros((dim, x.shape[1]))
        components[:keep] = vt[:keep]
        var = s**2
        explained = float(var[:keep].sum() / var.sum()) if var.sum() > 0 else 1.0
        return cls(standardizer=standardizer, centre=centre, components=components, scale=float(scale),
                   explained_variance_ratio=explained)

    def rescaled(self, scale: float) -> PCAProjection:
        return PCAProjection(self.standardizer, self.centre, self.components, float(scale),
                             self.explained_variance_ratio)

    def transform(self, x: np.ndarray) -> np.ndarray:
        z = self.standardizer.transform(x) - self.centre
        return (self.scale * (z @ self.components.T)).astype(np.float32)
