"""Large catalogs made from the real one: embeddings replicated with seeded noise, and a
``Catalog`` of that size that the real engine can search, score and place with.

A replica of part ``i`` is part ``i mod P`` (P real parts) moved in embedding space by Gaussian
noise of ``noise`` times each dimension's standard deviation (copy 0 of every part is exact, so
the real catalog is contained). The catalog's per-part arrays (embeddings, placement features,
boxes, duplicate groups) are full-size arrays of the large catalog, so the engine's gathers from
them cost what they would in a real catalog of that size; only meshes and point samples, read
per chosen part, are looked up in the real part's rows.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, cast, overload

import numpy as np

from service.artifacts.catalog import Catalog


def replicate_embeddings(base: np.ndarray, n: int, noise: float, seed: int) -> np.ndarray:
    """``n`` rows: ``base`` tiled, every copy after the first jittered (seeded).

    Args:
        base: the real catalog's embeddings.
        n: rows wanted (any n >= 1; the last copy may be partial).
        noise: Gaussian noise per dimension, as a fraction of that dimension's std in ``base``.
        seed: seed of the noise.

    Shapes:
        base: (P, D) -> (n, D) float32; row i is a copy of base row i mod P.
    """
    base = np.ascontiguousarray(base, dtype=np.float32)
    if base.ndim != 2 or len(base) == 0:
        raise ValueError(f"base embeddings must be a non-empty (P, D) array, found shape {base.shape}")
    if n < 1:
        raise ValueError(f"n must be at least 1, found {n}")
    P, D = base.shape
    reps = -(-n // P)
    out = np.tile(base, (reps, 1))[:n]
    if n > P and noise > 0:
        rng = np.random.default_rng(seed)
        scale = (noise * base.std(axis=0)).astype(np.float32)
        out[P:] += rng.standard_normal((n - P, D), dtype=np.float32) * scale
    return np.ascontiguousarray(out)


class _ReplicaRecords(Sequence[dict[str, Any]]):
    """Catalog records of the replicated catalog, made on access (a replica's own part id)."""

    def __init__(self, base: list[dict[str, Any]], part_ids: list[str]):
        self._base = base
        self._ids = part_ids

    def __len__(self) -> int:
        return len(self._ids)

    @overload
    def __getitem__(self, i: int) -> dict[str, Any]: ...
    @overload
    def __getitem__(self, i: slice) -> list[dict[str, Any]]: ...

    def __getitem__(self, i: int | slice) -> dict[str, Any] | list[dict[str, Any]]:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        if i < 0:
            i += len(self)
        if not 0 <= i < len(self):
            raise IndexError(f"record {i} out of range for a catalog of {len(self)} parts")
        rec = self._base[i % len(self._base)]
        return rec if i < len(self._base) else {**rec, "part_id": self._ids[i]}


class ReplicatedCatalog(Catalog):
    """A catalog of ``len(embeddings)`` parts built on a real ``base`` catalog (row i: part i mod P).

    Replicas of a real part keep its duplicate group (they are geometrically identical, which is
    what the catalog's near-duplicate groups mean), so duplicate collapse shows distinct parts.
    ``points``, ``mesh_vertices`` and friends stay the base catalog's arrays; ``part_points``,
    ``part_samples`` and ``mesh`` map a row back to its real part.

    Shapes (n parts):
        embeddings: (n, D) float32; part_features: (n, Fp) float32 (tiled, real memory).
    """

    def __init__(self, base: Catalog, embeddings: np.ndarray):
        n, P = len(embeddings), len(base)
        if embeddings.ndim != 2 or embeddings.shape[1] != base.embeddings.shape[1]:
            raise ValueError(f"embeddings must have shape (n, {base.embeddings.shape[1]}), "
                             f"found {embeddings.shape}")
        self.base = base
        reps = -(-n // P)
        rows = np.arange(n) % P

        def tile(a: np.ndarray) -> np.ndarray:
            return np.ascontiguousarray(np.tile(a, (reps,) + (1,) * (a.ndim - 1))[:n])

        ids = [*base.part_ids, *(f"{base.part_ids[i % P]}~{i // P}" for i in range(P, n))][:n]
        self.records = cast(list[dict[str, Any]], _ReplicaRecords(base.records, ids))
        self.embeddings = np.ascontiguousarray(embeddings, dtype=np.float32)
        self.part_features = tile(base.part_features)
        self.points = base.points
        self.mesh_vertices, self.mesh_faces = base.mesh_vertices, base.mesh_faces
        self.vertex_first, self.face_first = base.vertex_first, base.face_first
        self.part_ids = ids
        self.index_of = {pid: i for i, pid in enumerate(ids)}
        self.categories, self.shape_ids = base.categories, base.shape_ids
        self.category_of, self.shape_of = tile(base.category_of), tile(base.shape_of)
        self.translations, self.bbox_min, self.bbox_max = (tile(base.translations), tile(base.bbox_min),
                                                           tile(base.bbox_max))
        self.group = base.group[rows]
        self.group_size = np.bincount(self.group, minlength=n)[self.group]
        missing = [f.name for f in dataclasses.fields(Catalog) if not hasattr(self, f.name)]
        if missing:  # Catalog gained fields this replica does not fill: refuse rather than mislead
            raise TypeError(f"ReplicatedCatalog does not set Catalog field(s) {', '.join(missing)}; "
                            "update bench/replicate.py")

    def mesh(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        return self.base.mesh(int(i) % len(self.base))

    def part_points(self, i: int) -> np.ndarray:
        return self.base.part_points(int(i) % len(self.base))

    def part_samples(self, rows: np.ndarray, n: int) -> np.ndarray:
        return self.base.part_samples(np.asarray(rows, dtype=np.int64) % len(self.base), n)
