"""Large catalogs made from the real one: embeddings replicated with seeded noise, and a
``Catalog`` of that size that the real engine can search, score and place with.

A replica of part ``i`` is part ``i mod P`` (P real parts) moved in embedding space by Gaussian
noise of ``noise`` times each dimension's standard deviation (copy 0 of every part is exact, so
the real catalog is contained). The catalog's per-part arrays (embeddings, placement features,
boxes, duplicate groups) are full-size arrays of the large catalog, so the engine's gathers from
them cost what they would in a real catalog of that size; only meshes and point samples, read
per chosen part, are looked up in the real part's rows.

Up to a million parts those arrays are made in memory. For ten million they would not fit one
worker (embeddings 2 GB, placement features 5 GB as float16): ``write_replica_arrays`` writes
each as an uncompressed ``.npy`` file, block by block, and ``open_replica_arrays`` memory-maps
them read-only, so a worker holds in its own memory only what it computes, and reads a part's
rows from the page cache when a request gathers them. Part ids and the id -> row lookup are
computed on access (``{real id}~{copy}``), not held as 10M strings and a 10M-entry dict.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
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
    out = np.empty((n, base.shape[1]), np.float32)
    for start, block in _embedding_blocks(base, n, noise, seed, block_rows=n):
        out[start:start + len(block)] = block
    return out


def _embedding_blocks(base: np.ndarray, n: int, noise: float, seed: int, block_rows: int
                      ) -> Iterator[tuple[int, np.ndarray]]:
    """``replicate_embeddings``' rows in blocks of at most ``block_rows``: (first row, block).

    The noise is drawn from one generator in row order, so any block size gives the same rows.
    """
    P, D = base.shape
    rng = np.random.default_rng(seed)
    scale = (noise * base.std(axis=0)).astype(np.float32)
    for start in range(0, n, block_rows):
        rows = np.arange(start, min(n, start + block_rows))
        block = base[rows % P]
        jittered = rows >= P
        if noise > 0 and jittered.any():
            block[jittered] += rng.standard_normal((int(jittered.sum()), D), dtype=np.float32) * scale
        yield start, block


# The per-part arrays of a replicated catalog, with the dtype each is stored in (placement
# features as float16, as catalog.npz stores them: h's head gets them as float32).
REPLICA_ARRAYS = {"embeddings": np.float32, "part_features": np.float16, "translations": np.float32,
                  "bbox_min": np.float32, "bbox_max": np.float32, "category_of": np.int32,
                  "shape_of": np.int32, "group": np.int64, "group_size": np.int64}
_META = "replica.json"


def write_replica_arrays(base: Catalog, n: int, noise: float, seed: int, folder: Path,
                         progress: Callable[[Iterable[int]], Iterable[int]] | None = None,
                         block_rows: int = 250_000) -> None:
    """Write the ``n``-part replicated catalog's per-part arrays as ``.npy`` files in ``folder``.

    Row i holds real part ``i mod P``'s values (embeddings jittered as ``replicate_embeddings``
    makes them, the same rows). ``replica.json`` is written last: a folder without it is
    incomplete. ``progress`` wraps the iterable of block offsets (e.g. tqdm).

    Files (n parts): ``{name}.npy`` for each of ``REPLICA_ARRAYS``, shapes as in ``Catalog``.
    """
    folder.mkdir(parents=True, exist_ok=True)
    (folder / _META).unlink(missing_ok=True)
    P = len(base)
    sources = {"part_features": base.part_features, "translations": base.translations,
               "bbox_min": base.bbox_min, "bbox_max": base.bbox_max, "category_of": base.category_of,
               "shape_of": base.shape_of, "group": base.group}
    # Copies of a real part stay in its group: a group counts every copy of its members.
    group_size = _copies_of_group(base, n)
    out = {name: np.lib.format.open_memmap(folder / f"{name}.npy", mode="w+", dtype=dtype,
                                           shape=(n, *_row_shape(base, name)))
           for name, dtype in REPLICA_ARRAYS.items()}
    blocks = _embedding_blocks(base.embeddings, n, noise, seed, block_rows)
    starts: Iterable[int] = range(0, n, block_rows)
    for start in (progress(starts) if progress is not None else starts):
        first, emb = next(blocks)
        assert first == start, f"embedding block at row {first}, expected {start}"
        rows = np.arange(start, start + len(emb)) % P
        out["embeddings"][start:start + len(emb)] = emb
        for name, src in sources.items():
            out[name][start:start + len(emb)] = src[rows]
        out["group_size"][start:start + len(emb)] = group_size[base.group[rows]]
    for arr in out.values():
        arr.flush()
    (folder / _META).write_text(json.dumps({"parts": n, "base_parts": P, "noise": noise, "seed": seed}))


def _copies_of_group(base: Catalog, n: int) -> np.ndarray:
    """Parts in each real group root's group of the ``n``-part replica: (P,) int64 by root row."""
    P = len(base)
    copies = np.full(P, n // P, np.int64)
    copies[: n % P] += 1  # rows i < n mod P have one copy more
    return np.bincount(base.group, weights=copies, minlength=P).astype(np.int64)


def _row_shape(base: Catalog, name: str) -> tuple[int, ...]:
    return tuple(getattr(base, name).shape[1:])


def open_replica_arrays(folder: Path) -> dict[str, np.ndarray]:
    """The arrays ``write_replica_arrays`` wrote, memory-mapped read-only (nothing is loaded).

    ``FileNotFoundError`` naming the folder when it is missing or incomplete.
    """
    if not (folder / _META).is_file():
        raise FileNotFoundError(f"{folder}: no complete replicated catalog ({_META} missing)")
    n = int(json.loads((folder / _META).read_text())["parts"])
    arrays = {name: np.load(folder / f"{name}.npy", mmap_mode="r") for name in REPLICA_ARRAYS}
    wrong = {name: a.shape for name, a in arrays.items() if len(a) != n}
    if wrong:
        raise ValueError(f"{folder}: arrays of the wrong length for {n} parts: {wrong}")
    return arrays


class _ReplicaIds(Sequence[str]):
    """Part ids of the replicated catalog, made on access: the real id, then ``{real id}~{copy}``."""

    def __init__(self, base_ids: list[str], n: int):
        self._base, self._n = base_ids, n

    def __len__(self) -> int:
        return self._n

    @overload
    def __getitem__(self, i: int) -> str: ...
    @overload
    def __getitem__(self, i: slice) -> list[str]: ...

    def __getitem__(self, i: int | slice) -> str | list[str]:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(self._n))]
        i = int(i) + (self._n if i < 0 else 0)
        if not 0 <= i < self._n:
            raise IndexError(f"part {i} out of range for a catalog of {self._n} parts")
        P = len(self._base)
        return self._base[i] if i < P else f"{self._base[i % P]}~{i // P}"


class _ReplicaIndex(Mapping[str, int]):
    """Row of a replicated catalog's part id, parsed from the id (no 10M-entry dict)."""

    def __init__(self, base_index: dict[str, int], n: int):
        self._base, self._n = base_index, n

    def __getitem__(self, part_id: str) -> int:
        if part_id in self._base:
            return self._base[part_id]
        real, sep, copy = part_id.rpartition("~")
        row = self._base.get(real) if sep and copy.isdigit() and int(copy) >= 1 else None
        if row is None or int(copy) * len(self._base) + row >= self._n:
            raise KeyError(part_id)
        return int(copy) * len(self._base) + row

    def __iter__(self) -> Iterator[str]:
        return iter(_ReplicaIds(list(self._base), self._n))

    def __len__(self) -> int:
        return self._n


class _ReplicaRecords(Sequence[dict[str, Any]]):
    """Catalog records of the replicated catalog, made on access (a replica's own part id)."""

    def __init__(self, base: list[dict[str, Any]], part_ids: Sequence[str]):
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
    ``part_samples`` and ``mesh`` map a row back to its real part. Part ids, records and the id
    lookup are made on access.

    Args:
        base: the real catalog.
        embeddings: the replicated embeddings (``replicate_embeddings``); the other per-part
            arrays are tiled in memory. Or None with ``arrays``.
        arrays: all per-part arrays (``REPLICA_ARRAYS``; e.g. memory-mapped by
            ``open_replica_arrays``), used as they are.

    Shapes (n parts):
        embeddings: (n, D) float32; part_features: (n, Fp) float32 tiled in memory, or float16
        as given in ``arrays``.
    """

    def __init__(self, base: Catalog, embeddings: np.ndarray | None = None,
                 arrays: Mapping[str, np.ndarray] | None = None):
        if (embeddings is None) == (arrays is None):
            raise ValueError("give either embeddings or arrays")
        a = dict(arrays) if arrays is not None else {"embeddings": cast(np.ndarray, embeddings)}
        emb = a["embeddings"]
        n, P = len(emb), len(base)
        if emb.ndim != 2 or emb.shape[1] != base.embeddings.shape[1]:
            raise ValueError(f"embeddings must have shape (n, {base.embeddings.shape[1]}), "
                             f"found {emb.shape}")
        self.base = base
        if arrays is None:
            reps = -(-n // P)
            rows = np.arange(n) % P

            def tile(x: np.ndarray) -> np.ndarray:
                return np.ascontiguousarray(np.tile(x, (reps,) + (1,) * (x.ndim - 1))[:n])

            a = {"embeddings": np.ascontiguousarray(emb, dtype=np.float32),
                 "part_features": tile(base.part_features), "translations": tile(base.translations),
                 "bbox_min": tile(base.bbox_min), "bbox_max": tile(base.bbox_max),
                 "category_of": tile(base.category_of), "shape_of": tile(base.shape_of),
                 "group": base.group[rows]}
            a["group_size"] = np.bincount(a["group"], minlength=n)[a["group"]]
        missing_arrays = [name for name in REPLICA_ARRAYS if name not in a]
        if missing_arrays:
            raise ValueError(f"arrays lack {', '.join(missing_arrays)}")
        ids = _ReplicaIds(base.part_ids, n)
        self.records = cast(list[dict[str, Any]], _ReplicaRecords(base.records, ids))
        self.part_ids = cast(list[str], ids)
        self.index_of = cast(dict[str, int], _ReplicaIndex(base.index_of, n))
        self.embeddings, self.part_features = a["embeddings"], a["part_features"]
        self.translations, self.bbox_min, self.bbox_max = a["translations"], a["bbox_min"], a["bbox_max"]
        self.category_of, self.shape_of = a["category_of"], a["shape_of"]
        self.group, self.group_size = a["group"], a["group_size"]
        self.points = base.points
        self.mesh_vertices, self.mesh_faces = base.mesh_vertices, base.mesh_faces
        self.vertex_first, self.face_first = base.vertex_first, base.face_first
        self.categories, self.shape_ids = base.categories, base.shape_ids
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
