"""The settings the suggestion engine reads: a frozen subset of the service's ``Settings``.

The engine is made from the whole ``Settings`` (one class, one environment prefix, one place where
each limit is documented and checked) but reads only these fields, so that what changes its
answers is visible in one list. The values are validated once, by ``Settings``; here they are
copied, not checked again.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict

from service.settings import Settings


class EngineSettings(BaseModel):
    """What the engine reads of ``Settings`` (each field documented there, same name)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    # input
    min_points: int
    max_points: int
    seed: int
    default_k: int
    max_k: int
    max_exclude: int
    max_place_parts: int
    max_request_cost_ms: float
    # search
    faiss_threads: int
    overlap_max_batch: int
    neighbours_per_mode: int
    brute_force_max_parts: int
    exact_search_max_filtered: int
    # ranking and preferences
    infer_category: bool
    category_min_confidence: float
    suggest_order: Literal["share", "likelihood"]
    share_min_mode_weight: float
    share_order_head: int
    share_spread_sigmas: float
    diversity_min_mode_weight: float
    unfamiliar_diversity: bool
    unfamiliar_diversity_ratio: float
    rank_scale_weight: float
    rank_move_weight: float
    # placement, the complement check and regions
    fit_scale: bool
    scale_min: float
    scale_max: float
    suggest_complement_check: bool
    complement_candidates: int
    complement_part_samples: int
    complement_cover_distance: float
    complement_cover_share: float
    region_candidates: int
    # contact refinement
    suggest_refine_contact: bool
    contact_max_offset: float
    contact_tolerance: float
    contact_reach: float
    contact_search_points: int
    contact_part_samples: int
    contact_assembly_points: int
    contact_cache_parts: int
    contact_threads: int
    # warnings about unfamiliar queries
    ood_min_extent: float
    ood_max_extent: float
    ood_max_mode_distance: float
    familiarity_check: bool
    familiarity_threshold: float | None

    @classmethod
    def of(cls, settings: Settings) -> EngineSettings:
        """The engine's fields of ``settings``."""
        return cls.model_validate(settings.model_dump(include=set(cls.model_fields)))
