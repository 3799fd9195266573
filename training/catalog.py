"""The exported part catalog: one record per component of every shape, and its arrays.

The catalog holds every component of the processed dataset, train and test alike, each record
saying which split its shape belongs to (evaluation excludes a query's own shape instead).
Near-duplicates (the same geometry in different shapes) are marked with ``duplicate_of`` so the
service can show one of them: two parts are duplicates when their embeddings almost coincide AND
the Chamfer distance of their cached point samples is within the sampling noise; the first keeps
its place.
"""

from __future__ import annotations

from typing import Any

import faiss
import numpy as np

from service.artifacts.layout import CATALOG_FIELDS, format_part_id
from service.geometry.pointsets import chamfer_distance
from training.data.processed import ProcessedDataset
from training.data.sampling import sample_part


def part_records(ds: ProcessedDataset, split_of_shape: list[str]) -> list[dict[str, Any]]:
    """Catalog records (fields of ``service.artifacts.layout.CATALOG_FIELDS``), ``duplicate_of`` unset."""
    records = []
    for c in range(ds.n_components):
        s = int(ds.shape_of[c])
        meta = ds.shapes[s]
        local = c - int(ds.first_comp[s])
        verts, _ = ds.component_mesh(c)
        box_src = verts if len(verts) else ds.points[c].astype(np.float32)
        records.append({
            "part_id": format_part_id(str(meta["shape_id"]), local),
            "shape_id": str(meta["shape_id"]),
            "category": str(meta.get("category")),
            "style": meta.get("style"),
            "label": ds.component_label(c),
            "translation": [float(v) for v in ds.translation[c]],
            "bbox_min": [float(v) for v in box_src.min(axis=0)],
            "bbox_max": [float(v) for v in box_src.max(axis=0)],
            "area": float(ds.area[c]),
            "split": split_of_shape[s],
            "duplicate_of": None,
        })
    missing = set(CATALOG_FIELDS) - set(records[0]) if records else set()
    assert not missing, f"catalog record lacks {missing}"
    return records


def sample_parts(ds: ProcessedDataset, n: int, seed: int) -> np.ndarray:
    """``n`` cached points of every component, centred, with one seeded generator.

    Shapes:
        returns (C, n, 3) float32.
    """
    rng = np.random.default_rng(seed)
    return np.stack([sample_part(ds, c, n, rng) for c in range(ds.n_components)]) if ds.n_components \
        else np.zeros((0, n, 3), np.float32)


def find_duplicates(embeddings: np.ndarray, points: np.ndarray, area: np.ndarray, extents: np.ndarray,
                    embedding_radius: float, chamfer_factor: float,
                    size_tolerance: float) -> list[int | None]:
    """``duplicate_of`` for every part: the index of an earlier part with the same geometry, or None.

    Candidates are parts within ``embedding_radius`` (L2) in the embedding. A candidate is a
    duplicate when (1) its area and bounding-box extents match within ``size_tolerance`` (relative
    to the area, and to the larger box diagonal) and (2) the Chamfer distance of the cached point
    samples is below ``chamfer_factor * sqrt(area / S)``. Two independent samples of S points of
    one surface of area A lie about ``0.5 * sqrt(A / S)`` apart (mean nearest-neighbour distance,
    measured), so a factor of 0.65 sits just above that sampling noise whatever the sample size.
    The size test is needed because a mean-based Chamfer distance barely sees a plate that is 10%
    larger. Parts are visited in order and the first of a group keeps its place, so
    ``duplicate_of`` always points to a part that is not itself a duplicate.

    Shapes:
        embeddings (P, D) float32; points (P, S, 3); area (P,); extents (P, 3) bounding-box sizes.
    """
    n = len(embeddings)
    out: list[int | None] = [None] * n
    if n == 0 or embedding_radius <= 0 or chamfer_factor <= 0:
        return out
    index = faiss.IndexFlatL2(embeddings.shape[1])
    emb = np.ascontiguousarray(embeddings, dtype=np.float32)
    index.add(emb)
    lims, _, ids = index.range_search(emb, float(embedding_radius) ** 2)
    pts = points.astype(np.float32)
    area = area.astype(np.float64)
    extents = extents.astype(np.float64)
    diag = np.linalg.norm(extents, axis=1)
    spacing = np.sqrt(np.maximum(area, 0.0) / points.shape[1])
    for i in range(n):
        if out[i] is not None:
            continue
        for j in sorted(int(j) for j in ids[lims[i]:lims[i + 1]]):
            if j <= i or out[j] is not None:
                continue
            if abs(area[i] - area[j]) > size_tolerance * max(area[i], area[j]):
                continue
            if np.abs(extents[i] - extents[j]).max() > size_tolerance * max(diag[i], diag[j]):
                continue
            if chamfer_distance(pts[i], pts[j]) < chamfer_factor * max(spacing[i], spacing[j]):
                out[j] = i
    return out


def concat_meshes(ds: ProcessedDataset) -> dict[str, np.ndarray]:
    """The centred meshes of all components, in the catalog.npz layout (they already are)."""
    return {
        "mesh_vertices": ds.mesh_vertices.astype(np.float32),
        "mesh_faces": ds.mesh_faces.astype(np.int32),
        "vertex_first": ds.vertex_first.astype(np.int64),
        "face_first": ds.face_first.astype(np.int64),
    }
