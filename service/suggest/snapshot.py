"""The catalog one request reads from start to end: parts, their index and the search over them.

A ``CatalogSnapshot`` is immutable: a catalog write (``service.catalog_store.writer``) builds the
next one and the served object swaps its reference (``service.api.served``), so a request that
started on a snapshot finishes on it, and readers never wait for writers. The engine
(``service.suggest.engine``: networks, settings, caches) outlives every snapshot and is given the
one to read per call.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import faiss
import numpy as np

from service.artifacts.catalog import Catalog
from service.errors import InputError
from service.suggest.neighbours import CatalogSearch


@dataclass(frozen=True, eq=False)
class CatalogSnapshot:
    """One immutable catalog with its FAISS index (catalog row i = index row i) and its search."""

    catalog: Catalog
    index: faiss.Index
    search: CatalogSearch

    @classmethod
    def of(cls, catalog: Catalog, index: faiss.Index, brute_force_max_parts: int,
           exact_search_max_filtered: int) -> CatalogSnapshot:
        assert index.ntotal == len(catalog), (
            f"the index holds {index.ntotal} vectors, the catalog {len(catalog)} parts")
        return cls(catalog, index, CatalogSearch(catalog.embeddings, index, brute_force_max_parts,
                                                 exact_search_max_filtered))

    @cached_property
    def _category_masks(self) -> dict[int, np.ndarray]:
        return {}

    def category_mask(self, codes: list[int] | np.ndarray) -> np.ndarray:
        """Parts of the categories ``codes``: (P,) bool.

        One category's mask is made once per snapshot and returned read-only (the same array each
        time, so the search can keep its FAISS bitmap too): over 10M parts the comparison cost 3 ms
        of every request that names or infers a category. Masks of several categories are made
        per request (their combinations are the caller's to choose, so they are not kept).
        """
        key = sorted({int(c) for c in codes})
        if len(key) != 1:
            return np.isin(self.catalog.category_of, key)
        mask = self._category_masks.get(key[0])
        if mask is None:
            mask = self.catalog.category_of == key[0]
            mask.setflags(write=False)
            self._category_masks[key[0]] = mask
        return mask

    @cached_property
    def styles(self) -> np.ndarray:
        """Each part's catalog ``style`` ("" when it has none), read once per snapshot: (P,) str."""
        return np.array([str(r.get("style") or "") for r in self.catalog.records])

    def style_mask(self, styles: tuple[str, ...]) -> np.ndarray:
        """Parts whose style is one of ``styles``: (P,) bool; ``InputError`` naming unknown styles."""
        per_part = self.styles
        known = set(per_part.tolist()) - {""}
        unknown = [s for s in styles if s not in known]
        if unknown:
            raise InputError("unknown_style", f"unknown style(s) {', '.join(map(repr, unknown))}; known "
                             f"styles: {', '.join(sorted(known))}")
        return np.isin(per_part, list(styles))
