"""Kinds of parts, read from the catalog's own shapes: what a complete object of a category holds.

The assembly's "complete" rule compares likelihoods under g, and g can be content with less than
the data usually has: after a seat and a leg set of another shape its mixture offers more legs
and seats, and a back at weight 0.04-0.08 (docs/modeling.md). The data's shapes say more: most of
the chairs whose parts are like the placed ones have a back. This module turns that into numbers
without labels:

* a *kind* is a connected component of the graph that links a category's parts whose embeddings
  (f's, the catalog's) lie within ``distance`` of each other: parts that complement the same
  partial assemblies lie close, so a category's seats of every style form one kind, its backs one
  or two (``part_kinds``);
* the *nearest shapes* of a set of placed parts are the sampled training shapes of the category
  that hold the kinds of the largest share of the placed parts (a stool's legs lead to the stools,
  a chair's legs to the chairs);
* a *wanted kind* is one that at least ``min_share`` of the nearest shapes hold and no placed
  part has (``wanted_kinds``).

Labels are never read: kinds come from the embeddings, shapes from the catalog's shape ids.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from service.artifacts.catalog import Catalog, split_shapes

# Rows of the pairwise distance matrix computed at a time (bounds the memory of ``part_kinds``).
_CHUNK = 512


@dataclass(frozen=True)
class KindTable:
    """The kinds of one category's parts and the kinds each sampled training shape holds.

    Shapes:
        kind_of: (P,) int64 over the whole catalog: a part's kind, -1 outside the category or
            farther than the linking distance from every sampled part.
        shape_kinds: (S, K) bool: kinds held by each sampled training shape.
    """

    kind_of: np.ndarray
    shape_kinds: np.ndarray

    @property
    def kinds(self) -> int:
        return int(self.shape_kinds.shape[1])


def part_kinds(embeddings: np.ndarray, distance: float) -> np.ndarray:
    """The connected components of the graph linking embeddings closer than ``distance``.

    Shapes:
        embeddings: (n, D) -> (n,) int64 component ids in [0, components).
    """
    e = np.asarray(embeddings, dtype=np.float64)
    n = len(e)
    if n == 0:
        return np.zeros(0, np.int64)
    sq = np.einsum("nd,nd->n", e, e)
    rows, cols = [], []
    for a in range(0, n, _CHUNK):
        d2 = sq[a:a + _CHUNK, None] + sq[None] - 2.0 * (e[a:a + _CHUNK] @ e.T)     # (chunk, n)
        i, j = np.nonzero(d2 < distance * distance)
        rows.append(i + a)
        cols.append(j)
    r, c = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(r), np.int8), (r, c)), shape=(n, n))
    _, comp = connected_components(graph, directed=False)
    return comp.astype(np.int64)


def kind_table(catalog: Catalog, category: str, distance: float, max_shapes: int, seed: int = 0) -> KindTable:
    """The kinds of ``category``'s parts, linked over at most ``max_shapes`` of its training shapes
    (a seeded draw, as ``own_cover_shares``); every other part of the category takes the kind of
    its nearest sampled part when that lies within ``distance`` (else -1)."""
    code = catalog.category_codes([category])[0]
    shapes = [rows for _, rows in sorted(split_shapes(catalog, "train").items())
              if catalog.category_of[rows[0]] == code]
    if len(shapes) > max_shapes:
        pick = np.random.default_rng(seed).choice(len(shapes), size=max_shapes, replace=False)
        shapes = [shapes[j] for j in np.sort(pick)]
    kind_of = np.full(len(catalog), -1, np.int64)
    if not shapes:
        return KindTable(kind_of, np.zeros((0, 0), bool))
    sampled = np.concatenate([np.asarray(rows, np.int64) for rows in shapes])
    emb = catalog.embeddings
    comp = part_kinds(emb[sampled], distance)
    kind_of[np.flatnonzero(catalog.category_of == code)] = _nearest_kind(
        emb[catalog.category_of == code], emb[sampled], comp, distance)
    kind_of[sampled] = comp
    shape_kinds = np.zeros((len(shapes), int(comp.max()) + 1), bool)
    start = 0
    for s, rows in enumerate(shapes):
        shape_kinds[s, comp[start:start + len(rows)]] = True
        start += len(rows)
    return KindTable(kind_of, shape_kinds)


def _nearest_kind(x: np.ndarray, ref: np.ndarray, ref_kind: np.ndarray, distance: float) -> np.ndarray:
    """Each row of ``x``'s nearest reference's kind, -1 when that lies ``distance`` or farther.

    Shapes:
        x: (n, D), ref: (m, D), ref_kind: (m,) -> (n,) int64.
    """
    x = np.asarray(x, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    out = np.full(len(x), -1, np.int64)
    sq_ref = np.einsum("md,md->m", ref, ref)
    for a in range(0, len(x), _CHUNK):
        xa = x[a:a + _CHUNK]
        d2 = np.einsum("nd,nd->n", xa, xa)[:, None] + sq_ref[None] - 2.0 * (xa @ ref.T)
        j = np.argmin(d2, axis=1)
        near = d2[np.arange(len(xa)), j] < distance * distance
        out[a:a + _CHUNK] = np.where(near, ref_kind[j], -1)
    return out


def wanted_kinds(table: KindTable, placed: np.ndarray, min_share: float) -> list[tuple[int, float]]:
    """The kinds that at least ``min_share`` of the placed parts' nearest shapes hold and no placed
    part has, with that share, most shared first (see the module doc).

    Shapes:
        placed: (n,) int64 the placed parts' kinds (-1: none, a part no shape explains).
    """
    placed = np.asarray(placed, dtype=np.int64)
    known = placed[placed >= 0]
    if len(known) == 0 or table.shape_kinds.size == 0:
        return []
    # Each shape's share of the placed parts whose kind it holds (a part of no kind counts as
    # held by none).
    explained = table.shape_kinds[:, known].sum(axis=1) / len(placed)                  # (S,)
    near = explained >= explained.max()
    share = table.shape_kinds[near].mean(axis=0)                                        # (K,)
    share[known] = 0.0
    order = np.argsort(-share, kind="stable")
    return [(int(k), float(share[k])) for k in order if share[k] >= min_share]
