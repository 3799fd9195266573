"""Request and response schemas of the HTTP API, with the examples shown at ``/docs``.

Requests validate types and static bounds here. Limits that are settings are checked by
``service.settings.Limits``, one check per limit: the conversions below apply the ones that can
fail before decoding (the point count of a body, the batch size), and the engine, which in-process
callers reach without a schema, the rest (``k``, exclusions, the decoded point count). Request
schemas convert themselves into engine types (``to_points``, ``to_options``, ``checked_items``).
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PlainValidator, model_validator

from service.errors import InputError
from service.geometry.frames import Frame
from service.geometry.inputs import points_from_base64, points_from_json, points_from_list, points_to_base64
from service.settings import Limits, check_point_count
from service.suggest.engine import SuggestOptions
from service.suggest.preferences import Preferences
from service.suggest.region import Region

# Request numbers and flags are strict: JSON `false` or `"1"` is not a coordinate, a count or a
# flag (pydantic would otherwise coerce them). Integers are still accepted for floats.
Finite = Annotated[float, Field(allow_inf_nan=False, strict=True)]
Number = Annotated[float, Field(strict=True)]
Count = Annotated[int, Field(strict=True)]
Flag = Annotated[bool, Field(strict=True)]
Vec3 = tuple[float, float, float]
# Largest |coordinate| of a frame's centre and largest radius: with the catalog's extents a
# placed box then stays far inside float64 (centre -1.7e308 with radius 1.7e308 answered 200
# with null translations: the sums overflowed to infinity, which JSON cannot hold).
FRAME_MAX = 1e15
# Largest seed: numpy's generators take any non-negative integer, JSON carries at most 64 bits.
SEED_MAX = 2**63 - 1
FrameCoord = Annotated[float, Field(allow_inf_nan=False, strict=True, ge=-FRAME_MAX, le=FRAME_MAX)]
# JSON points: checked and converted in one pass (``points_from_json``), documented as numbers.
PointRows = Annotated[Any, PlainValidator(points_from_json, json_schema_input_type=list[list[float]])]

# A small valid query for the examples: a ring of 16 points (a chair seat's rim, say).
_RING: list[Any] = [[round(0.5 * math.cos(a), 4), 0.0, round(0.5 * math.sin(a), 4)]
         for a in np.linspace(0, 2 * math.pi, 16, endpoint=False).tolist()]
_RING_B64 = points_to_base64(np.array(_RING, dtype=np.float32))


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class FrameIn(_Strict):
    """The caller's frame; omit for the canonical frame (y up, object centred, unit radius)."""

    center: tuple[FrameCoord, FrameCoord, FrameCoord] = Field(
        default=(0.0, 0.0, 0.0), description=f"Centre of the complete object in caller units (each at most "
        f"{FRAME_MAX:g} in size).")
    radius: Finite = Field(default=1.0, gt=0, le=FRAME_MAX, description=(
        f"Radius of the complete object in caller units (at most {FRAME_MAX:g})."))
    up_axis: Literal["y", "z"] = Field(default="y", description="The caller's up axis.")

    def to_frame(self) -> Frame:
        return Frame(center=np.array(self.center, dtype=np.float64), radius=self.radius, up_axis=self.up_axis)


Coord3 = tuple[FrameCoord, FrameCoord, FrameCoord]


class RegionIn(_Strict):
    """A spot in the request's frame: a point and a radius (a click), or a box (a drag)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"point": [0.3, -0.2, 0.3], "radius": 0.15}, {"min": [0.1, -1.0, 0.1], "max": [0.5, -0.2, 0.5]}]})

    point: Coord3 | None = Field(default=None, description="The spot's centre (with `radius`).")
    radius: Finite | None = Field(default=None, gt=0, le=FRAME_MAX, description=(
        "With `point`: parts whose placed box comes within this distance of the point."))
    min: Coord3 | None = Field(default=None, description="A box's smallest corner (with `max`).")
    max: Coord3 | None = Field(default=None, description="A box's largest corner (with `min`).")

    def to_region(self) -> Region:
        """The engine's region; ``InputError`` (``invalid_region``) unless exactly one form is complete."""
        ball = (self.point, self.radius)
        box = (self.min, self.max)
        if all(v is not None for v in ball) and all(v is None for v in box):
            assert self.point is not None and self.radius is not None
            return Region.ball(np.array(self.point), self.radius)
        if all(v is not None for v in box) and all(v is None for v in ball):
            assert self.min is not None and self.max is not None
            return Region.box(np.array(self.min), np.array(self.max))
        given = [n for n in ("point", "radius", "min", "max") if getattr(self, n) is not None]
        raise InputError("invalid_region", "a region is either point and radius, or min and max; found "
                         + (", ".join(given) if given else "none of them"))


class SuggestOptionsIn(_Strict):
    """Options of one suggestion query."""

    k: Count | None = Field(default=None, description=(
        "Suggestions to return (default and maximum: settings COMPLEMENTME_DEFAULT_K, COMPLEMENTME_MAX_K)."))
    category: str | list[str] | None = Field(default=None, description=(
        "Only parts of this category (or categories)."))
    exclude_parts: list[str] = Field(default_factory=list, description=(
        "Part ids never to suggest; their near-duplicates are excluded too."))
    exclude_shapes: list[str] = Field(default_factory=list, description=(
        "Source shape ids whose parts are never suggested."))
    collapse_duplicates: Flag = Field(default=True, description=(
        "Show one part per group of near-identical parts."))
    frame: FrameIn | None = Field(default=None, description="The frame of the points and of the answer.")
    style: str | list[str] | None = Field(default=None, description=(
        "Only parts of this catalog style (or styles), e.g. \"armchair\"."))
    mode_weights: list[Annotated[float, Field(ge=0, allow_inf_nan=False, strict=True)]] | None = Field(
        default=None, description=(
            "One factor per mixture mode (GET /model: n_modes) multiplying g's mode weights before "
            "ranking: favour some kinds of complement over others."))
    exclude_modes: list[Count] = Field(default_factory=list, description=(
        "Mixture modes whose kind of complement is never suggested."))
    diversity: Flag = Field(default=False, description=(
        "A gallery balanced over modes: round-robin over the modes by weight instead of "
        "likelihood order."))
    refine_contact: Flag | None = Field(default=None, description=(
        "Nudge each placement (at most COMPLEMENTME_CONTACT_MAX_OFFSET) so the part touches the "
        "query without sinking into it; the move is reported as contact_offset. Omitted: "
        "COMPLEMENTME_SUGGEST_REFINE_CONTACT (false unless configured; refinement costs about ten "
        "times the rest of a suggestion)."))
    complement_check: Flag | None = Field(default=None, description=(
        "Place the best-ranked candidates and move those lying mostly on the query's own surface "
        "(parts it already has) behind the others. Omitted: COMPLEMENTME_SUGGEST_COMPLEMENT_CHECK "
        "(true unless configured)."))
    fit_scale: Flag | None = Field(default=None, description=(
        "Fit each part in size to the query (per-axis `scale` from the placement network, applied "
        "about the part's centre; the placed box is the scaled one). Omitted: "
        "COMPLEMENTME_FIT_SCALE (true unless configured)."))
    region: RegionIn | None = Field(default=None, description=(
        "Suggest for this spot: only parts whose placed box (after scale fitting) reaches into the "
        "region, in the request's frame, ranked among the best COMPLEMENTME_REGION_CANDIDATES "
        "candidates. The answer's `region` says how many were placed and how many fell in; an "
        "empty answer carries a `region_empty` warning saying why."))
    fit_frame: Flag | None = Field(default=None, description=(
        "Estimate the complete object's frame from the partial one and answer in it: centre, radius "
        "and (without `frame`) the up axis, the hypothesis under which the model is surest "
        "(`service/suggest/frame_fit.py`); the answer's `frame` is the one used and `frame_fitted` is true. "
        "With `frame`, only its `up_axis` is kept. Omitted: fitted for mesh uploads sent without "
        "`frame` when COMPLEMENTME_FIT_FRAME_UPLOADS is on (off by default), never for JSON points."))

    def preferences(self) -> Preferences:
        return Preferences(mode_weights=tuple(self.mode_weights) if self.mode_weights is not None else None,
                           exclude_modes=tuple(self.exclude_modes), diversity=self.diversity)

    def to_options(self) -> SuggestOptions:
        cats = [self.category] if isinstance(self.category, str) else list(self.category or [])
        styles = [self.style] if isinstance(self.style, str) else list(self.style or [])
        return SuggestOptions(k=self.k, categories=tuple(cats), exclude_parts=tuple(self.exclude_parts),
                              exclude_shapes=tuple(self.exclude_shapes),
                              collapse_duplicates=self.collapse_duplicates,
                              frame=self.frame.to_frame() if self.frame else Frame(),
                              refine_contact=self.refine_contact, complement_check=self.complement_check,
                              fit_scale=self.fit_scale, styles=tuple(styles),
                              preferences=self.preferences(),
                              region=self.region.to_region() if self.region is not None else None)


class PointsIn(_Strict):
    """A partial assembly as points: a JSON list, or base64 float32 (faster) - exactly one of them."""

    points: PointRows | None = Field(default=None, description=(
        "[[x, y, z], ...] in the request's frame."))
    points_base64: str | None = Field(default=None, description=(
        "Base64 of little-endian float32 x, y, z triples (12 bytes per point)."))

    @model_validator(mode="after")
    def _one_source(self) -> PointsIn:
        if self.points is not None and self.points_base64 is not None:
            raise ValueError("give either points or points_base64, not both")
        return self

    def to_points(self, max_points: int) -> np.ndarray:
        """The points as ``(M, 3) float32``; ``InputError`` when missing, malformed or too many."""
        if self.points_base64 is not None:
            return points_from_base64(self.points_base64, max_points)
        if self.points is None:
            raise InputError("missing_points", "give the partial assembly as points or points_base64")
        check_point_count(len(self.points), 0, max_points)
        if isinstance(self.points, np.ndarray):
            return self.points
        return points_from_list(self.points)


class SuggestRequest(PointsIn, SuggestOptionsIn):
    """A partial assembly and the options of its suggestions."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"points": _RING, "k": 5},
        {"points_base64": _RING_B64, "k": 10, "category": "chair", "exclude_shapes": ["chair-0007"],
         "frame": {"center": [0.0, 0.0, 0.45], "radius": 0.6, "up_axis": "z"}},
    ]})


class PlaceRequest(PointsIn):
    """A partial assembly and the parts the user chose for it."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"points": _RING, "part_ids": ["chair-0007/2", "chair-0011/0"]},
    ]})

    part_ids: list[str] = Field(..., description="Catalog part ids to place.")
    frame: FrameIn | None = Field(default=None, description="The frame of the points and of the answer.")
    refine_contact: Flag = Field(default=True, description=(
        "Nudge each placement so the part touches the query without sinking into it."))
    fit_scale: Flag | None = Field(default=None, description=(
        "Fit each part in size (per-axis `scale`). Omitted: COMPLEMENTME_FIT_SCALE."))


class BatchRequest(_Strict):
    """Many suggestion queries answered with batched inference."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"items": [{"points": _RING, "k": 3}, {"points_base64": _RING_B64, "category": "table"}]},
    ]})

    # Items are validated one by one, so one malformed item fails alone.
    items: list[Any] = Field(..., description=(
        "Suggestion requests (each a SuggestRequest); at most COMPLEMENTME_MAX_BATCH_ITEMS."),
        json_schema_extra={"items": {"$ref": "#/components/schemas/SuggestRequest"}})

    def checked_items(self, limits: Limits) -> list[Any]:
        """The items, raw; ``InputError`` for none or more than ``max_batch_items``."""
        limits.check_batch_items(len(self.items))
        return self.items


# --------------------------------------------------------------------------------------------
# Responses.


class ErrorDetail(BaseModel):
    code: str = Field(..., description="Stable machine-readable error code.")
    message: str = Field(..., description="What was wrong, for humans.")
    details: list[dict[str, Any]] | None = Field(default=None, description=(
        "Per-field problems (validation errors)."))


class ErrorResponse(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [
        {"error": {"code": "too_few_points", "message": "3 points given, at least 16 are needed"}},
    ]})

    error: ErrorDetail


class FrameOut(BaseModel):
    center: Vec3
    radius: float
    up_axis: Literal["y", "z"]
    scale: float = Field(..., description="Factor to apply to catalog part geometry (canonical units).")
    rotation: list[list[float]] = Field(..., description=(
        "3x3 matrix turning catalog part geometry into the caller's axes: "
        "placed vertex = scale * rotation @ v + translation."))


class PartLinks(BaseModel):
    part: str = Field(..., description="The part's record.")
    mesh: str = Field(..., description="The part's mesh as GLB (add ?format=obj or ?format=ply).")
    points: str = Field(..., description="The part's point samples.")


class SuggestionOut(BaseModel):
    rank: int
    part_id: str
    shape_id: str
    category: str
    label: str | None
    score: float = Field(..., description=(
        "Log-likelihood of the part's embedding under the predicted mixture."))
    rank_score: float = Field(..., description=(
        "The key the answer is ordered by: `score` less the fit penalties (the part's fitted "
        "scale away from 1 and its placement away from where it sat in its own shape; settings "
        "COMPLEMENTME_RANK_SCALE_WEIGHT and COMPLEMENTME_RANK_MOVE_WEIGHT). Higher is better; "
        "the share order deals slots to modes in this order, and the complement check demotes "
        "covered parts behind it."))
    mode: int = Field(..., description="The mixture mode that explains the part best.")
    mode_weight: float = Field(..., description="That mode's weight.")
    duplicates: int = Field(..., description="Catalog parts in this part's near-duplicate group.")
    covered: bool | None = Field(default=None, description=(
        "The complement check's verdict: placed where the answer puts it (before contact "
        "refinement), the part lies mostly on the partial assembly's own surface, so it "
        "duplicates or would replace a part already there rather than add one. Covered parts come "
        "after the others. null when the check did not run (`complement_check` false, or "
        "COMPLEMENTME_SUGGEST_COMPLEMENT_CHECK off and not asked for)."))
    covered_share: float | None = Field(default=None, ge=0, le=1, description=(
        "The share of the part's surface samples within COMPLEMENTME_COMPLEMENT_COVER_DISTANCE of "
        "the partial assembly's points; `covered` is true from COMPLEMENTME_COMPLEMENT_COVER_SHARE "
        "on. null when the check did not run."))
    translation: Vec3 = Field(..., description="Where the part's bounding-box centre goes (caller frame).")
    contact_offset: Vec3 = Field(..., description=(
        "The contact refinement's share of the translation (zero when off or not needed)."))
    bbox_min: Vec3 = Field(..., description="Placed bounding box (caller frame), after scaling.")
    bbox_max: Vec3
    scale: Vec3 = Field(default=(1.0, 1.0, 1.0), description=(
        "Per-axis scale (caller frame axes) that fits the part to the query, about its centre; "
        "[1, 1, 1] when fitting is off or the model has no scale head. The catalog geometry is "
        "never changed: apply it when placing the part."))
    links: PartLinks


class InferredCategoryOut(BaseModel):
    category: str = Field(..., description="The category read from the partial assembly.")
    confidence: float = Field(..., description="The model's probability of that category.")
    applied: bool = Field(..., description=(
        "The suggestions were kept in that category (confidence at least "
        "COMPLEMENTME_CATEGORY_MIN_CONFIDENCE)."))


class WarningOut(BaseModel):
    code: str = Field(..., description=(
        "`frame` (the points are far from the model's unit-radius frame), `category_unsure` (no "
        "category is likely enough), `unfamiliar` (nothing in the catalog is like what the model "
        "expects), `unfamiliar_shape` (the partial assembly is unlike every training shape: the "
        "category and suggestions are guesses) or `region_empty` (no candidate is placed in the "
        "request's region)."))
    message: str = Field(..., description="What is wrong and how to fix it.")
    guess: bool = Field(default=False, description=(
        "True when the warning makes the suggestions guesses (`frame`, `category_unsure`, "
        "`unfamiliar`, `unfamiliar_shape`): what a client shows beside them."))


class RegionOut(BaseModel):
    placed: int = Field(..., description=(
        "Best-ranked candidates placed and tested against the region (at most "
        "COMPLEMENTME_REGION_CANDIDATES)."))
    inside: int = Field(..., description="Of those, the parts whose placed box reaches into the region.")
    nearest_gap: float | None = Field(..., description=(
        "When none is inside: how far the nearest placed box stays from the region (request's units)."))


class ModeOut(BaseModel):
    mode: int
    weight: float


class SuggestResponse(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{
        "model_version": "2025.01-chairs", "input_points": 16, "candidates": 212,
        "frame": {"center": [0, 0, 0], "radius": 1.0, "up_axis": "y", "scale": 1.0,
                  "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
        "modes": [{"mode": 0, "weight": 0.61}, {"mode": 1, "weight": 0.39}],
        "suggestions": [{
            "rank": 1, "part_id": "chair-0007/2", "shape_id": "chair-0007", "category": "chair",
            "label": "leg", "score": 41.2, "rank_score": 38.9, "mode": 0, "mode_weight": 0.61,
            "duplicates": 4,
            "translation": [0.31, -0.52, 0.28], "contact_offset": [0.0, -0.012, 0.0],
            "bbox_min": [0.27, -0.98, 0.24], "bbox_max": [0.35, -0.06, 0.32],
            "links": {"part": "/parts/chair-0007/2", "mesh": "/parts/chair-0007/2/mesh",
                      "points": "/parts/chair-0007/2/points"}}],
    }]})

    model_version: str
    frame: FrameOut
    input_points: int = Field(..., description="Points received (before resampling to the model's count).")
    candidates: int = Field(..., description="Distinct catalog parts re-scored before ranking.")
    modes: list[ModeOut]
    suggestions: list[SuggestionOut]
    inferred_category: InferredCategoryOut | None = Field(default=None, description=(
        "When the request named no category: the category the model reads from the query."))
    warnings: list[WarningOut] = Field(default_factory=list, description=(
        "What makes this answer doubtful (the status stays 200)."))
    region: RegionOut | None = Field(default=None, description=(
        "When the request gave a region: how many candidates were placed and how many fell in it."))
    frame_fitted: bool = Field(default=False, description=(
        "The service estimated `frame` from the partial (`fit_frame`)."))


class PlacementOut(BaseModel):
    part_id: str
    translation: Vec3
    contact_offset: Vec3 = Field(..., description=(
        "The contact refinement's share of the translation (zero when off or not needed)."))
    bbox_min: Vec3
    bbox_max: Vec3
    scale: Vec3 = Field(default=(1.0, 1.0, 1.0), description=(
        "Per-axis scale (caller frame axes) that fits the part, about its centre."))
    links: PartLinks


class PlaceResponse(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{
        "model_version": "2025.01-chairs",
        "frame": {"center": [0, 0, 0], "radius": 1.0, "up_axis": "y", "scale": 1.0,
                  "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
        "placements": [{"part_id": "chair-0007/2", "translation": [0.31, -0.52, 0.28],
                        "contact_offset": [0.0, -0.012, 0.0],
                        "bbox_min": [0.27, -0.98, 0.24], "bbox_max": [0.35, -0.06, 0.32],
                        "links": {"part": "/parts/chair-0007/2", "mesh": "/parts/chair-0007/2/mesh",
                                  "points": "/parts/chair-0007/2/points"}}],
    }]})

    model_version: str
    frame: FrameOut
    placements: list[PlacementOut]


class BatchItemOut(BaseModel):
    index: int
    ok: bool
    result: SuggestResponse | None = None
    error: ErrorDetail | None = None


class BatchResponse(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{
        "model_version": "2025.01-chairs",
        "results": [
            {"index": 0, "ok": True, "result": {"...": "a SuggestResponse"}},
            {"index": 1, "ok": False, "error": {"code": "non_finite_points",
                                                "message": "point 3 has a NaN or infinite coordinate"}},
        ]}]})

    model_version: str
    results: list[BatchItemOut]


_PART_EXAMPLE: dict[str, Any] = {
    "part_id": "chair-0007/2", "shape_id": "chair-0007", "category": "chair", "style": "armchair",
    "label": "leg", "split": "train", "translation": [0.31, -0.52, 0.28],
    "bbox_min": [-0.04, -0.46, -0.04], "bbox_max": [0.04, 0.46, 0.04], "area": 0.15,
    "duplicate_of": None, "duplicates": 4, "n_points": 1000, "n_vertices": 24, "n_faces": 44,
    "name": None, "origin": "shipped",
    "links": {"part": "/parts/chair-0007/2", "mesh": "/parts/chair-0007/2/mesh",
              "points": "/parts/chair-0007/2/points"}}


class PartOut(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [_PART_EXAMPLE]})

    part_id: str
    shape_id: str
    category: str
    style: str | None
    label: str | None
    split: str
    translation: Vec3 = Field(..., description="Bounding-box centre in the source shape (canonical frame).")
    bbox_min: Vec3 = Field(..., description="Centred bounding box.")
    bbox_max: Vec3
    area: float
    duplicate_of: str | None = Field(..., description="Part id this part is a near-duplicate of.")
    duplicates: int = Field(..., description="Catalog parts in this part's near-duplicate group.")
    n_points: int
    n_vertices: int
    n_faces: int
    name: str | None = Field(default=None, description="Free-text name (added parts).")
    origin: Literal["shipped", "added"] = Field(default="shipped", description=(
        "Whether the part ships with the artifacts or was added through POST /parts."))
    links: PartLinks


class PartsPage(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{
        "total": 1, "offset": 0, "limit": 50, "items": [_PART_EXAMPLE],
    }]})

    total: int
    offset: int
    limit: int
    items: list[PartOut]


class PartPointsOut(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [
        {"part_id": "chair-0007/2", "n_points": 2, "points": [[0.01, -0.4, 0.02], [-0.03, 0.1, 0.0]]},
    ]})

    part_id: str
    n_points: int
    points: list[list[float]] | None = Field(default=None, description="Centred samples (encoding=json).")
    points_base64: str | None = Field(default=None, description=(
        "Little-endian float32 triples (encoding=base64)."))


class CategoryOut(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{"name": "chair", "parts": 2210}]})

    name: str
    parts: int


class ModelInfo(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{
        "model_version": "2025.01-chairs", "format_version": 1, "n_points": 1000, "placement_points": 1000,
        "embedding_dim": 50, "n_modes": 10, "part_count": 4210,
        "categories": [{"name": "chair", "parts": 2210}],
        "limits": {"min_points": 16, "max_points": 100000, "default_k": 10, "max_k": 100}}]})

    model_version: str
    format_version: int
    n_points: int
    placement_points: int = Field(description="Points h takes of a query and of a part (n_points "
                                  "unless the artifacts give h its own count).")
    embedding_dim: int
    n_modes: int
    part_count: int
    categories: list[CategoryOut]
    limits: dict[str, int]


class Replication(BaseModel):
    """Where a replica of the postgres backend is in the shared database's changes."""

    database: Literal["up", "unreachable"] = Field(..., description=(
        "Whether the replica reaches the database now (unreachable: reads serve the last snapshot, "
        "writes answer 503)."))
    applied_change: int = Field(..., description="The last change the served catalog includes.")
    database_change: int = Field(..., description="The latest change the replica knows the database has.")
    lag_changes: int = Field(..., description="database_change - applied_change.")
    lag_seconds: float = Field(..., description=(
        "How long the replica has known of a change it has not applied yet (0: up to date)."))
    last_error: str | None = Field(..., description="Why the database is unreachable, if it is.")


class Health(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [
        {"status": "ok"}, {"status": "ready", "model_version": "2025.01-chairs"},
        {"status": "degraded", "model_version": "2025.01-chairs", "catalog": {
            "database": "unreachable", "applied_change": 412, "database_change": 412, "lag_changes": 0,
            "lag_seconds": 0.0, "last_error": "connection refused"}}]})

    status: str = Field(..., description=(
        "ok (liveness), ready, or degraded: ready, but the catalog database cannot be reached "
        "(suggestions are served from the last snapshot; catalog writes answer 503)."))
    model_version: str | None = None
    catalog: Replication | None = Field(default=None, description=(
        "With the postgres catalog backend: this replica's place in the database's changes."))
