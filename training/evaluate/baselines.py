"""The methods the benchmark compares "Ours" with: Random, CK10 and the fixed embedding.

Every method answers two questions about a query (see ``Method``): a ranking of candidate
catalog rows, best first, and a score per given row (higher is better) for full rankings. The
protocol then filters every ranking through the same candidate pool and duplicate collapse
(``protocol.finalize_ranking``), so no method can see the query's own shape.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from service.artifacts.catalog import Catalog
from training.evaluate.descriptors import DESCRIPTOR_NAME, Standardizer, descriptors
from training.evaluate.protocol import Query, ShapeIndex, sample_rows, stable_code


class Method(Protocol):
    """A retrieval method under test."""

    name: str
    # Whether ``scores`` of a row depends on that row alone (not on its source shape). Only such
    # methods get the exact-component recall, where the removed part is put back into the pool:
    # CK10 scores a part through its source shape, which for that part is the query itself.
    per_part_scores: bool

    def rank(self, query: Query, pool: np.ndarray, k: int) -> np.ndarray:
        """Catalog rows best first; at least the best ``k`` of ``pool`` (other rows may appear)."""
        ...

    def scores(self, query: Query, rows: np.ndarray) -> np.ndarray:
        """One score per row, higher is better. Shapes: rows (p,) -> (p,) float64."""
        ...


def rank_by_scores(scores: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Rows sorted by descending score, ties broken by row index (deterministic).

    Shapes:
        scores (p,), rows (p,) -> (p,) int64.
    """
    rows = np.asarray(rows, dtype=np.int64)
    return rows[np.lexsort((rows, -np.asarray(scores, dtype=np.float64)))]


class ScoredMethod:
    """A method whose ranking is its scores sorted over the pool."""

    name = "scored"
    per_part_scores = True

    def scores(self, query: Query, rows: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def rank(self, query: Query, pool: np.ndarray, k: int) -> np.ndarray:
        return rank_by_scores(self.scores(query, pool), pool)


class RandomMethod(ScoredMethod):
    """Uniformly random candidates: one seeded random score per (query, catalog row)."""

    name = "Random"
    description = "uniformly random parts of the candidate pool (a seeded random score per query and part)"

    def __init__(self, n_parts: int, seed: int):
        self.n_parts = n_parts
        self.seed = seed

    def scores(self, query: Query, rows: np.ndarray) -> np.ndarray:
        per_row = np.random.default_rng([self.seed, stable_code(query.qid)]).random(self.n_parts)
        return per_row[np.asarray(rows, dtype=np.int64)]


class CK10Method:
    """Chaudhuri and Koltun 2010, as the paper describes it: similar shapes, dissimilar parts.

    1. Every catalog shape gets a global descriptor of its complete surface (``n_points``
       area-weighted samples of all its parts); the query gets the descriptor of its points.
       Shapes are ranked by the Euclidean distance of standardised descriptors to the query's.
    2. Every part gets the same descriptor of its own (centred) samples; a candidate's
       dissimilarity is its distance to the nearest part already in the query.
    3. The ranking lists the parts of the ``n_shapes`` most similar shapes first, most
       dissimilar first, then the parts of the other shapes by shape similarity and then
       dissimilarity.

    The query's own shape is never in the pool, so step 1 ranks only other shapes.
    """

    name = "CK10"
    per_part_scores = False

    def __init__(self, index: ShapeIndex, n_shapes: int = 5, n_points: int = 1000, seed: int = 0,
                 n_pairs: int = 4096):
        if n_shapes <= 0:
            raise ValueError(f"CK10 needs n_shapes >= 1, got {n_shapes}")
        cat: Catalog = index.catalog
        self.index = index
        self.n_shapes = n_shapes
        self.n_pairs = n_pairs
        self.seed = seed
        self.description = (f"global descriptor of the complete shape, then the {n_shapes} most similar "
                            "shapes' parts ranked by distance to the nearest query part; descriptor: "
                            f"{DESCRIPTOR_NAME}, standardised per feature")
        part_desc = index.part_descriptors(n_pairs)
        self.part_std = Standardizer.fit(part_desc)
        self.part_desc = self.part_std.transform(part_desc)
        shape_points = [sample_rows(index, index.rows[sid], n_points,
                                    np.random.default_rng([seed, stable_code(sid)])) for sid in cat.shape_ids]
        shape_desc = descriptors(shape_points, n_pairs=n_pairs)
        self.shape_std = Standardizer.fit(shape_desc)
        self.shape_desc = self.shape_std.transform(shape_desc)      # row = shape code

    def _keys(self, query: Query, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Shape distance and part dissimilarity of each row (for rows of other shapes)."""
        cat = self.index.catalog
        qdesc = self.shape_std.transform(descriptors([query.points], n_pairs=self.n_pairs))[0]
        shape_dist = np.linalg.norm(self.shape_desc - qdesc, axis=1)        # (n_shapes,)
        present = self.part_desc[query.present]                              # (r, F)
        diff = self.part_desc[rows][:, None, :] - present[None]
        dissim = np.linalg.norm(diff, axis=2).min(axis=1)                    # (p,)
        return shape_dist[cat.shape_of[rows]], dissim

    def rank(self, query: Query, pool: np.ndarray, k: int) -> np.ndarray:
        pool = np.asarray(pool, dtype=np.int64)
        sdist, dissim = self._keys(query, pool)
        codes = self.index.catalog.shape_of[pool]
        # Shape order by distance (ties by shape code), over the shapes present in the pool.
        shapes = np.unique(codes)
        shape_d = np.array([sdist[codes == s][0] for s in shapes])
        order = shapes[np.lexsort((shapes, shape_d))]
        shape_rank = np.empty(codes.max() + 1, dtype=np.int64)
        shape_rank[order] = np.arange(len(order))
        srank = shape_rank[codes]
        top = srank < self.n_shapes
        bucket_rank = np.where(top, 0, srank)
        return pool[np.lexsort((pool, -dissim, bucket_rank))]

    def scores(self, query: Query, rows: np.ndarray) -> np.ndarray:
        """Minus the position in ``rank`` over ``rows`` (CK10 has no per-part score of its own)."""
        rows = np.asarray(rows, dtype=np.int64)
        ranked = self.rank(query, rows, len(rows))
        pos = np.empty(len(rows), dtype=np.float64)
        where = {int(r): i for i, r in enumerate(ranked.tolist())}
        for i, r in enumerate(rows.tolist()):
            pos[i] = -where[r]
        return pos
