"""Immutable catalog snapshots: the shipped parts followed by the added ones, and their index.

A request reads one snapshot from start to end (``service.suggest.snapshot.CatalogSnapshot``:
one catalog, its index and search); a write builds the next one and the served object swaps its
reference (``service.api.served``), so reads never wait for writes. The engine, its networks
and caches are not rebuilt. Building a snapshot must stay cheap as the catalog grows, so the large arrays
(meshes, preview points, embeddings, part features) live in growable buffers: the shipped rows
are copied in once, added rows are appended after the filled prefix, and each snapshot holds
views of the prefix it was built on. An append writes only past every existing view, so older
snapshots still being read are never touched; a delete rebuilds the buffers.

The index of a snapshot with additions is an exact flat index of the same metric over all its
embeddings (catalog row i = index row i, as in the shipped artifacts). Copying the vectors costs
O(parts x D) per snapshot: a few milliseconds for 100k parts of 50 dimensions.

The index file in the data folder (``added-index.npz``) holds the added embeddings' index and
the change sequence it reflects; it is derived data, checked against the database at start.
"""

from __future__ import annotations

import io
import json
import logging
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import faiss
import numpy as np

from service.artifacts.catalog import Catalog
from service.artifacts.files import write_file_atomic
from service.artifacts.layout import CATALOG_ARRAY_NAMES, catalog_arrays
from service.catalog_store.store import PartGeometry

log = logging.getLogger(__name__)


@dataclass
class AddedPart:
    """An added part as the snapshot needs it: its catalog record and arrays.

    Shapes:
        embedding: (D,) float32; part_feature: (Fp,) float32; geometry.points: (S, 3) float16.
    """

    row_id: int
    record: dict[str, Any]
    embedding: np.ndarray
    part_feature: np.ndarray
    geometry: PartGeometry


class _Growable:
    """Rows filled from the front of a larger buffer; views of a filled prefix stay valid."""

    def __init__(self, first: np.ndarray, growth: float = 1.5):
        self.growth = growth
        # A little room after the shipped rows; the first large addition grows the buffer.
        self._buf = np.empty((len(first) + max(256, len(first) // 16), *first.shape[1:]), dtype=first.dtype)
        self._buf[:len(first)] = first
        self.n = len(first)

    def extend(self, rows: np.ndarray) -> None:
        need = self.n + len(rows)
        if need > len(self._buf):
            # A new buffer: snapshots still reading the old one keep it alive until they finish.
            bigger = np.empty((max(need, int(len(self._buf) * self.growth)), *self._buf.shape[1:]),
                              dtype=self._buf.dtype)
            bigger[:self.n] = self._buf[:self.n]
            self._buf = bigger
        self._buf[self.n:need] = rows
        self.n = need

    def view(self) -> np.ndarray:
        return self._buf[:self.n]


class CatalogBuilder:
    """Builds catalog snapshots of the shipped catalog plus added parts (appended in order)."""

    def __init__(self, base: Catalog):
        self.base = base
        self.set_parts([])

    @property
    def n_points(self) -> int:
        """Preview points per part (S), fixed by the shipped catalog."""
        return self.base.n_points

    def set_parts(self, parts: list[AddedPart]) -> None:
        """Start over from the shipped catalog with exactly ``parts`` added (after a delete)."""
        b = self.base
        self._last: Catalog | None = None  # the previous snapshot, extended by the next one
        self.records: list[dict[str, Any]] = list(b.records)
        self._embeddings = _Growable(b.embeddings)
        self._part_features = _Growable(b.part_features)
        self._points = _Growable(b.points)
        self._vertices = _Growable(b.mesh_vertices)
        self._faces = _Growable(b.mesh_faces)
        self._vertex_first = _Growable(b.vertex_first)
        self._face_first = _Growable(b.face_first)
        self.added = 0
        self.append(parts)

    def append(self, parts: list[AddedPart]) -> None:
        """Add parts after the current ones."""
        if not parts:
            return
        S = self.n_points
        for p in parts:
            assert p.geometry.points.shape == (S, 3), (
                f"part {p.record['part_id']}: preview points of shape {p.geometry.points.shape}, "
                f"expected ({S}, 3)")
        self._embeddings.extend(np.stack([p.embedding for p in parts]).astype(np.float32))
        self._part_features.extend(np.stack([p.part_feature for p in parts]).astype(np.float32))
        self._points.extend(np.stack([p.geometry.points for p in parts]).astype(np.float16))
        v0, f0 = self._vertices.n, self._faces.n
        nv = np.cumsum([len(p.geometry.vertices) for p in parts])
        nf = np.cumsum([len(p.geometry.faces) for p in parts])
        self._vertices.extend(np.concatenate([p.geometry.vertices for p in parts]).astype(np.float32))
        self._faces.extend(np.concatenate([p.geometry.faces for p in parts]).astype(np.int32))
        self._vertex_first.extend((v0 + nv).astype(np.int64))
        self._face_first.extend((f0 + nf).astype(np.int64))
        self.records.extend(p.record for p in parts)
        self.added += len(parts)

    def catalog(self) -> Catalog:
        """A new immutable catalog over the rows added so far.

        Building a ``Catalog`` walks every record in Python (22 ms for 7k parts); after an append
        the new snapshot is the previous one extended by the new rows instead (about 1 ms). The
        extension is checked once against a full build, and not used if ``Catalog`` has grown
        fields it does not know.
        """
        arrays = catalog_arrays(embeddings=self._embeddings.view(), part_features=self._part_features.view(),
                                points=self._points.view(), mesh_vertices=self._vertices.view(),
                                mesh_faces=self._faces.view(), vertex_first=self._vertex_first.view(),
                                face_first=self._face_first.view())
        prev = self._last
        if prev is not None and _extension_ok(prev) and len(prev) < len(self.records):
            cat = extend_catalog(prev, self.records[len(prev):], arrays)
        else:
            cat = Catalog(records=list(self.records), **arrays)
        self._last = cat
        return cat


# Attributes ``extend_catalog`` sets; a Catalog with others is always built in full.
_EXTENDED = frozenset({
    "records", *CATALOG_ARRAY_NAMES, "part_ids", "index_of", "categories", "category_of", "shape_ids",
    "shape_of", "translations", "bbox_min", "bbox_max", "group", "group_size"})


def _extension_ok(cat: Catalog) -> bool:
    unknown = set(vars(cat)) - _EXTENDED
    if unknown:
        log.warning("Catalog has fields %s that snapshots do not extend; building them in full", unknown)
    return not unknown


def _codes(prev_names: list[str], prev_codes: np.ndarray, new_names: list[str]
           ) -> tuple[list[str], np.ndarray]:
    """Sorted names and codes of old + new rows (old codes remapped if new names sort among them)."""
    names = sorted(set(prev_names).union(new_names))
    code = {n: i for i, n in enumerate(names)}
    old = prev_codes if len(names) == len(prev_names) else \
        np.array([code[n] for n in prev_names], dtype=np.int32)[prev_codes]
    return names, np.concatenate([old, np.array([code[n] for n in new_names], dtype=np.int32)])


def extend_catalog(prev: Catalog, new: list[dict[str, Any]], arrays: dict[str, np.ndarray]) -> Catalog:
    """``prev`` followed by the records ``new`` (added parts: no near-duplicates), as a new
    Catalog equal to a full build over all records, in O(parts) numpy work instead of Python.

    Shapes:
        arrays: the catalog arrays over all rows (prev's and the new ones).
    """
    n0, k = len(prev), len(new)
    cat = Catalog.__new__(Catalog)
    cat.records = [*prev.records, *new]
    for name, value in arrays.items():
        setattr(cat, name, value)
    cat.part_ids = [*prev.part_ids, *(r["part_id"] for r in new)]
    cat.index_of = {**prev.index_of, **{r["part_id"]: n0 + i for i, r in enumerate(new)}}
    cat.categories, cat.category_of = _codes(prev.categories, prev.category_of, [r["category"] for r in new])
    cat.shape_ids, cat.shape_of = _codes(prev.shape_ids, prev.shape_of, [r["shape_id"] for r in new])
    for name in ("translation", "bbox_min", "bbox_max"):
        rows = np.array([r[name] for r in new], dtype=np.float32).reshape(-1, 3)
        attr = "translations" if name == "translation" else name
        setattr(cat, attr, np.concatenate([getattr(prev, attr), rows]))
    assert all(r["duplicate_of"] is None for r in new), "added parts have no near-duplicates"
    cat.group = np.concatenate([prev.group, np.arange(n0, n0 + k, dtype=prev.group.dtype)])
    cat.group_size = np.concatenate([prev.group_size, np.ones(k, dtype=prev.group_size.dtype)])
    return cat


def combined_index(base_index: faiss.Index, catalog: Catalog, base_parts: int) -> faiss.Index:
    """The index a snapshot searches: the shipped one while nothing is added, else an exact flat
    index of the same metric over every embedding of ``catalog``."""
    if len(catalog) == base_parts:
        return base_index
    index = faiss.IndexFlat(catalog.embeddings.shape[1], base_index.metric_type)
    index.add(np.ascontiguousarray(catalog.embeddings, dtype=np.float32))
    return index


# --------------------------------------------------------------------------------------------
# The index file of the data folder.


@dataclass
class IndexFile:
    """What ``added-index.npz`` says: the added parts it covers and the sequence it reflects.

    Shapes:
        row_ids: (n,) int64 (``parts.id``); embeddings: (n, D) float32 (read back from the index).
    """

    seq: int
    model_version: str
    row_ids: np.ndarray
    embeddings: np.ndarray


def write_index_file(path: Path, seq: int, model_version: str, row_ids: list[int],
                     embeddings: np.ndarray, metric: int) -> None:
    """Write the added parts' FAISS index with the sequence it reflects, atomically."""
    dim = embeddings.shape[1] if embeddings.ndim == 2 else 0
    index = faiss.IndexFlat(max(dim, 1), metric)
    if len(row_ids):
        index.add(np.ascontiguousarray(embeddings, dtype=np.float32))
    meta = {"seq": int(seq), "model_version": model_version, "count": len(row_ids)}
    buf = io.BytesIO()
    np.savez(buf, index=faiss.serialize_index(index), row_ids=np.asarray(row_ids, dtype=np.int64),
             meta=np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8))
    write_file_atomic(path, buf.getvalue())


def read_index_file(path: Path) -> IndexFile | None:
    """The index file's content, or None when it is missing or unreadable (then it is rebuilt)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(bytes(z["meta"]).decode())
            row_ids = z["row_ids"].astype(np.int64)
            index = faiss.deserialize_index(z["index"])
        count = int(meta["count"])
        vectors = (index.reconstruct_n(0, index.ntotal) if index.ntotal
                   else np.zeros((0, index.d), np.float32))
        if count != len(row_ids) or index.ntotal != count:
            raise ValueError(f"{index.ntotal} vectors and {len(row_ids)} row ids, meta says {count}")
        return IndexFile(int(meta["seq"]), str(meta["model_version"]), row_ids, vectors)
    except (OSError, ValueError, KeyError, RuntimeError, zipfile.BadZipFile, EOFError) as exc:
        log.warning("%s: unreadable index file, rebuilding it from the database (%s)", path, exc)
        return None
