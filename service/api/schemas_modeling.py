"""Request and response schemas of the modeling routes: ``POST /assemble`` and ``POST /export``.

Like ``schemas``: static bounds here, limits that are settings checked by the engine side, and
request schemas that convert themselves into engine types.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from service.api.schemas import (
    _RING,
    SEED_MAX,
    Count,
    Finite,
    Flag,
    FrameIn,
    FrameOut,
    PartLinks,
    PointsIn,
    Vec3,
    _Strict,
)
from service.geometry.frames import Frame
from service.modeling.assembly import AssembleOptions
from service.modeling.export_mesh import ExportItem
from service.suggest.preferences import Preferences


class AssembleOptionsIn(_Strict):
    """How to grow the assembly (all optional)."""

    max_parts: Count | None = Field(default=None, description=(
        "Parts to add to the start (default COMPLEMENTME_ASSEMBLE_MAX_PARTS, at most "
        "COMPLEMENTME_MAX_ASSEMBLE_PARTS); fewer when no candidate is likely enough."))
    strategy: Literal["greedy", "sample"] = Field(default="greedy", description=(
        "greedy: the most likely eligible part at every step; sample: a mode drawn by its weight "
        "(seeded), then that mode's most likely part."))
    seed: Count = Field(default=0, ge=0, le=SEED_MAX, description="Seed of the sampler (0 to 2**63 - 1).")
    temperature: Finite = Field(default=1.0, gt=0, description=(
        "sample: mode probabilities proportional to weight ** (1 / temperature); > 1 flattens."))
    branching: Count = Field(default=1, ge=1, description=(
        "Children per state: 1 gives one chain; 2 gives the paper's binary tree of possibilities "
        "(at most COMPLEMENTME_ASSEMBLE_MAX_NODES parts over the tree)."))
    category: str | list[str] | None = Field(default=None, description=(
        "Candidates' categories (default: the start part's; for a cloud or mesh, the first added part's)."))
    style: str | list[str] | None = Field(default=None, description="Only parts of this catalog style.")
    exclude_shapes: list[str] = Field(default_factory=list, description=(
        "Source shapes never to take parts from."))
    mode_weights: list[Annotated[float, Field(ge=0, allow_inf_nan=False, strict=True)]] | None = Field(
        default=None, description="One factor per mixture mode multiplying g's mode weights at every step.")
    exclude_modes: list[Count] = Field(default_factory=list, description="Mixture modes never added.")
    refine_contact: Flag = Field(default=True, description=(
        "Nudge each placed part into contact with the parts placed before it."))
    frame: FrameIn | None = Field(default=None, description=(
        "The frame of the start points and parts, and of the answer."))
    fit_frame: Flag | None = Field(default=None, description=(
        "Estimate the complete object's frame from the start points or mesh (as `/suggest`'s "
        "`fit_frame`; the answer's `frame` is the one used). Omitted: fitted for mesh uploads sent "
        "without `frame` when COMPLEMENTME_FIT_FRAME_UPLOADS is on (off by default), never for JSON points."))

    def to_options(self) -> AssembleOptions:
        def tup(v: str | list[str] | None) -> tuple[str, ...]:
            return (v,) if isinstance(v, str) else tuple(v or ())
        return AssembleOptions(
            max_parts=self.max_parts, strategy=self.strategy, seed=self.seed, temperature=self.temperature,
            branching=self.branching, categories=tup(self.category), styles=tup(self.style),
            exclude_shapes=tuple(self.exclude_shapes),
            preferences=Preferences(mode_weights=tuple(self.mode_weights) if self.mode_weights else None,
                                    exclude_modes=tuple(self.exclude_modes)),
            refine_contact=self.refine_contact, frame=self.frame.to_frame() if self.frame else Frame())


class PlacedPartIn(_Strict):
    part_id: str = Field(..., description="Catalog part id.")
    translation: tuple[Finite, Finite, Finite] = Field(..., description=(
        "Where its bounding-box centre is (the request's frame), e.g. from an earlier answer."))


class AssembleRequest(PointsIn, AssembleOptionsIn):
    """Where to start and how to grow.

    The start is one catalog part (``part_id``, at its place in its source shape), or an
    assembly being edited: placed catalog parts (``parts``) and/or points (``points`` or
    ``points_base64``, e.g. a scan).
    """

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"part_id": "chair-0007/0", "max_parts": 6},
        {"part_id": "chair-0007/0", "strategy": "sample", "seed": 3, "branching": 2, "max_parts": 4},
        {"parts": [{"part_id": "chair-0007/0", "translation": [0.0, -0.16, 0.0]},
                   {"part_id": "chair-0011/2", "translation": [0.0, -0.55, 0.0]}], "max_parts": 3},
        {"points": _RING, "category": "chair", "refine_contact": False},
    ]})

    part_id: str | None = Field(default=None, description=(
        "Start from this catalog part, at its place in its source shape (canonical frame)."))
    parts: list[PlacedPartIn] | None = Field(default=None, description=(
        "Start from these placed catalog parts (at most COMPLEMENTME_MAX_ASSEMBLE_PARTS)."))

    @model_validator(mode="after")
    def _one_start(self) -> AssembleRequest:
        cloud = self.points is not None or self.points_base64 is not None
        if self.part_id is not None and (cloud or self.parts is not None):
            raise ValueError("part_id starts from one part: give no parts or points with it")
        if self.part_id is None and not cloud and not self.parts:
            raise ValueError("give a start: part_id, parts, points or points_base64")
        return self


class StepOut(BaseModel):
    node: int = Field(..., description="Index of this part in `nodes` (and in `steps` without branching).")
    parent: int | None = Field(..., description="The node this part was added to (null: the start).")
    depth: int = Field(..., description="Parts added up to and including this one.")
    part_id: str
    shape_id: str
    category: str
    label: str | None
    score: float = Field(..., description="Log-likelihood under the mixture predicted at that step.")
    mode: int
    mode_weight: float
    distance: float = Field(..., description=(
        "Distance of the part's embedding to its mode's mean, in RMS standard deviations."))
    translation: Vec3 = Field(..., description="Where the part's bounding-box centre goes (caller frame).")
    contact_offset: Vec3 = Field(..., description="The contact refinement's share of the translation.")
    bbox_min: Vec3
    bbox_max: Vec3
    scale: Vec3 = Field(default=(1.0, 1.0, 1.0), description=(
        "Per-axis scale (the request's frame axes) that fits the part, about its centre; the box "
        "above is the scaled one."))
    stop_reason: str | None = Field(..., description="On a leaf: why its branch ended.")
    added_by: Literal["likely", "unmet_mode", "missing_spot"] = Field(default="likely", description=(
        "Which rule of the step chose the part: `likely`, the most likely eligible candidate; "
        "`unmet_mode`, a heavy mode of g's mixture that no placed part explained; `missing_spot`, "
        "a spot most of the category's shapes nearest the assembly fill and it left empty "
        "(docs/modeling.md)."))
    added_message: str = Field(default="", description="`added_by` in words, for a user.")
    links: PartLinks


class StartOut(BaseModel):
    kind: Literal["part", "parts", "points", "mesh"]
    part_id: str | None = None
    translation: Vec3 | None = Field(default=None, description="Where the start part sits (caller frame).")
    points: int | None = Field(default=None, description="Start points received.")
    parts: int | None = Field(default=None, description="Start parts received.")
    links: PartLinks | None = None


class AssembleResponse(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{
        "model_version": "2025.01-chairs",
        "frame": {"center": [0, 0, 0], "radius": 1.0, "up_axis": "y", "scale": 1.0,
                  "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
        "start": {"kind": "part", "part_id": "chair-0007/0", "translation": [0.0, -0.16, 0.0],
                  "links": {"part": "/parts/chair-0007/0", "mesh": "/parts/chair-0007/0/mesh",
                            "points": "/parts/chair-0007/0/points"}},
        "category": "chair", "strategy": "greedy", "stop_reason": "complete",
        "steps": [{"node": 0, "parent": None, "depth": 1, "part_id": "chair-0011/2", "shape_id": "chair-0011",
                   "category": "chair", "label": "leg", "score": 41.2, "mode": 3, "mode_weight": 0.4,
                   "distance": 1.3, "translation": [0.0, -0.55, 0.0], "contact_offset": [0.0, -0.01, 0.0],
                   "bbox_min": [-0.4, -0.95, -0.4], "bbox_max": [0.4, -0.15, 0.4], "stop_reason": None,
                   "links": {"part": "/parts/chair-0011/2", "mesh": "/parts/chair-0011/2/mesh",
                             "points": "/parts/chair-0011/2/points"}}],
        "nodes": [], "timings": {"suggest": 0.02, "contact": 0.01, "total": 0.04},
    }]})

    model_version: str
    frame: FrameOut
    start: StartOut
    category: str | None = Field(..., description="The category candidates were restricted to.")
    strategy: str
    stop_reason: str = Field(..., description=(
        "Why the main chain ended: complete, max_parts, duplicates, unlikely, no_candidates or "
        "node_budget (docs/modeling.md)."))
    stop_message: str = Field(default="", description="The stop reason in words, for a user.")
    steps: list[StepOut] = Field(..., description="The main chain: the first choice at every step.")
    nodes: list[StepOut] = Field(..., description="Every placed part of the tree (with branching >= 2).")
    timings: dict[str, float] = Field(..., description=(
        "Seconds spent suggesting, choosing (eligibility tests), refining contact, in total."))
    frame_fitted: bool = Field(default=False, description=(
        "The service estimated `frame` from the start (`fit_frame`)."))


class ExportItemIn(_Strict):
    part_id: str = Field(..., description="Catalog part id.")
    translation: tuple[Finite, Finite, Finite] = Field(..., description=(
        "Where the part's bounding-box centre goes (the request's frame), as /suggest answers it."))
    scale: Annotated[float, Field(gt=0, le=1000, allow_inf_nan=False)] | tuple[
        Annotated[float, Field(gt=0, le=1000, allow_inf_nan=False)],
        Annotated[float, Field(gt=0, le=1000, allow_inf_nan=False)],
        Annotated[float, Field(gt=0, le=1000, allow_inf_nan=False)]] = Field(default=1.0, description=(
            "Scale about the part's centre: one number, or per axis of the request's frame as "
            "/suggest, /place and /assemble answer it (`scale`)."))


class ExportRequest(_Strict):
    """Placed parts to write as one mesh file."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"examples": [
        {"format": "glb", "parts": [{"part_id": "chair-0007/0", "translation": [0.0, -0.16, 0.0]},
                                    {"part_id": "chair-0011/2", "translation": [0.0, -0.55, 0.0],
                                     "scale": 1.0}]},
    ]})

    parts: list[ExportItemIn] = Field(..., description="At most COMPLEMENTME_MAX_EXPORT_PARTS parts.")
    format: Literal["glb", "obj"] = Field(default="glb", description="Binary glTF 2.0 or Wavefront OBJ.")
    frame: FrameIn | None = Field(default=None, description="The frame of the translations.")

    def to_items(self) -> list[ExportItem]:
        return [ExportItem(p.part_id, p.translation, p.scale) for p in self.parts]

