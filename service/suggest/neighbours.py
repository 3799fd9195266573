"""The search of the request path: the catalog parts nearest each mixture mean (``CatalogSearch``).

Exact nearest catalog parts by brute force in numpy, for catalogs a flat index would serve.

The engine needs, per query, the parts among the ``nn`` nearest of any of its mixture means (the
candidates it then re-scores by likelihood). On the shipped catalog (7,315 parts, 50-D) FAISS's
flat search spends its time in per-row heaps, not in distances: 8 means, top 64, took about
1.0 ms, and 256 means (a batch of 32 queries) 24 ms. One matrix product, one ``np.partition``
per row and a threshold give the same parts (ties included) in 0.23 ms and 5.5 ms.

A category the snapshot keeps a mask for (named or inferred: most requests) is searched over its
own columns of the embedding matrix, cut once per snapshot and category: masking all 8,300
columns and partitioning them cost about 0.9 ms per request, the category's ninth 0.1 ms.

Squared L2 distances are ``|x|^2 - 2 m.x`` (the ``|m|^2`` term does not change any row's order);
for an inner-product index the nearest parts are those of largest ``m.x``.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import faiss
import numpy as np

# Read-only filter masks (one per category of the snapshot) whose FAISS bitmaps are kept.
FILTERS_KEPT = 64


class _PerKeptMask:
    """Data derived from a read-only mask (one a snapshot keeps: ``CatalogSnapshot.category_mask``),
    made once and kept beside it, keyed by the array's identity and holding a reference so the
    identity stays its own (at most ``FILTERS_KEPT`` masks). Writeable masks are made per call.
    """

    def __init__(self, make: Callable[[np.ndarray], Any]):
        self._make = make
        self._kept: dict[int, tuple[np.ndarray, Any]] = {}
        self._lock = threading.Lock()

    def __call__(self, mask: np.ndarray) -> Any:
        if mask.flags.writeable:
            return self._make(mask)
        kept = self._kept.get(id(mask))
        if kept is None or kept[0] is not mask:
            kept = (mask, self._make(mask))
            with self._lock:
                if len(self._kept) >= FILTERS_KEPT:
                    self._kept.pop(next(iter(self._kept)))
                self._kept[id(mask)] = kept
        return kept[1]

    def __len__(self) -> int:
        return len(self._kept)


class BruteForceNeighbours:
    """The union of each query's means' ``nn`` nearest parts, over a fixed embedding matrix."""

    def __init__(self, embeddings: np.ndarray, inner_product: bool = False):
        emb = np.asarray(embeddings, dtype=np.float32)
        self._transposed = np.ascontiguousarray(emb.T)  # (D, P): the product reads it row by row
        self._sq_norms = None if inner_product else np.einsum("pd,pd->p", emb, emb)
        self.size = len(emb)
        # A kept mask's rows, their columns of the transposed embeddings and their squared norms:
        # an inferred category is a ninth of the shipped catalog, and searching its columns alone
        # is that much less work than masking all of them (the answer is the same).
        self._subsets = _PerKeptMask(self._cut)

    def _cut(self, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        rows = np.flatnonzero(allowed)
        return (rows, np.ascontiguousarray(self._transposed[:, rows]),
                None if self._sq_norms is None else self._sq_norms[rows])

    def neighbour_union(self, means: np.ndarray, modes: int, nn: int,
                        allowed: np.ndarray | None = None) -> list[np.ndarray]:
        """Distinct rows within the ``nn`` nearest parts of any of each query's ``modes`` means.

        Rows with ``allowed`` False are never returned. Parts tied with the ``nn``-th distance are
        all kept, so a query may get a few more than ``nn`` per mean.

        Shapes:
            means: (Q * modes, D), each query's means consecutive; allowed: (P,) bool.
            returns: Q sorted int64 arrays.
        """
        queries = len(means) // modes
        if allowed is not None and not allowed.flags.writeable:
            rows, transposed, sq_norms = self._subsets(allowed)
            products = np.asarray(means, dtype=np.float32) @ transposed  # (Q * modes, allowed)
            return [rows[f] for f in _union(products, sq_norms, queries, modes, nn, None)]
        dist = np.asarray(means, dtype=np.float32) @ self._transposed  # (Q * modes, P)
        return _union(dist, self._sq_norms, queries, modes, nn, allowed)


def _union(dist: np.ndarray, sq_norms: np.ndarray | None, queries: int, modes: int, nn: int,
           allowed: np.ndarray | None) -> list[np.ndarray]:
    """``BruteForceNeighbours.neighbour_union`` from the products ``dist`` (turned into distances
    in place): each query's columns within the ``nn`` nearest of any of its means, ties kept.

    Shapes:
        dist: (Q * modes, P) means . embeddings; sq_norms: (P,) or None (inner product);
        allowed: (P,) bool or None -> Q sorted int64 arrays of columns.
    """
    if sq_norms is None:
        np.negative(dist, out=dist)
    else:
        dist *= -2.0
        dist += sq_norms
    available = dist.shape[1]
    if allowed is not None:
        dist[:, ~allowed] = np.inf
        available = int(allowed.sum())
    nn = min(nn, available)
    if nn == 0 or queries == 0:
        return [np.zeros(0, np.int64) for _ in range(queries)]
    kth = np.partition(dist, nn - 1, axis=1)[:, nn - 1:nn]  # (Q * modes, 1)
    near = np.any((dist <= kth).reshape(queries, modes, -1), axis=1)  # (Q, P)
    if allowed is not None:
        near &= allowed  # an all-inf row (nn == available) must not admit filtered parts
    return [np.flatnonzero(row).astype(np.int64) for row in near]


class CatalogSearch:
    """The nearest catalog parts of mixture means, over one catalog's embeddings and index.

    numpy brute force (``BruteForceNeighbours``) for a flat index over at most
    ``brute_force_max_parts`` parts; else FAISS (for millions of parts a compressed index whose
    shortlist is re-ranked exactly, ``service.artifacts.indexing``), with a filter as an ID
    selector, or an exact search over the allowed rows when they are few.
    """

    def __init__(self, embeddings: np.ndarray, index: faiss.Index, brute_force_max_parts: int,
                 exact_search_max_filtered: int):
        self.embeddings = embeddings
        self.index = index
        self.exact_search_max_filtered = exact_search_max_filtered
        small = len(embeddings) <= brute_force_max_parts
        inner = index.metric_type == faiss.METRIC_INNER_PRODUCT
        self.brute_force = (BruteForceNeighbours(embeddings, inner_product=inner)
                            if small and isinstance(index, faiss.IndexFlat) else None)
        # A kept mask's count and FAISS bitmap (see _filter).
        self._filters = _PerKeptMask(
            lambda m: (int(np.count_nonzero(m)), np.packbits(m, bitorder="little")))

    def neighbour_union(self, means: np.ndarray, modes: int, nn: int,
                        allowed: np.ndarray | None = None) -> list[np.ndarray]:
        """Distinct allowed rows among the ``nn`` nearest parts of any of each query's ``modes`` means.

        Shapes:
            means: (Q * modes, D) float32, each query's means consecutive; allowed: (P,) bool.
            returns: Q int64 arrays of distinct catalog rows.
        """
        if self.brute_force is not None:
            return self.brute_force.neighbour_union(means, modes, nn, allowed)
        labels = self._faiss_search(means, nn, allowed)
        found = []
        for j in range(len(means) // modes):
            ids = labels[j * modes:(j + 1) * modes].ravel()
            ids = np.unique(ids[ids >= 0])
            if allowed is not None:
                ids = ids[allowed[ids]]  # also covers indexes that ignore selectors
            found.append(ids)
        return found

    def _faiss_search(self, x: np.ndarray, nn: int, allowed: np.ndarray | None) -> np.ndarray:
        """FAISS labels (Q, nn) of the nearest parts, restricted to ``allowed`` rows if given."""
        if allowed is None:
            return self.index.search(x, nn)[1]
        # Counted, not listed: listing the allowed rows of 10M parts cost 7 ms per request.
        count, packed = self._filter(allowed)
        if count <= self.exact_search_max_filtered and (
                count < len(allowed) // 2 or not isinstance(self.index, faiss.IndexFlat)):
            # An approximate index probes the lists (or graph nodes) nearest the query, and few of
            # them may hold parts that pass a narrow filter; a flat index with a selector checks
            # every part one by one (1.1 ms for a category of the shipped catalog, against 0.1 ms
            # for the same search over that category's rows): search those parts exactly instead.
            return self._exact_subset(x, nn, np.flatnonzero(allowed))
        sel = faiss.IDSelectorBitmap(len(allowed), faiss.swig_ptr(packed))
        params = _search_parameters(self.index, sel)
        if params is None:  # an index type without selector support: filter afterwards
            return self.index.search(x, min(len(self.embeddings), 4 * nn))[1]
        return self.index.search(x, nn, params=params)[1]

    def _filter(self, allowed: np.ndarray) -> tuple[int, np.ndarray]:
        """The allowed rows' count and FAISS bitmap (little-endian bits).

        A read-only mask is one the snapshot keeps (a category's): its count and bitmap are kept
        beside it (``_PerKeptMask``; over 10M parts, packing the bitmap cost about 2 ms of every
        filtered request). Other masks are packed per call.
        """
        count, packed = self._filters(allowed)
        return count, packed

    def _exact_subset(self, x: np.ndarray, nn: int, rows: np.ndarray) -> np.ndarray:
        """Exact nearest catalog rows among ``rows``: labels (Q, nn), -1 past the subset's size."""
        out = np.full((len(x), nn), -1, dtype=np.int64)
        if len(rows) == 0:
            return out
        k = min(nn, len(rows))
        sub = np.ascontiguousarray(self.embeddings[rows], dtype=np.float32)
        _, found = faiss.knn(x, sub, k, metric=self.index.metric_type)
        out[:, :k] = np.where(found >= 0, rows[np.maximum(found, 0)], -1)
        return out


def _search_parameters(index: faiss.Index, sel: faiss.IDSelector) -> faiss.SearchParameters | None:
    """Search parameters carrying an ID selector, of the kind this index type expects."""
    params: Any
    if isinstance(index, faiss.IndexRefine):  # the selector goes to the base; the re-rank keeps it
        base = _search_parameters(faiss.downcast_index(index.base_index), sel)
        if base is None:
            return None
        params = faiss.IndexRefineSearchParameters()
        params.base_index_params = base
        params.k_factor = index.k_factor
        params.referenced_objects = [base]  # SWIG keeps a raw pointer: keep ``base`` alive with it
        return params
    if isinstance(index, faiss.IndexPreTransform):  # e.g. zero-padding before an SQ8 IVF
        inner = _search_parameters(faiss.downcast_index(index.index), sel)
        if inner is None:
            return None
        params = faiss.SearchParametersPreTransform()
        params.index_params = inner
        params.referenced_objects = [inner]
        return params
    if isinstance(index, faiss.IndexIVF):
        # Search parameters replace the index's own: left at their defaults, a filtered search
        # probed 1 list (nprobe) or kept 16 graph candidates (efSearch), not the tuned breadth.
        params = faiss.SearchParametersIVF()
        params.nprobe = index.nprobe
        params.max_codes = index.max_codes
    elif isinstance(index, faiss.IndexHNSW):
        params = getattr(faiss, "SearchParametersHNSW")()  # noqa: B009  (missing from faiss's stubs)
        params.efSearch = index.hnsw.efSearch
    elif isinstance(index, faiss.IndexFlat):
        params = faiss.SearchParameters()
    else:
        return None
    params.sel = sel
    return params
