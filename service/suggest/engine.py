"""The suggestion engine: partial assembly in, ranked and placed catalog parts out.

One request (or a batch of them) goes through these steps, each one batched:

1. points to the canonical frame, resampled to the networks' N points (seeded);
2. g: the mixture {phi_k, mu_k, sigma_k} and h_query: the query's placement feature, one run
   each for the whole batch;
3. FAISS: the nearest catalog parts of every mean, all K means (of all queries sharing the same
   filter) in one search;
4. the union of candidates re-scored by the exact mixture log-likelihood, ranked, near-identical
   parts collapsed (catalog ``duplicate_of``), the top ones kept (k, or ``complement_candidates``
   when the complement check runs);
5. h_head over every kept candidate of the batch in one run, with the parts' precomputed
   features from catalog.npz; then the complement check (``service.suggest.complement``): parts that h
   places mostly onto the query's own surface, i.e. parts the query already has, move behind
   the others, and the top k stay;
6. contact refinement (``service.suggest.contact``; for suggestions only when asked, or when the setting
   ``suggest_refine_contact`` turns it on by default: it costs about ten times the rest of the
   request): each placed part nudged by at most ``contact_max_offset`` so it touches the
   query's points; translations and boxes mapped back to the caller's frame.

Requests may also reweight or exclude g's modes and ask for a mode-balanced gallery
(``service.suggest.preferences``).

No HTTP here: routes, the CLI and tests call these methods directly.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Any

import faiss
import numpy as np

from service.artifacts.loading import Artifacts
from service.errors import DeadlineError, InputError, PayloadTooLargeError, ServiceError
from service.geometry.frames import Frame
from service.geometry.inputs import check_points
from service.geometry.mesh import resample_points
from service.settings import Settings
from service.suggest.complement import covered_share, demote_covered
from service.suggest.contact import Assembly, ContactParams, PartContacts, Surface, refine_offset
from service.suggest.mixture import mixture_log_likelihood
from service.suggest.neighbours import BruteForceNeighbours
from service.suggest.preferences import Preferences, diverse_order, share_order
from service.suggest.region import Region

log = logging.getLogger(__name__)


# The cost model of a suggestion query, in estimated CPU milliseconds (max_request_cost_ms,
# batch_max_cost_ms). Measured in process on the shipped artifacts (engine.suggest_batch, one
# core, training running on the other): a query cost 3.7 ms in a batch of 32 and 6-8 ms alone;
# 100k points against 1.5k added about 5 ms (frame, resampling); contact refinement cost 37-85 ms
# for k = 10 and 0.93-1.38 s for k = 100, 10-14 ms per refined part.
QUERY_COST_MS = 4.0
POINT_COST_MS = 0.05 / 1000
REFINED_PART_COST_MS = 12.0
# A region query searches 256 neighbours per mode, and places and checks 256 candidates: it cost
# about 5 ms more than the same query without a region (13 ms against 7.7 ms, best of 5, a chair
# seat with a category filter, trainings running on both cores), most of it in the wider search.
REGION_PART_COST_MS = 5.0 / 256


@dataclass(frozen=True)
class SuggestOptions:
    """What a caller may ask of one suggestion query (all optional)."""

    k: int | None = None                     # suggestions to return (None: the default setting)
    categories: tuple[str, ...] = ()         # only parts from these categories (empty: all)
    exclude_parts: tuple[str, ...] = ()      # never these parts, nor their near-duplicates
    exclude_shapes: tuple[str, ...] = ()     # never parts of these source shapes
    collapse_duplicates: bool = True         # one part per near-duplicate group
    frame: Frame = field(default_factory=Frame)
    refine_contact: bool | None = None       # nudge placements into contact (suggest.contact);
                                             # None: the setting suggest_refine_contact
    complement_check: bool | None = None     # demote parts the query already has (suggest.complement);
                                             # None: the setting suggest_complement_check
    fit_scale: bool | None = None            # fit parts in size (h's scale head); None: setting fit_scale
    styles: tuple[str, ...] = ()             # only parts of these catalog styles (empty: all)
    preferences: Preferences = field(default_factory=Preferences)  # mode weights, exclusions, gallery
    region: Region | None = None             # only parts placed in this spot (caller's frame)


@dataclass
class Suggestion:
    """One ranked suggestion, placed in the caller's frame.

    Shapes:
        translation, bbox_min, bbox_max: (3,) float64 in the caller's frame.
    """

    rank: int
    part_index: int
    part_id: str
    shape_id: str
    category: str
    label: str | None
    score: float          # log-likelihood of the part's embedding under the mixture
    mode: int             # mixture mode that explains the part best
    mode_weight: float    # that mode's weight phi_k
    duplicates: int       # catalog parts in this part's near-duplicate group (1: none)
    translation: np.ndarray
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    contact_offset: np.ndarray = field(default_factory=lambda: np.zeros(3))  # part of translation
    scale: np.ndarray = field(default_factory=lambda: np.ones(3))  # per axis, about the part's centre


@dataclass(frozen=True)
class InferredCategory:
    """The category g's category head reads from a query that named none."""

    category: str
    confidence: float     # the head's probability of that category
    applied: bool         # the suggestions were kept in it (confidence >= category_min_confidence)


@dataclass(frozen=True)
class QueryWarning:
    """Something about a query that the answer should not hide (status stays 200)."""

    code: str             # "frame", "category_unsure", "unfamiliar", "region_empty"
    message: str          # what is wrong and how to fix it


@dataclass(frozen=True)
class RegionReport:
    """How a region query went: candidates placed and tested, and how many fell in the region."""

    placed: int           # best-ranked candidates placed by h and tested (at most region_candidates)
    inside: int           # of those, placed with their box reaching into the region
    nearest_gap: float | None  # when none is inside: the nearest placed box's distance (caller units)


@dataclass
class SuggestResult:
    """The answer to one query.

    Shapes:
        mode_weights: (K,) float32.   mode_means, mode_sigmas: (K, D) float32 (the mixture's modes).
    """

    suggestions: list[Suggestion]
    mode_weights: np.ndarray
    frame: Frame
    n_input_points: int
    candidates: int                       # distinct parts re-scored before ranking
    timings: dict[str, float] = field(default_factory=dict)  # seconds per stage (whole batch)
    mode_means: np.ndarray | None = None
    mode_sigmas: np.ndarray | None = None
    inferred_category: InferredCategory | None = None
    warnings: list[QueryWarning] = field(default_factory=list)
    region: RegionReport | None = None    # set when the query gave a region


@dataclass
class Placement:
    """Where one chosen part goes.

    Shapes:
        translation, bbox_min, bbox_max, contact_offset: (3,) caller frame.
    """

    part_index: int
    part_id: str
    translation: np.ndarray
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    contact_offset: np.ndarray = field(default_factory=lambda: np.zeros(3))  # part of translation
    scale: np.ndarray = field(default_factory=lambda: np.ones(3))  # per axis, about the part's centre


@dataclass
class PlaceResult:
    placements: list[Placement]
    frame: Frame
    n_input_points: int
    timings: dict[str, float] = field(default_factory=dict)


# A query's ranked candidates: kept rows (k',), log-likelihoods (k',), best modes (k',) and
# the number of candidates scored.
_Ranked = tuple[np.ndarray, np.ndarray, np.ndarray, int]


@dataclass
class _Query:
    """One validated query inside a batch: canonical points and its resolved filter."""

    item: int
    points: np.ndarray                 # (N, 3) float32 canonical, resampled
    full: np.ndarray                   # (M, 3) float32 canonical, as given (contact refinement)
    n_input: int
    options: SuggestOptions
    k: int
    allowed: np.ndarray | None         # (P,) bool, None when nothing is filtered
    filter_key: tuple[tuple[str, ...], ...]
    inferred: InferredCategory | None = None
    warnings: list[QueryWarning] = field(default_factory=list)
    region: Region | None = None       # the request's region in the canonical frame
    region_report: RegionReport | None = None


class SuggestionEngine:
    """Suggest and place catalog parts for partial assemblies, on loaded artifacts."""

    def __init__(self, artifacts: Artifacts, settings: Settings):
        self.artifacts = artifacts
        self.settings = settings
        self.catalog = artifacts.catalog
        self.networks = artifacts.networks
        self.index = artifacts.index
        self.brute_force = self._brute_force_search()
        self.contacts = PartContacts(
            ContactParams(max_offset=settings.contact_max_offset, tolerance=settings.contact_tolerance,
                          search_points=settings.contact_search_points, seed=settings.seed),
            part_samples=settings.contact_part_samples, assembly_points=settings.contact_assembly_points,
            cache_entries=settings.contact_cache_parts)
        self._styles: tuple[int, np.ndarray] | None = None  # (catalog id, style per part)

    @property
    def model_version(self) -> str:
        return self.artifacts.model_version

    # ---------------------------------------------------------------- step 1: input
    def canonical(self, points: np.ndarray, frame: Frame) -> np.ndarray:
        """Check limits and map to the canonical frame.

        Shapes:
            points: (M, 3) in the caller's frame -> (M, 3) float32 canonical.
        """
        s = self.settings
        pts = frame.to_canonical(check_points(points, s.min_points, s.max_points))
        if not np.isfinite(pts).all():  # finite input, but a frame that blows it up (tiny radius)
            raise InputError("non_finite_points", "points are not finite in the canonical frame; "
                             "check the frame's center and radius")
        return pts

    def resample(self, canonical: np.ndarray) -> np.ndarray:
        """Canonical points resampled to the networks' N points (seeded): (M, 3) -> (N, 3) float32."""
        n = self.artifacts.n_points
        pts = canonical
        if len(pts) != n:
            pts = resample_points(pts, n, self.settings.seed)
        return np.ascontiguousarray(pts, dtype=np.float32)

    def prepare(self, points: np.ndarray, frame: Frame) -> np.ndarray:
        """Check limits, map to the canonical frame and resample to N points.

        Shapes:
            points: (M, 3) in the caller's frame -> (N, 3) float32 canonical.
        """
        return self.resample(self.canonical(points, frame))

    def _resolve(self, item: int, points: np.ndarray, options: SuggestOptions) -> _Query:
        cat = self.catalog
        k = self._checked_k(options)
        allowed: np.ndarray | None = None
        if options.categories:
            allowed = np.isin(cat.category_of, cat.category_codes(list(options.categories)))
        if options.exclude_parts:
            groups = cat.group[[cat.lookup(p) for p in options.exclude_parts]]
            keep = ~np.isin(cat.group, groups)
            allowed = keep if allowed is None else allowed & keep
        if options.exclude_shapes:
            keep = ~np.isin(cat.shape_of, [cat.shape_code(sid) for sid in options.exclude_shapes])
            allowed = keep if allowed is None else allowed & keep
        if options.styles:
            keep = self._style_mask(options.styles)
            allowed = keep if allowed is None else allowed & keep
        key = (tuple(sorted(options.categories)), tuple(sorted(options.exclude_parts)),
               tuple(sorted(options.exclude_shapes)), tuple(sorted(options.styles)))
        full = self.canonical(points, options.frame)
        region = options.region.in_frame(options.frame) if options.region is not None else None
        return _Query(item, self.resample(full), full, len(points), options, k, allowed, key,
                      warnings=self._frame_warnings(full), region=region)

    def _frame_warnings(self, canonical: np.ndarray) -> list[QueryWarning]:
        """A ``frame`` warning when the points are far from the model's unit-radius frame.

        Shapes:
            canonical: (M, 3) float32.
        """
        s = self.settings
        lo, hi = canonical.min(axis=0), canonical.max(axis=0)
        reach = float(np.linalg.norm(canonical - (lo + hi) / 2, axis=1).max())
        if s.ood_min_extent <= reach <= s.ood_max_extent:
            return []
        return [QueryWarning("frame", f"the points reach {reach:.3g} from their centre in the model's frame, "
                             "where a whole object reaches 1: the answer is unlikely to fit; give "
                             "frame.radius (the object's radius in your units) and frame.center")]

    def _infer_category(self, q: _Query, probs: np.ndarray | None) -> None:
        """Read the query's category from g's head when it named none; filter when sure enough.

        Shapes:
            probs: (C,) over the manifest's categories, or None without a head.
        """
        s, cat = self.settings, self.catalog
        names = self.artifacts.manifest.get("categories") or []
        if probs is None or q.options.categories or not s.infer_category or len(names) != len(probs):
            return
        best = int(np.argmax(probs))
        name, confidence = str(names[best]), float(probs[best])
        in_catalog = name in cat.categories
        # A style filter already names what the caller wants (styles belong to one category):
        # the inference is reported, not applied.
        applied = confidence >= s.category_min_confidence and in_catalog and not q.options.styles
        q.inferred = InferredCategory(name, confidence, applied)
        if q.options.styles:
            return
        if applied:
            keep = cat.category_of == cat.category_codes([name])[0]
            q.allowed = keep if q.allowed is None else q.allowed & keep
            q.filter_key = ((name,), *q.filter_key[1:])
        else:
            q.warnings.append(QueryWarning(
                "category_unsure", f"the partial assembly looks most like a {name} (probability "
                f"{confidence:.2f}), which is not sure enough to keep the suggestions in one category; "
                "name the category (categories) or check the frame"))

    def _style_mask(self, styles: tuple[str, ...]) -> np.ndarray:
        """Parts whose catalog ``style`` is one of ``styles``; ``InputError`` naming unknown styles."""
        cat = self.catalog
        if self._styles is None or self._styles[0] != id(cat.records) or len(self._styles[1]) != len(cat):
            self._styles = (id(cat.records), np.array([str(r.get("style") or "") for r in cat.records]))
        per_part = self._styles[1]
        known = set(per_part.tolist()) - {""}
        unknown = [s for s in styles if s not in known]
        if unknown:
            raise InputError("unknown_style", f"unknown style(s) {', '.join(map(repr, unknown))}; known "
                             f"styles: {', '.join(sorted(known))}")
        return np.isin(per_part, list(styles))

    def _checks_complement(self, options: SuggestOptions) -> bool:
        """Whether a suggestion query's candidates go through the complement check."""
        return _or_default(options.complement_check, self.settings.suggest_complement_check)

    def _shortlist(self, q: _Query) -> int:
        """Ranked candidates kept for placement: k, or more when the complement check will reorder
        them, or the region's candidate budget when only parts placed in a region count."""
        n = max(q.k, self.settings.complement_candidates) if self._checks_complement(q.options) else q.k
        return max(n, self.settings.region_candidates) if q.region is not None else n

    def _per_mode(self, q: _Query) -> int:
        """Nearest parts a query needs of each mode's mean: at least k, so that a large k is not
        starved of candidates, and the region's candidate budget for a region query."""
        return max(q.k, self.settings.region_candidates) if q.region is not None else q.k

    def _refines(self, options: SuggestOptions) -> bool:
        """Whether a suggestion query's placements get contact refinement."""
        return _or_default(options.refine_contact, self.settings.suggest_refine_contact)

    # ---------------------------------------------------------------- cost, checked up front
    def query_cost(self, n_points: int, options: SuggestOptions) -> float:
        """Estimated CPU milliseconds of one suggestion query (see ``max_request_cost_ms``)."""
        k = self.settings.default_k if options.k is None else options.k
        refined = max(0, k) if self._refines(options) else 0
        placed = self.settings.region_candidates if options.region is not None else 0
        return (QUERY_COST_MS + POINT_COST_MS * max(0, n_points) + REFINED_PART_COST_MS * refined
                + REGION_PART_COST_MS * placed)

    def check_query(self, n_points: int, options: SuggestOptions) -> float:
        """Refuse what can be refused before a query joins a batch; its estimated cost.

        Raises ``InputError`` for k out of range, too many exclusions or preferences that leave
        no mode (the checks of ``_resolve`` that need neither points nor the catalog).
        """
        self._checked_k(options)
        return self.query_cost(n_points, options)

    def _checked_k(self, options: SuggestOptions) -> int:
        """The query's k, after the checks that need neither points nor the catalog."""
        limits = self.settings.limits
        k = limits.k(options.k)
        limits.check_exclusions(len(options.exclude_parts) + len(options.exclude_shapes))
        options.preferences.check(self.artifacts.n_modes)
        return k

    def check_budget(self, cost: float, queries: int = 1) -> None:
        """``PayloadTooLargeError`` when a request's estimated cost is over ``max_request_cost_ms``."""
        budget = self.settings.max_request_cost_ms
        if cost > budget:
            raise PayloadTooLargeError("over_budget", (
                f"the request's {queries} quer{'y' if queries == 1 else 'ies'} would take about "
                f"{cost:.0f} ms of CPU, over the budget of {budget:g} ms per request "
                "(COMPLEMENTME_MAX_REQUEST_COST_MS); ask for fewer items, a smaller k or no "
                "refine_contact (12 ms per refined suggestion), or split the request"))

    # ---------------------------------------------------------------- public API
    def suggest(self, points: np.ndarray, options: SuggestOptions | None = None) -> SuggestResult:
        """Ranked, placed suggestions for one partial assembly; raises ``ServiceError`` on bad input.

        Shapes:
            points: (M, 3) in the caller's frame (``options.frame``).
        """
        result = self.suggest_batch([(points, options or SuggestOptions())])[0]
        if isinstance(result, ServiceError):
            raise result
        return result

    def suggest_batch(self, items: list[tuple[np.ndarray, SuggestOptions]],
                      deadlines: Sequence[float | None] | None = None) -> list[SuggestResult | ServiceError]:
        """Suggestions for many queries with batched inference; a bad item yields its own error.

        Returns one entry per item, in order: a ``SuggestResult`` or the ``ServiceError`` that
        item raised (the other items are unaffected: every step past the batched network runs
        is checked per query). ``deadlines`` (``time.monotonic()``, one per item, None: none):
        an item past its deadline before contact refinement, the costly step, gets a
        ``DeadlineError`` instead of being refined.
        """
        t0 = time.perf_counter()
        # OpenMP's thread count is per calling thread: set it in this one (the batcher's worker)
        # for the FAISS calls below, or FAISS starts a team of one thread per core for every
        # calling thread (searches took 13 ms instead of 0.1 ms in the server).
        faiss.omp_set_num_threads(self.settings.faiss_threads)
        errors: dict[int, ServiceError] = {}
        queries: list[_Query] = []
        for i, (points, options) in enumerate(items):
            try:
                queries.append(self._resolve(i, points, options))
            except ServiceError as exc:
                errors[i] = exc
        if not queries:
            return [errors[i] for i in range(len(items))]
        timings = {"prepare": time.perf_counter() - t0}
        batch = np.stack([q.points for q in queries])  # (B, N, 3)
        # h_query needs only the points and is needed only by h_head: it runs on a thread of its
        # own meanwhile (ONNX Runtime releases the GIL), beside g, the search and the scoring.
        beside = (_BESIDE.submit(_timed, self.networks.query_features, batch)
                  if len(queries) <= self.settings.overlap_max_batch else None)
        t = time.perf_counter()
        mix = self.networks.mixture(batch)
        for b, q in enumerate(queries):
            self._infer_category(q, None if mix.category_probs is None else mix.category_probs[b])
        timings["g"] = time.perf_counter() - t
        t = time.perf_counter()
        candidates = self._search(queries, mix.means)
        timings["search"] = time.perf_counter() - t

        t = time.perf_counter()
        ranked: dict[int, _Ranked] = {}  # query position b -> its ranked candidates
        for b, q in enumerate(queries):
            with _own_error(q, errors):
                ranked[b] = self._rank(q, candidates[b], mix.weights[b], mix.means[b], mix.sigmas[b])
        timings["score"] = time.perf_counter() - t

        qf, timings["h_query"] = (beside.result() if beside is not None
                                  else _timed(self.networks.query_features, batch))
        # One h_head run over every kept candidate of every query.
        t = time.perf_counter()
        rows = np.concatenate([np.zeros(0, np.int64)] + [np.full(len(r[0]), b) for b, r in ranked.items()]
                              ).astype(np.int64)
        parts = np.concatenate([np.zeros(0, np.int64)] + [r[0] for r in ranked.values()]).astype(np.int64)
        translations, scales = (np.zeros((0, 3), np.float32), np.ones((0, 3), np.float32))
        if len(parts):
            translations, scales = self.networks.place_and_fit(qf[rows], self.catalog.part_features[parts])
        timings["h_head"] = time.perf_counter() - t
        t = time.perf_counter()
        placed: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
        fitted: dict[int, np.ndarray] = {}
        for b, (idx, scores, modes, _) in ranked.items():
            q = queries[b]
            tr = translations[rows == b]
            with _own_error(q, errors):
                fit = self._fitted(scales[rows == b], q.options.fit_scale)
                if q.region is not None:
                    inside = self._in_region(q, idx, tr, fit)
                    idx, scores, modes = idx[inside], scores[inside], modes[inside]
                    tr, fit = tr[inside], fit[inside]
                order = self._complement_order(q, idx, tr)
                placed[b] = (idx[order], scores[order], modes[order], tr[order])
                fitted[b] = fit[order]
        timings["complement"] = time.perf_counter() - t
        t = time.perf_counter()
        offsets: dict[int, np.ndarray] = {}
        for b, (idx, _, _, tr) in placed.items():
            q = queries[b]
            deadline = deadlines[q.item] if deadlines is not None else None
            with _own_error(q, errors):
                if deadline is not None and time.monotonic() > deadline:
                    raise DeadlineError("deadline_exceeded", "the request's deadline passed before its "
                                        "placements were refined")
                offsets[b] = (self.contact_offsets(q.full, idx, tr) if self._refines(q.options) and len(idx)
                              else np.zeros((len(idx), 3)))
        timings["contact"] = time.perf_counter() - t

        out: dict[int, SuggestResult | ServiceError] = dict(errors)
        for b, off in offsets.items():
            q = queries[b]
            idx, scores, modes, tr = placed[b]
            with _own_error(q, errors):
                found = self._suggestions(idx, scores, modes, mix.weights[b], tr, off, q.options.frame,
                                          fitted[b])
                out[q.item] = SuggestResult(
                    suggestions=found,
                    mode_weights=mix.weights[b], frame=q.options.frame, n_input_points=q.n_input,
                    candidates=ranked[b][3], timings=timings, mode_means=mix.means[b],
                    mode_sigmas=mix.sigmas[b], inferred_category=q.inferred,
                    warnings=q.warnings + self._familiarity_warnings(idx, modes, mix.means[b], mix.sigmas[b]),
                    region=q.region_report)
        out.update(errors)
        timings["total"] = time.perf_counter() - t0
        return [out[i] for i in range(len(items))]

    def place(self, points: np.ndarray, part_ids: list[str], frame: Frame | None = None,
              refine_contact: bool = True, fit_scale: bool | None = None) -> PlaceResult:
        """Translations (and placed boxes) of chosen parts next to a partial assembly.

        Shapes:
            points: (M, 3) in the caller's frame.
        """
        frame = frame or Frame()
        if not part_ids:
            raise InputError("no_parts", "give at least one part id to place")
        if len(part_ids) > self.settings.max_place_parts:
            raise InputError("too_many_parts", f"{len(part_ids)} part ids given, at most "
                             f"{self.settings.max_place_parts} are accepted")
        idx = np.array([self.catalog.lookup(p) for p in part_ids], dtype=np.int64)
        t0 = time.perf_counter()
        full = self.canonical(points, frame)
        canonical = self.resample(full)
        timings = {"prepare": time.perf_counter() - t0}
        t = time.perf_counter()
        qf = self.networks.query_features(canonical[None])
        timings["h_query"] = time.perf_counter() - t
        t = time.perf_counter()
        tr, raw_scale = self.networks.place_and_fit(np.repeat(qf, len(idx), axis=0),
                                                    self.catalog.part_features[idx])
        scale = self._fitted(raw_scale, fit_scale)
        timings["h_head"] = time.perf_counter() - t
        t = time.perf_counter()
        off = self.contact_offsets(full, idx, tr) if refine_contact else np.zeros((len(idx), 3))
        timings["contact"] = time.perf_counter() - t
        trans, lo, hi = self._placed(idx, tr + off, frame, scale)
        off_caller = off @ frame.rotation * frame.radius
        scale_caller = _caller_scale(scale, frame)
        placements = [Placement(int(i), self.catalog.part_ids[i], trans[j], lo[j], hi[j], off_caller[j],
                                scale_caller[j])
                      for j, i in enumerate(idx)]
        return PlaceResult(placements, frame, len(points), timings)

    def warmup(self) -> SuggestResult:
        """Run one suggestion and one placement on a query made from the first catalog shape;
        the suggestion's result (a test checks it is not empty)."""
        cat = self.catalog
        parts = np.flatnonzero(cat.shape_of == cat.shape_of[0])
        points = np.concatenate([cat.part_points(int(i)) + cat.translations[i] for i in parts])
        result = self.suggest(points, SuggestOptions(k=min(5, self.settings.max_k)))
        if result.suggestions:
            self.place(points, [result.suggestions[0].part_id])
        log.info("warm-up passed: %d suggestions in %.1f ms", len(result.suggestions),
                 1000 * result.timings.get("total", 0.0))
        return result

    def contact_offsets(self, full: np.ndarray, rows: np.ndarray, translations: np.ndarray) -> np.ndarray:
        """Contact refinement offsets (canonical) of parts placed next to canonical points.

        Shapes:
            full: (M, 3) canonical query points; rows: (n,); translations: (n, 3) -> (n, 3) float64.
        """
        return self.refine_against(self.contacts.assembly_from_points(full), rows, translations)

    def refine_against(self, assembly: Assembly, rows: np.ndarray, translations: np.ndarray,
                       scales: np.ndarray | None = None) -> np.ndarray:
        """Contact refinement offsets of catalog parts placed against an assembly.

        The bounded search first (``contact_max_offset``); a part it leaves floating (apart from
        the assembly, not sunk into it) gets a second search reaching ``contact_reach``, so that
        a part h left hanging in the air is pulled onto what it attaches to. ``scales``: per-axis
        sizes the parts are fitted to (None: as in the catalog).

        Shapes:
            rows: (n,); translations: (n, 3) canonical; scales: (n, 3) -> (n, 3) float64 offsets.
        """
        t = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
        if scales is None or np.all(np.asarray(scales) == 1.0):
            found = self.contacts.refine(self.catalog, rows, t, assembly)
            surfaces = [lambda j=j: self.contacts.part_surface(self.catalog, int(rows[j])).moved(t[j])
                        for j in range(len(t))]
        else:
            surfaces = [lambda j=j: scaled_surface(self.contacts.part_surface(self.catalog, int(rows[j])),
                                                   scales[j]).moved(t[j]) for j in range(len(t))]
            found = [refine_offset(make(), assembly, self.contacts.params) for make in surfaces]
        offsets = np.array([r.offset for r in found], dtype=np.float64).reshape(-1, 3)
        params = self.contacts.params
        reach = replace(params, max_offset=self.settings.contact_reach)
        if reach.max_offset <= params.max_offset:
            return offsets
        for j, r in enumerate(found):
            if not r.resolved and r.before.depth <= params.tolerance < r.before.gap:
                offsets[j] = refine_offset(surfaces[j](), assembly, reach).offset
        return offsets

    # ---------------------------------------------------------------- steps 3-6
    def _search(self, queries: list[_Query], means: np.ndarray) -> list[np.ndarray]:
        """Candidate catalog rows per query: the nearest parts to any of its modes' means (numpy
        brute force for small flat catalogs, else FAISS).

        Queries sharing a filter share one search call (all their K means at once).

        Shapes:
            means: (B, K, D) -> list of B arrays of distinct catalog rows (int64).
        """
        K = means.shape[1]
        groups: dict[tuple, list[int]] = defaultdict(list)
        for b, q in enumerate(queries):
            groups[q.filter_key].append(b)
        found: list[np.ndarray] = [np.zeros(0, np.int64)] * len(queries)
        for members in groups.values():
            allowed = queries[members[0]].allowed
            want = max(self.settings.neighbours_per_mode, *(self._per_mode(queries[b]) for b in members))
            nn = min(len(self.catalog), want)
            flat = np.ascontiguousarray(means[members].reshape(-1, means.shape[2]), dtype=np.float32)
            if self.brute_force is not None:
                unions = self.brute_force.neighbour_union(flat, K, nn, allowed)
                for b, ids in zip(members, unions, strict=True):
                    found[b] = ids
                continue
            labels = self._faiss_search(flat, nn, allowed)
            for j, b in enumerate(members):
                ids = labels[j * K:(j + 1) * K].ravel()
                ids = np.unique(ids[ids >= 0])
                if allowed is not None:
                    ids = ids[allowed[ids]]  # also covers indexes that ignore selectors
                found[b] = ids
        return found

    def _brute_force_search(self) -> BruteForceNeighbours | None:
        """numpy brute force in place of a flat index, for catalogs up to ``brute_force_max_parts``."""
        small = len(self.catalog) <= self.settings.brute_force_max_parts
        if not (small and isinstance(self.index, faiss.IndexFlat)):
            return None
        return BruteForceNeighbours(self.catalog.embeddings,
                                    inner_product=self.index.metric_type == faiss.METRIC_INNER_PRODUCT)

    def _faiss_search(self, x: np.ndarray, nn: int, allowed: np.ndarray | None) -> np.ndarray:
        """FAISS labels (Q, nn) of the nearest parts, restricted to ``allowed`` rows if given."""
        if allowed is None:
            return self.index.search(x, nn)[1]
        rows = np.flatnonzero(allowed)
        if len(rows) <= self.settings.exact_search_max_filtered and (
                len(rows) < len(allowed) // 2 or not isinstance(self.index, faiss.IndexFlat)):
            # An approximate index probes the lists (or graph nodes) nearest the query, and few of
            # them may hold parts that pass a narrow filter; a flat index with a selector checks
            # every part one by one (1.1 ms for a category of the shipped catalog, against 0.1 ms
            # for the same search over that category's rows): search those parts exactly instead.
            return self._exact_subset(x, nn, rows)
        packed = np.packbits(allowed, bitorder="little")
        sel = faiss.IDSelectorBitmap(len(allowed), faiss.swig_ptr(packed))
        params = _search_parameters(self.index, sel)
        if params is None:  # an index type without selector support: filter afterwards
            return self.index.search(x, min(len(self.catalog), 4 * nn))[1]
        return self.index.search(x, nn, params=params)[1]

    def _exact_subset(self, x: np.ndarray, nn: int, rows: np.ndarray) -> np.ndarray:
        """Exact nearest catalog rows among ``rows``: labels (Q, nn), -1 past the subset's size."""
        out = np.full((len(x), nn), -1, dtype=np.int64)
        if len(rows) == 0:
            return out
        k = min(nn, len(rows))
        sub = np.ascontiguousarray(self.catalog.embeddings[rows], dtype=np.float32)
        _, found = faiss.knn(x, sub, k, metric=self.index.metric_type)
        out[:, :k] = np.where(found >= 0, rows[np.maximum(found, 0)], -1)
        return out

    def _rank(self, q: _Query, cand: np.ndarray, weights: np.ndarray, means: np.ndarray,
              sigmas: np.ndarray) -> _Ranked:
        """Score candidates under the mixture, sort, collapse duplicates, keep the top k.

        Returns kept rows (k',), their log-likelihoods (k',), best modes (k',) and the number
        of candidates scored.
        """
        if len(cand) == 0:
            empty = np.zeros(0, np.int64)
            return empty, np.zeros(0), empty, 0
        prefs = q.options.preferences
        emb = self.catalog.embeddings[cand]
        n_scored = len(cand)
        if prefs.exclude_modes:  # drop the parts g's own mixture puts in an excluded mode
            _, own_mode = mixture_log_likelihood(emb, weights, means, sigmas)
            keep_own = ~np.isin(own_mode, prefs.exclude_modes)
            cand, emb = cand[keep_own], emb[keep_own]
        w = prefs.weights(weights) if prefs.reweights else weights
        live = np.flatnonzero(w > 0)  # a mode weighted 0 contributes nothing (not even a floor)
        ll, best = mixture_log_likelihood(emb, w[live], means[live], sigmas[live])
        mode = live[best]
        order = np.argsort(-ll, kind="stable")  # ties keep catalog order: deterministic
        cand, ll, mode = cand[order], ll[order], mode[order]
        if q.options.collapse_duplicates:
            _, first = np.unique(self.catalog.group[cand], return_index=True)
            keep = np.sort(first)
        else:
            keep = np.arange(len(cand))
        if prefs.diversity:
            keep = keep[diverse_order(mode[keep], w, self.settings.diversity_min_mode_weight)]
        elif self.settings.suggest_order == "share":
            keep = keep[share_order(mode[keep], w, self.settings.share_min_mode_weight)]
        keep = keep[:self._shortlist(q)]
        return cand[keep], ll[keep], mode[keep], n_scored

    def _in_region(self, q: _Query, idx: np.ndarray, translations: np.ndarray, scales: np.ndarray
                   ) -> np.ndarray:
        """Which placed candidates reach into the query's region; records the query's region report.

        Judged on h's placement with the fitted scale, before contact refinement (which moves a
        part by at most ``contact_max_offset``).

        Shapes:
            idx (P,), translations (P, 3) canonical, scales (P, 3) -> (P,) bool.
        """
        assert q.region is not None
        cat = self.catalog
        t, sc = translations.astype(np.float64), scales.astype(np.float64)
        gap = q.region.gap(t + sc * cat.bbox_min[idx], t + sc * cat.bbox_max[idx])
        inside = gap <= 0.0
        nearest = None
        if len(gap) and not inside.any():
            nearest = float(gap.min()) * q.options.frame.radius
            q.warnings.append(QueryWarning("region_empty", (
                f"none of the {len(gap)} best-ranked candidates is placed in the region: the nearest "
                f"placed part stays {nearest:.3g} from it (in the request's units); give a larger "
                "region, or one nearer the partial assembly, where parts attach (placements follow "
                "the points: a spot far from them gets nothing)")))
        elif not len(gap):
            q.warnings.append(QueryWarning("region_empty", (
                "no candidate to place: the filters (category, style, exclusions, modes) leave none")))
        q.region_report = RegionReport(placed=len(gap), inside=int(inside.sum()), nearest_gap=nearest)
        return inside

    def _complement_order(self, q: _Query, idx: np.ndarray, translations: np.ndarray) -> np.ndarray:
        """The top k of a query's ranked, placed candidates (indices), covered parts demoted."""
        if not self._checks_complement(q.options) or len(idx) == 0:
            return np.arange(min(len(idx), q.k))
        s = self.settings
        samples = self.catalog.part_samples(idx, s.complement_part_samples)
        share = covered_share(q.points, samples, translations.astype(np.float32), s.complement_cover_distance)
        return demote_covered(share, s.complement_cover_share)[:q.k]

    def _placed(self, idx: np.ndarray, translations: np.ndarray, frame: Frame, scales: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Canonical translations of parts to caller-frame translations and placed boxes.

        The box is the part's catalog box scaled about its centre (the translation) by its
        fitted per-axis scale.

        Shapes:
            idx (P,), translations (P, 3), scales (P, 3) canonical axes -> (P, 3) x 3, caller frame.
        """
        t = translations.astype(np.float64)
        sc = scales.astype(np.float64)
        cat = self.catalog
        lo, hi = frame.box_from_canonical(t + sc * cat.bbox_min[idx], t + sc * cat.bbox_max[idx])
        return frame.from_canonical(t), lo, hi

    def _fitted(self, raw: np.ndarray, asked: bool | None) -> np.ndarray:
        """Fitting scales as served: clipped to the settings' range, or ones when fitting is off.

        Shapes:
            raw (P, 3) -> (P, 3) float64.
        """
        s = self.settings
        if not _or_default(asked, s.fit_scale):
            return np.ones((len(raw), 3))
        return np.clip(raw.astype(np.float64), s.scale_min, s.scale_max)

    def _familiarity_warnings(self, idx: np.ndarray, modes: np.ndarray, means: np.ndarray,
                              sigmas: np.ndarray) -> list[QueryWarning]:
        """An ``unfamiliar`` warning when even the best suggestion is far from its mode's mean.

        Shapes:
            idx (P,) ranked rows, modes (P,); means, sigmas (K, D).
        """
        if len(idx) == 0:
            return []
        k = int(modes[0])
        z = (self.catalog.embeddings[int(idx[0])] - means[k]) / sigmas[k]
        distance = float(np.sqrt(np.mean(np.square(z))))
        if distance <= self.settings.ood_max_mode_distance:
            return []
        return [QueryWarning("unfamiliar", f"the best suggestion lies {distance:.1f} sigmas from what the "
                             "model expects (in-distribution queries stay within "
                             f"{self.settings.ood_max_mode_distance:g}): the partial assembly is unlike "
                             "anything the model was trained on; check the frame (frame.radius, "
                             "frame.center, frame.up) and the category")]

    def _suggestions(self, idx: np.ndarray, scores: np.ndarray, modes: np.ndarray, weights: np.ndarray,
                     translations: np.ndarray, offsets: np.ndarray, frame: Frame, scales: np.ndarray
                     ) -> list[Suggestion]:
        cat = self.catalog
        trans, lo, hi = self._placed(idx, translations + offsets, frame, scales)
        off_caller = offsets @ frame.rotation * frame.radius
        scale_caller = _caller_scale(scales, frame)
        out = []
        for r, i in enumerate(idx.tolist()):
            rec = cat.records[i]
            out.append(Suggestion(
                rank=r + 1, part_index=i, part_id=rec["part_id"], shape_id=rec["shape_id"],
                category=rec["category"], label=rec["label"], score=float(scores[r]),
                mode=int(modes[r]), mode_weight=float(weights[modes[r]]),
                duplicates=int(cat.group_size[i]), translation=trans[r], bbox_min=lo[r], bbox_max=hi[r],
                contact_offset=off_caller[r], scale=scale_caller[r]))
        return out


# The one thread (per process, shared by every engine snapshot) that runs h_query beside g; the
# executor starts it at the first submit.
_BESIDE = ThreadPoolExecutor(max_workers=1, thread_name_prefix="h-query")


@contextmanager
def _own_error(q: _Query, errors: dict[int, ServiceError]) -> Iterator[None]:
    """Record a query's own ``ServiceError`` against it alone (its batch goes on without it)."""
    try:
        yield
    except ServiceError as exc:
        errors[q.item] = exc


def _caller_scale(scales: np.ndarray, frame: Frame) -> np.ndarray:
    """Per-axis scales from the model's axes to the caller's: exact for the axis-swapping frames
    (``up``) the API offers, whose rotations are signed permutations.

    Shapes:
        scales (P, 3) -> (P, 3) float64.
    """
    return np.asarray(scales, dtype=np.float64) @ np.abs(frame.rotation)


def _timed(fn: Any, *args: Any) -> tuple[Any, float]:
    t = time.perf_counter()
    return fn(*args), time.perf_counter() - t


def scaled_surface(surface: Surface, scale: np.ndarray) -> Surface:
    """A centred part's oriented samples scaled per axis about its centre (normals transformed
    by the inverse scale and renormalised).

    Shapes:
        scale: (3,).
    """
    s = np.asarray(scale, dtype=np.float64).reshape(1, 3)
    if np.all(s == 1.0):
        return surface
    normals = None
    if surface.normals is not None:
        n = surface.normals / s
        normals = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return Surface(surface.points * s, normals)


def _or_default(asked: bool | None, setting: bool) -> bool:
    """A request's flag, or the service's setting when the request did not say."""
    return setting if asked is None else asked


def _search_parameters(index: faiss.Index, sel: faiss.IDSelector) -> faiss.SearchParameters | None:
    """Search parameters carrying an ID selector, of the kind this index type expects."""
    params: Any
    if isinstance(index, faiss.IndexIVF):
        params = faiss.SearchParametersIVF()
    elif isinstance(index, faiss.IndexHNSW):
        params = getattr(faiss, "SearchParametersHNSW")()  # noqa: B009  (missing from faiss's stubs)
    elif isinstance(index, faiss.IndexFlat):
        params = faiss.SearchParameters()
    else:
        return None
    params.sel = sel
    return params
