"""Engine results to JSON-ready dicts matching the response schemas (checked by the tests).

Routes return these through ``OrjsonResponse`` directly: building pydantic response objects for
every suggestion would cost more than the scoring does.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from service.artifacts.catalog import Catalog, part_links
from service.geometry.frames import Frame
from service.suggest.engine import PlaceResult, SuggestResult


def _vec(a: np.ndarray) -> list[float]:
    return np.asarray(a, dtype=np.float64).tolist()


def render_frame(frame: Frame) -> dict[str, Any]:
    return {"center": _vec(frame.center), "radius": float(frame.radius), "up_axis": frame.up_axis,
            "scale": float(frame.radius), "rotation": frame.part_rotation.tolist()}


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
            "label": s.label, "score": s.score, "mode": s.mode, "mode_weight": s.mode_weight,
            "duplicates": s.duplicates, "translation": _vec(s.translation),
            "contact_offset": _vec(s.contact_offset), "bbox_min": _vec(s.bbox_min),
            "bbox_max": _vec(s.bbox_max), "scale": _vec(s.scale), "links": part_links(s.part_id),
        } for s in result.suggestions],
        "inferred_category": (None if result.inferred_category is None else {
            "category": result.inferred_category.category,
            "confidence": result.inferred_category.confidence,
            "applied": result.inferred_category.applied}),
        "warnings": [{"code": w.code, "message": w.message} for w in result.warnings],
        "region": (None if result.region is None else {
            "placed": result.region.placed, "inside": result.region.inside,
            "nearest_gap": result.region.nearest_gap}),
    }


def render_place(result: PlaceResult, model_version: str) -> dict[str, Any]:
    return {
        "model_version": model_version,
        "frame": render_frame(result.frame),
        "placements": [{
            "part_id": p.part_id, "translation": _vec(p.translation),
            "contact_offset": _vec(p.contact_offset), "bbox_min": _vec(p.bbox_min),
            "bbox_max": _vec(p.bbox_max), "scale": _vec(p.scale), "links": part_links(p.part_id),
        } for p in result.placements],
    }


def render_part(catalog: Catalog, i: int) -> dict[str, Any]:
    rec = catalog.records[i]
    dup = rec["duplicate_of"]
    return {
        "part_id": rec["part_id"], "shape_id": rec["shape_id"], "category": rec["category"],
        "style": rec["style"], "label": rec["label"], "split": rec["split"],
        "translation": [float(x) for x in rec["translation"]],
        "bbox_min": [float(x) for x in rec["bbox_min"]], "bbox_max": [float(x) for x in rec["bbox_max"]],
        "area": float(rec["area"]),
        "duplicate_of": catalog.part_ids[dup] if dup is not None else None,
        "duplicates": int(catalog.group_size[i]),
        "n_points": catalog.n_points,
        "n_vertices": int(catalog.vertex_first[i + 1] - catalog.vertex_first[i]),
        "n_faces": int(catalog.face_first[i + 1] - catalog.face_first[i]),
        "name": rec.get("name"), "origin": rec.get("origin", "shipped"),
        "links": part_links(rec["part_id"]),
    }
