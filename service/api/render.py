"""Engine results to JSON-ready dicts matching the response schemas (checked by the tests).

Routes return these through ``OrjsonResponse`` directly: building pydantic response objects for
every suggestion would cost more than the scoring does. A placed part (a suggestion, a placement,
an assembly's node) is rendered by ``render_placed`` and a catalog part's record (``PartOut``)
by ``render_record``, whoever answers with it.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from service.artifacts.catalog import Catalog, part_links
from service.catalog_store.store import StoredPart
from service.catalog_store.writer import added_record
from service.geometry.frames import Frame
from service.suggest.engine import PlaceResult, SuggestResult


def _vec(a: np.ndarray) -> list[float]:
    return np.asarray(a, dtype=np.float64).tolist()


def render_frame(frame: Frame) -> dict[str, Any]:
    return {"center": _vec(frame.center), "radius": float(frame.radius), "up_axis": frame.up_axis,
            "scale": float(frame.radius), "rotation": frame.part_rotation.tolist()}


def render_placed(part_id: str, translation: np.ndarray, contact_offset: np.ndarray, bbox_min: np.ndarray,
                  bbox_max: np.ndarray, scale: np.ndarray) -> dict[str, Any]:
    """Where a part goes, in the answer's frame, and its links.

    Shapes:
        translation, contact_offset, bbox_min, bbox_max, scale: (3,).
    """
    return {"translation": _vec(translation), "contact_offset": _vec(contact_offset),
            "bbox_min": _vec(bbox_min), "bbox_max": _vec(bbox_max), "scale": _vec(scale),
            "links": part_links(part_id)}


def render_suggest(result: SuggestResult, model_version: str, frame_fitted: bool = False) -> dict[str, Any]:
    return {
        "frame_fitted": frame_fitted,
        "model_version": model_version,
        "frame": render_frame(result.frame),
        "input_points": result.n_input_points,
        "candidates": result.candidates,
        "modes": [{"mode": k, "weight": float(w)} for k, w in enumerate(result.mode_weights.tolist())],
        "suggestions": [{
            "rank": s.rank, "part_id": s.part_id, "shape_id": s.shape_id, "category": s.category,
            "label": s.label, "score": s.score, "rank_score": s.rank_score, "mode": s.mode,
            "mode_weight": s.mode_weight, "duplicates": s.duplicates,
            "covered": s.covered, "covered_share": s.covered_share,
            **render_placed(s.part_id, s.translation, s.contact_offset, s.bbox_min, s.bbox_max, s.scale),
        } for s in result.suggestions],
        "inferred_category": (None if result.inferred_category is None else {
            "category": result.inferred_category.category,
            "confidence": result.inferred_category.confidence,
            "applied": result.inferred_category.applied}),
        "warnings": [{"code": w.code, "message": w.message, "guess": w.guess} for w in result.warnings],
        "region": (None if result.region is None else {
            "placed": result.region.placed, "inside": result.region.inside,
            "nearest_gap": result.region.nearest_gap}),
    }


def render_place(result: PlaceResult, model_version: str) -> dict[str, Any]:
    return {
        "model_version": model_version,
        "frame": render_frame(result.frame),
        "placements": [{
            "part_id": p.part_id,
            **render_placed(p.part_id, p.translation, p.contact_offset, p.bbox_min, p.bbox_max, p.scale),
        } for p in result.placements],
    }


def render_part(catalog: Catalog, i: int) -> dict[str, Any]:
    """Catalog row ``i`` as ``PartOut``."""
    dup = catalog.records[i]["duplicate_of"]
    return render_record(catalog.records[i], duplicate_of=catalog.part_ids[dup] if dup is not None else None,
                         duplicates=int(catalog.group_size[i]), n_points=catalog.n_points,
                         n_vertices=int(catalog.vertex_first[i + 1] - catalog.vertex_first[i]),
                         n_faces=int(catalog.face_first[i + 1] - catalog.face_first[i]))


def render_stored_part(p: StoredPart, n_points: int) -> dict[str, Any]:
    """A part just stored as ``PartOut`` (what ``POST /parts`` answers): an added part has no
    near-duplicates."""
    return render_record(added_record(p), duplicate_of=None, duplicates=1, n_points=n_points,
                         n_vertices=p.n_vertices, n_faces=p.n_faces)


def render_record(rec: dict[str, Any], *, duplicate_of: str | None, duplicates: int, n_points: int,
                  n_vertices: int, n_faces: int) -> dict[str, Any]:
    """A catalog record (``CATALOG_FIELDS``, and an added part's name and origin) as ``PartOut``."""
    return {
        "part_id": rec["part_id"], "shape_id": rec["shape_id"], "category": rec["category"],
        "style": rec["style"], "label": rec["label"], "split": rec["split"],
        "translation": [float(x) for x in rec["translation"]],
        "bbox_min": [float(x) for x in rec["bbox_min"]], "bbox_max": [float(x) for x in rec["bbox_max"]],
        "area": float(rec["area"]), "duplicate_of": duplicate_of, "duplicates": duplicates,
        "n_points": n_points, "n_vertices": n_vertices, "n_faces": n_faces,
        "name": rec.get("name"), "origin": rec.get("origin", "shipped"),
        "links": part_links(rec["part_id"]),
    }
