"""The suggestion engine: partial assembly in, ranked and placed catalog parts out.

One request (or a batch of them) goes through these steps, each one batched:

1. points to the canonical frame, resampled to the networks' N points (seeded; h takes its own
   count when the artifacts give it one, ``placement_points``);
2. g: the mixture {phi_k, mu_k, sigma_k} and h_query: the query's placement feature, one run
   each for the whole batch; g's head names the category when the request does not, and g's
   answer is compared with its answers for training shapes (``service.suggest.familiarity``:
   an ``unfamiliar_shape`` warning for a shape of no kind the model knows);
3. the search (``CatalogSearch`` of the request's ``CatalogSnapshot``: numpy brute force or
   FAISS): the nearest catalog parts of every mean, all K means (of all queries sharing the same
   filter) in one search;
4. the union of candidates re-scored by the exact mixture log-likelihood, ranked, near-identical
   parts collapsed (catalog ``duplicate_of``), dealt to g's modes (the share order; after its head
   a near-copy of a part dealt before it waits: ``preferences.spread_order``), the top ones kept
   (k, or ``complement_candidates`` when the complement check runs);
5. h_head over every kept candidate of the batch in one run, with the parts' precomputed
   features from catalog.npz; then the complement check (``service.suggest.complement``): parts that h
   places mostly onto the query's own surface, i.e. parts the query already has, move behind
   the others (each group dealt again), and the top k stay;
6. contact refinement (``service.suggest.contact``; for suggestions only when asked, or when the setting
   ``suggest_refine_contact`` turns it on by default: for k = 10 it about doubles the CPU time of
   a request): each placed part nudged by at most ``contact_max_offset`` so it touches the
   query's points; translations and boxes mapped back to the caller's frame.

Requests may also reweight or exclude g's modes and ask for a mode-balanced gallery
(``service.suggest.preferences``).

No HTTP here: routes, the CLI and tests call these methods directly.
"""

from __future__ import annotations

import logging
import threading
import time
import weakref
from collections import defaultdict
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import faiss
import numpy as np

from service.artifacts.catalog import Catalog
from service.artifacts.loading import Artifacts
from service.artifacts.models import Mixture
from service.errors import DeadlineError, InputError, PayloadTooLargeError, ServiceError
from service.geometry.frames import Frame
from service.geometry.inputs import check_points
from service.geometry.mesh import resample_points
from service.settings import Settings
from service.suggest.complement import complement_order, covered_share, is_covered
from service.suggest.contact import Assembly, ContactParams, PartContacts, refine_offsets
from service.suggest.engine_settings import EngineSettings
from service.suggest.familiarity import FamiliarityCheck, Projection, mixture_descriptor
from service.suggest.fit_rank import fit_keys
from service.suggest.mixture import mixture_log_likelihood, paired_sigma_distances
from service.suggest.neighbours import BruteForceNeighbours
from service.suggest.preferences import Preferences, diverse_order, spread_share_order
from service.suggest.region import Region
from service.suggest.snapshot import CatalogSnapshot

log = logging.getLogger(__name__)


# The cost model of a suggestion query, in estimated CPU milliseconds (max_request_cost_ms,
# batch_max_cost_ms). Measured in process on the shipped artifacts (engine.suggest_batch, one
# core, training running on the other): a query cost 3.7 ms in a batch of 32 and 6-8 ms alone;
# 100k points against 1.5k added about 5 ms (frame, resampling). Contact refinement, compiled
# (contact_kernel), cost 30 ms of CPU for k = 100 on one thread, 3.4 ms for k = 10 (the benchmark
# query, contact_threads 1, 2026-12-07; 38 ms for k = 100 before that day's kernel changes, 12 ms
# a part before it was compiled): about 0.3 ms per refined part, rounded up as the rest are.
QUERY_COST_MS = 4.0
POINT_COST_MS = 0.05 / 1000
REFINED_PART_COST_MS = 0.35
# A region query searches 256 neighbours per mode, and places and checks 256 candidates: it cost
# about 5 ms more than the same query without a region (13 ms against 7.7 ms, best of 5, a chair
# seat with a category filter, trainings running on both cores), most of it in the wider search.
REGION_PART_COST_MS = 5.0 / 256
# A mixture-only query (frame fitting's: g alone) cost 0.3 ms: 27 ms for 90 in one batch (2-core
# AVX-512 host, a training run on the other core).
MIXTURE_QUERY_COST_MS = 0.3


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
    mixture_only: bool = False               # g's answer alone, no suggestions (frame fitting's
                                             # scoring queries; not offered by the API)


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
    rank_score: float     # the answer order's key: score less the fit penalties (suggest.fit_rank)
    mode: int             # mixture mode that explains the part best
    mode_weight: float    # that mode's weight phi_k
    duplicates: int       # catalog parts in this part's near-duplicate group (1: none)
    translation: np.ndarray
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    contact_offset: np.ndarray = field(default_factory=lambda: np.zeros(3))  # part of translation
    scale: np.ndarray = field(default_factory=lambda: np.ones(3))  # per axis, about the part's centre
    # The complement check's measure at h's placement: the share of the part's samples on the
    # query's own surface, and whether that makes it covered (it mostly duplicates, or would
    # replace, a part the query has); None when the check did not run.
    covered_share: float | None = None
    covered: bool | None = None


@dataclass(frozen=True)
class InferredCategory:
    """The category g's category head reads from a query that named none."""

    category: str
    confidence: float     # the head's probability of that category
    applied: bool         # the suggestions were kept in it (confidence >= category_min_confidence)


@dataclass(frozen=True)
class QueryWarning:
    """Something about a query that the answer should not hide (status stays 200)."""

    code: str             # "frame", "category_unsure", "unfamiliar", "unfamiliar_shape", "region_empty"
    message: str          # what is wrong and how to fix it

    @property
    def guess(self) -> bool:
        """Whether the warning makes the answer's suggestions guesses (``GUESS_CODES``): what a
        client shows beside them. The page and the Blender add-on read this flag, not a list of
        codes of their own."""
        return self.code in GUESS_CODES


# Warnings that make the suggestions guesses: a shape, a frame or a category the model cannot
# vouch for. ``region_empty`` only says that the region held no candidate.
GUESS_CODES = frozenset({"frame", "category_unsure", "unfamiliar", "unfamiliar_shape"})


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
    familiarity: float | None = None      # g's answer's distance to the familiarity bank (None: no check)
    # The category head's probability of the query's category (``category_probability``; None
    # without a head): frame fitting prefers the hypotheses in which the query looks like one.
    category_probability: float | None = None


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


@dataclass(frozen=True)
class Ranked:
    """One query's candidates after scoring: the kept catalog rows, best first.

    Shapes:
        rows, scores, modes: (k',) int64, float64, int64.
    """

    rows: np.ndarray      # catalog rows
    scores: np.ndarray    # log-likelihoods under the (reweighted) mixture
    modes: np.ndarray     # the mode that explains each part best
    scored: int           # distinct candidates scored before ranking
    weights: np.ndarray | None = None   # (K,) the mode weights the order was dealt by (None: none)
    sigmas: np.ndarray | None = None    # (K, D) the mixture's standard deviations (the spread order)

    @classmethod
    def empty(cls) -> Ranked:
        none = np.zeros(0, np.int64)
        return cls(none, np.zeros(0), none, 0)


@dataclass(frozen=True)
class Placed:
    """One query's chosen parts with h's placement, in the order they are answered.

    Shapes:
        rows, scores, modes, keys, covered: (P,); translations: (P, 3) canonical; scales: (P, 3)
        fitted, canonical axes.
    """

    rows: np.ndarray
    scores: np.ndarray
    modes: np.ndarray
    translations: np.ndarray
    scales: np.ndarray
    keys: np.ndarray      # the answer order's key (service.suggest.fit_rank): scores less fit penalties
    covered: np.ndarray   # the complement check's covered share at h's placement; NaN: not checked

    def take(self, keep: np.ndarray) -> Placed:
        """The parts ``keep`` (a mask or indices, in that order)."""
        return Placed(self.rows[keep], self.scores[keep], self.modes[keep], self.translations[keep],
                      self.scales[keep], self.keys[keep], self.covered[keep])


class QueryMixture(NamedTuple):
    """g's mixture for one query of a batch.

    Shapes:
        weights: (K,); means, sigmas: (K, D).
    """

    weights: np.ndarray
    means: np.ndarray
    sigmas: np.ndarray

    @classmethod
    def of(cls, mix: Mixture, b: int) -> QueryMixture:
        return cls(mix.weights[b], mix.means[b], mix.sigmas[b])


def category_probability(probs: np.ndarray | None, names: Sequence[str],
                         named: Sequence[str]) -> float | None:
    """The category head's probability of a query's category: the most probable of the categories
    it names, or of all when it names none (or none the head knows); None without a head.

    Shapes:
        probs: (C,) over ``names`` (the manifest's categories).
    """
    if probs is None or len(probs) != len(names) or not len(probs):
        return None
    rows = [i for i, name in enumerate(names) if name in named]
    return float(np.max(probs[rows] if rows else probs))


@dataclass
class Query:
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
    familiarity: float | None = None   # g's answer's distance to the training bank (None: no bank)


class StageTimer:
    """Seconds per named stage of one engine call (the ``timings`` of its results)."""

    def __init__(self) -> None:
        self.timings: dict[str, float] = {}

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        t = time.perf_counter()
        try:
            yield
        finally:
            self.timings[name] = time.perf_counter() - t


class SuggestionEngine:
    """Suggest and place catalog parts for partial assemblies.

    Long-lived: the networks, the settings the engine reads (``EngineSettings``), the contact
    refinement's cache of part samples and the thread that runs h_query beside g. The catalog
    comes from a ``CatalogSnapshot`` given per call; without one, the shipped catalog of the
    artifacts (``shipped``) is read.
    """

    def __init__(self, artifacts: Artifacts, settings: Settings):
        self.artifacts = artifacts
        # What the engine reads of the settings, and no more: the assembly and the frame fit that
        # run on it get the service's settings from their caller.
        self.config = c = EngineSettings.of(settings)
        self.limits = settings.limits
        self.networks = artifacts.networks
        self.shipped = self.snapshot(artifacts.catalog, artifacts.index)
        self.contacts = PartContacts(
            ContactParams(max_offset=c.contact_max_offset, tolerance=c.contact_tolerance,
                          search_points=c.contact_search_points, seed=c.seed, threads=c.contact_threads),
            part_samples=c.contact_part_samples, assembly_points=c.contact_assembly_points,
            cache_entries=c.contact_cache_parts)
        bank = artifacts.familiarity
        self.familiarity = (FamiliarityCheck(bank.descriptors, c.familiarity_threshold or bank.threshold,
                                             Projection(bank.mean, bank.components))
                            if c.familiarity_check and bank is not None else None)
        self._beside: ThreadPoolExecutor | None = None
        self._beside_lock = threading.Lock()

    def snapshot(self, catalog: Catalog, index: faiss.Index) -> CatalogSnapshot:
        """A snapshot of ``catalog`` and its index, searched as this engine's settings say."""
        c = self.config
        return CatalogSnapshot.of(catalog, index, c.brute_force_max_parts, c.exact_search_max_filtered)

    @property
    def model_version(self) -> str:
        return self.artifacts.model_version

    @property
    def catalog(self) -> Catalog:
        """The shipped catalog (a served process reads the current snapshot's, ``service.api.served``)."""
        return self.shipped.catalog

    @property
    def index(self) -> faiss.Index:
        return self.shipped.index

    @property
    def brute_force(self) -> BruteForceNeighbours | None:
        return self.shipped.search.brute_force

    def _runner(self) -> ThreadPoolExecutor:
        """The one thread that runs h_query beside g, started at first use."""
        with self._beside_lock:
            if self._beside is None:
                self._beside = ThreadPoolExecutor(max_workers=1, thread_name_prefix="h-query")
                weakref.finalize(self, self._beside.shutdown, wait=False)
            return self._beside

    def close(self) -> None:
        """Stop the h_query thread (after the call it runs); a later call starts it again."""
        with self._beside_lock:
            beside, self._beside = self._beside, None
        if beside is not None:
            beside.shutdown(wait=True)

    # ---------------------------------------------------------------- step 1: input
    def canonical(self, points: np.ndarray, frame: Frame) -> np.ndarray:
        """Check limits and map to the canonical frame.

        Shapes:
            points: (M, 3) in the caller's frame -> (M, 3) float32 canonical.
        """
        c = self.config
        pts = frame.to_canonical(check_points(points, c.min_points, c.max_points))
        if not np.isfinite(pts).all():  # finite input, but a frame that blows it up (tiny radius)
            raise InputError("non_finite_points", "points are not finite in the canonical frame; "
                             "check the frame's center and radius")
        return pts

    def resample(self, canonical: np.ndarray, n: int | None = None) -> np.ndarray:
        """Canonical points resampled to n points (seeded; None: f and g's N): (M, 3) -> (n, 3) float32."""
        n = self.artifacts.n_points if n is None else n
        pts = canonical
        if len(pts) != n:
            pts = resample_points(pts, n, self.config.seed)
        return np.ascontiguousarray(pts, dtype=np.float32)

    def placement_input(self, q: Query) -> np.ndarray:
        """The points h takes of a query: its f and g points, or its own count of the full cloud
        when the artifacts give h more (``placement_points``). (N_h, 3) float32."""
        n = self.artifacts.placement_points
        return q.points if n == len(q.points) else self.resample(q.full, n)

    def prepare(self, points: np.ndarray, frame: Frame) -> np.ndarray:
        """Check limits, map to the canonical frame and resample to N points.

        Shapes:
            points: (M, 3) in the caller's frame -> (N, 3) float32 canonical.
        """
        return self.resample(self.canonical(points, frame))

    def resolve(self, item: int, points: np.ndarray, options: SuggestOptions, snap: CatalogSnapshot) -> Query:
        """A query checked, in the canonical frame, with the catalog rows its filters allow."""
        cat = snap.catalog
        k = self._checked_k(options)
        allowed: np.ndarray | None = None
        if options.categories:
            allowed = snap.category_mask(cat.category_codes(list(options.categories)))
        if options.exclude_parts:
            groups = cat.group[[cat.lookup(p) for p in options.exclude_parts]]
            keep = ~np.isin(cat.group, groups)
            allowed = keep if allowed is None else allowed & keep
        if options.exclude_shapes:
            keep = ~np.isin(cat.shape_of, [cat.shape_code(sid) for sid in options.exclude_shapes])
            allowed = keep if allowed is None else allowed & keep
        if options.styles:
            keep = snap.style_mask(options.styles)
            allowed = keep if allowed is None else allowed & keep
        key = (tuple(sorted(options.categories)), tuple(sorted(options.exclude_parts)),
               tuple(sorted(options.exclude_shapes)), tuple(sorted(options.styles)))
        full = self.canonical(points, options.frame)
        region = options.region.in_frame(options.frame) if options.region is not None else None
        return Query(item, self.resample(full), full, len(points), options, k, allowed, key,
                     warnings=self._frame_warnings(full), region=region)

    def _frame_warnings(self, canonical: np.ndarray) -> list[QueryWarning]:
        """A ``frame`` warning when the points are far from the model's unit-radius frame.

        Shapes:
            canonical: (M, 3) float32.
        """
        c = self.config
        # float64: a tiny frame.radius puts float32 points near 1e20, whose squares overflow float32.
        pts = canonical.astype(np.float64)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        reach = float(np.linalg.norm(pts - (lo + hi) / 2, axis=1).max())
        if c.ood_min_extent <= reach <= c.ood_max_extent:
            return []
        return [QueryWarning("frame", f"the points reach {reach:.3g} from their centre in the model's frame, "
                             "where a whole object reaches 1: the answer is unlikely to fit; give "
                             "frame.radius (the object's radius in your units) and frame.center")]

    def infer_category(self, q: Query, probs: np.ndarray | None, snap: CatalogSnapshot) -> None:
        """Read the query's category from g's head when it named none; filter when sure enough.

        Shapes:
            probs: (C,) over the manifest's categories, or None without a head.
        """
        c, cat = self.config, snap.catalog
        names = self.artifacts.head_categories
        if probs is None or q.options.categories or not c.infer_category or len(names) != len(probs):
            return
        best = int(np.argmax(probs))
        name, confidence = str(names[best]), float(probs[best])
        in_catalog = name in cat.categories
        # A style filter already names what the caller wants (styles belong to one category):
        # the inference is reported, not applied.
        applied = confidence >= c.category_min_confidence and in_catalog and not q.options.styles
        q.inferred = InferredCategory(name, confidence, applied)
        if q.options.styles:
            return
        if applied:
            keep = snap.category_mask(cat.category_codes([name]))
            q.allowed = keep if q.allowed is None else q.allowed & keep
            q.filter_key = ((name,), *q.filter_key[1:])
        else:
            q.warnings.append(QueryWarning(
                "category_unsure", f"the partial assembly looks most like a {name} (probability "
                f"{confidence:.2f}), which is not sure enough to keep the suggestions in one category; "
                "name the category (categories) or check the frame"))

    def _checks_complement(self, options: SuggestOptions) -> bool:
        """Whether a suggestion query's candidates go through the complement check."""
        return _or_default(options.complement_check, self.config.suggest_complement_check)

    def _shortlist(self, q: Query) -> int:
        """Ranked candidates kept for placement: k, or more when the complement check or the fit
        key will reorder them, or the region's candidate budget when only parts placed in a
        region count. (The same shortlist for every k keeps a shorter answer the head of a
        longer one.)"""
        c = self.config
        n = max(q.k, c.complement_candidates) if self._reorders(q.options) else q.k
        return max(n, self.config.region_candidates) if q.region is not None else n

    def _reorders(self, options: SuggestOptions) -> bool:
        """Whether the placed shortlist is reordered before the top k: by the complement check, or
        by the fit key (either weight non-zero)."""
        c = self.config
        return self._checks_complement(options) or bool(c.rank_scale_weight or c.rank_move_weight)

    def _per_mode(self, q: Query) -> int:
        """Nearest parts a query needs of each mode's mean: at least k, so that a large k is not
        starved of candidates, and the region's candidate budget for a region query."""
        return max(q.k, self.config.region_candidates) if q.region is not None else q.k

    def _refines(self, options: SuggestOptions) -> bool:
        """Whether a suggestion query's placements get contact refinement."""
        return _or_default(options.refine_contact, self.config.suggest_refine_contact)

    # ---------------------------------------------------------------- cost, checked up front
    def query_cost(self, n_points: int, options: SuggestOptions) -> float:
        """Estimated CPU milliseconds of one suggestion query (see ``max_request_cost_ms``)."""
        if options.mixture_only:
            return MIXTURE_QUERY_COST_MS + POINT_COST_MS * max(0, n_points)
        k = self.config.default_k if options.k is None else options.k
        refined = max(0, k) if self._refines(options) else 0
        placed = self.config.region_candidates if options.region is not None else 0
        return (QUERY_COST_MS + POINT_COST_MS * max(0, n_points) + REFINED_PART_COST_MS * refined
                + REGION_PART_COST_MS * placed)

    def check_query(self, n_points: int, options: SuggestOptions) -> float:
        """Refuse what can be refused before a query joins a batch; its estimated cost.

        Raises ``InputError`` for k out of range, too many exclusions or preferences that leave
        no mode (the checks of ``resolve`` that need neither points nor the catalog).
        """
        self._checked_k(options)
        return self.query_cost(n_points, options)

    def _checked_k(self, options: SuggestOptions) -> int:
        """The query's k, after the checks that need neither points nor the catalog."""
        limits = self.limits
        k = limits.k(options.k)
        limits.check_exclusions(len(options.exclude_parts) + len(options.exclude_shapes))
        options.preferences.check(self.artifacts.n_modes)
        return k

    def check_budget(self, cost: float, queries: int = 1) -> None:
        """``PayloadTooLargeError`` when a request's estimated cost is over ``max_request_cost_ms``."""
        budget = self.config.max_request_cost_ms
        if cost > budget:
            raise PayloadTooLargeError("over_budget", (
                f"the request's {queries} quer{'y' if queries == 1 else 'ies'} would take about "
                f"{cost:.0f} ms of CPU, over the budget of {budget:g} ms per request "
                "(COMPLEMENTME_MAX_REQUEST_COST_MS); ask for fewer items, a smaller k or no "
                f"refine_contact ({REFINED_PART_COST_MS:g} ms per refined suggestion), or split the request"))

    # ---------------------------------------------------------------- public API
    def suggest(self, points: np.ndarray, options: SuggestOptions | None = None,
                snapshot: CatalogSnapshot | None = None) -> SuggestResult:
        """Ranked, placed suggestions for one partial assembly; raises ``ServiceError`` on bad input.

        Shapes:
            points: (M, 3) in the caller's frame (``options.frame``).
        """
        result = self.suggest_batch([(points, options or SuggestOptions())], snapshot=snapshot)[0]
        if isinstance(result, ServiceError):
            raise result
        return result

    def suggest_batch(self, items: list[tuple[np.ndarray, SuggestOptions]],
                      deadlines: Sequence[float | None] | None = None,
                      snapshot: CatalogSnapshot | None = None) -> list[SuggestResult | ServiceError]:
        """Suggestions for many queries with batched inference; a bad item yields its own error.

        Returns one entry per item, in order: a ``SuggestResult`` or the ``ServiceError`` that
        item raised (the other items are unaffected: every step past the batched network runs
        is checked per query). ``deadlines`` (``time.monotonic()``, one per item, None: none):
        an item past its deadline before contact refinement, the costly step, gets a
        ``DeadlineError`` instead of being refined. ``snapshot``: the catalog to read (None:
        the shipped one).
        """
        snap = snapshot or self.shipped
        timer = StageTimer()
        with timer.stage("total"):
            out = self._run_batch(items, deadlines, snap, timer)
        return out

    def _run_batch(self, items: list[tuple[np.ndarray, SuggestOptions]],
                   deadlines: Sequence[float | None] | None, snap: CatalogSnapshot,
                   timer: StageTimer) -> list[SuggestResult | ServiceError]:
        """The steps of ``suggest_batch``, each timed (the stage names the metrics report)."""
        errors: dict[int, ServiceError] = {}
        queries: list[Query] = []
        with timer.stage("prepare"):
            # OpenMP's thread count is per calling thread: set it in this one (the batcher's
            # worker) for the FAISS calls below, or FAISS starts a team of one thread per core for
            # every calling thread (searches took 13 ms instead of 0.1 ms in the server).
            faiss.omp_set_num_threads(self.config.faiss_threads)
            for i, (points, options) in enumerate(items):
                try:
                    queries.append(self.resolve(i, points, options, snap))
                except ServiceError as exc:
                    errors[i] = exc
        if not queries:
            return [errors[i] for i in range(len(items))]
        everything = np.stack([q.points for q in queries])  # (B, N, 3)
        # Mixture-only queries (frame fitting's) stop after g: the rest go on without them.
        rest = [b for b, q in enumerate(queries) if not q.options.mixture_only]
        if self.artifacts.placement_points == self.artifacts.n_points or not rest:
            batch = everything if len(rest) == len(queries) else everything[rest]
        else:  # h takes its own count of each query's points (placement_points)
            batch = np.stack([self.placement_input(queries[b]) for b in rest])
        # h_query needs only the points and is needed only by h_head: it runs on a thread of its
        # own meanwhile (ONNX Runtime releases the GIL), beside g, the search and the scoring.
        beside = (self._runner().submit(_timed, self.networks.query_features, batch)
                  if rest and len(rest) <= self.config.overlap_max_batch else None)
        out: dict[int, SuggestResult | ServiceError] = {}
        with timer.stage("g"):
            mix = self.networks.mixture(everything)
            distances = self.familiarity_distances(mix.weights, mix.means)
            kind: dict[int, float | None] = {}
            for b, q in enumerate(queries):
                probs = None if mix.category_probs is None else mix.category_probs[b]
                self.infer_category(q, probs, snap)
                kind[q.item] = category_probability(probs, self.artifacts.head_categories,
                                                    q.options.categories)
                if distances is not None:
                    q.familiarity = float(distances[b])
                    hedged = self._hedges(q)
                    if hedged:  # answered as the caller's own `diversity` request would be
                        q.options = replace(q.options, preferences=replace(q.options.preferences,
                                                                           diversity=True))
                    q.warnings.extend(self._shape_warnings(q.familiarity, hedged))
                if q.options.mixture_only:
                    out[q.item] = self._mixture_answer(q, QueryMixture.of(mix, b), kind[q.item],
                                                       timer.timings)
        if len(rest) < len(queries):
            queries, mix = [queries[b] for b in rest], mix.take(rest)
            if not queries:
                out.update(errors)
                return [out[i] for i in range(len(items))]
        with timer.stage("search"):
            candidates = self.search(queries, mix.means, snap)
        ranked: dict[int, Ranked] = {}  # query position b -> its ranked candidates
        with timer.stage("score"):
            for b, q in enumerate(queries):
                with _own_error(q, errors):
                    ranked[b] = self.rank(q, candidates[b], mix.weights[b], mix.means[b], mix.sigmas[b], snap)
        qf, timer.timings["h_query"] = (beside.result() if beside is not None
                                        else _timed(self.networks.query_features, batch))
        with timer.stage("h_head"):
            translations, scales = self.place_ranked(qf, ranked, snap)
        placed: dict[int, Placed] = {}
        with timer.stage("complement"):
            for b, r in ranked.items():
                with _own_error(queries[b], errors):
                    placed[b] = self.select(queries[b], r, translations[b], scales[b], snap)
        offsets: dict[int, np.ndarray] = {}
        with timer.stage("contact"):
            for b, p in placed.items():
                q = queries[b]
                with _own_error(q, errors):
                    offsets[b] = self.refine(q, p, deadlines[q.item] if deadlines is not None else None, snap)
        out.update(errors)
        for b, off in offsets.items():
            q = queries[b]
            with _own_error(q, errors):
                answer = self.answer(q, placed[b], off, QueryMixture.of(mix, b), ranked[b], snap,
                                     timer.timings)
                answer.familiarity = q.familiarity
                answer.category_probability = kind.get(q.item)
                out[q.item] = answer
        out.update(errors)
        return [out[i] for i in range(len(items))]

    @staticmethod
    def _mixture_answer(q: Query, mix: QueryMixture, category_probability: float | None,
                        timings: dict[str, float]) -> SuggestResult:
        """The answer to a mixture-only query: g's modes (with the familiarity distance and the
        category head's probability), no suggestions."""
        return SuggestResult(suggestions=[], mode_weights=mix.weights, frame=q.options.frame,
                             n_input_points=q.n_input, candidates=0, timings=timings,
                             mode_means=mix.means, mode_sigmas=mix.sigmas, inferred_category=q.inferred,
                             warnings=q.warnings, familiarity=q.familiarity,
                             category_probability=category_probability)

    def place_ranked(self, query_features: np.ndarray, ranked: dict[int, Ranked], snap: CatalogSnapshot
                     ) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
        """h_head over every kept candidate of every query, in one run: raw translations and
        scales (canonical) per query position.

        Shapes:
            query_features: (B, Fq) -> {b: (k'_b, 3)}, {b: (k'_b, 3)}.
        """
        rows = np.concatenate([np.zeros(0, np.int64)] + [np.full(len(r.rows), b) for b, r in ranked.items()]
                              ).astype(np.int64)
        parts = np.concatenate([np.zeros(0, np.int64)] + [r.rows for r in ranked.values()]).astype(np.int64)
        translations, scales = (np.zeros((0, 3), np.float32), np.ones((0, 3), np.float32))
        if len(parts):
            translations, scales = self.networks.place_and_fit(query_features[rows],
                                                               snap.catalog.part_features[parts])
        return ({b: translations[rows == b] for b in ranked}, {b: scales[rows == b] for b in ranked})

    def select(self, q: Query, ranked: Ranked, translations: np.ndarray, raw_scales: np.ndarray,
               snap: CatalogSnapshot) -> Placed:
        """A query's placed candidates as answered: scales fitted, only those in its region (if it
        gave one), covered parts demoted by the complement check, the top k.

        Shapes:
            translations, raw_scales: (k', 3) canonical, h's output for ``ranked.rows``.
        """
        c = self.config
        fit = self._fitted(raw_scales, q.options.fit_scale)
        # The key reads h's scale whether or not the answer fits it: a part that needs rescaling
        # fits worse either way (served unscaled, it is the wrong size).
        keys = fit_keys(ranked.scores, self._clipped(raw_scales), translations,
                        snap.catalog.translations[ranked.rows], c.rank_scale_weight, c.rank_move_weight)
        placed = Placed(ranked.rows, ranked.scores, ranked.modes, translations, fit, keys,
                        np.full(len(ranked.rows), np.nan))
        if q.region is not None:
            placed = placed.take(self._in_region(q, placed, snap))
        if len(placed.rows) and self._checks_complement(q.options):
            samples = snap.catalog.part_samples(placed.rows, c.complement_part_samples)
            share = covered_share(q.points, samples, placed.translations.astype(np.float32),
                                  c.complement_cover_distance)
            placed = replace(placed, covered=share)
        return placed.take(self._answer_order(q, placed, ranked, snap)[:q.k])

    def refine(self, q: Query, placed: Placed, deadline: float | None, snap: CatalogSnapshot) -> np.ndarray:
        """Contact refinement offsets (canonical) of a query's placed parts, zeros when it is off.

        Raises ``DeadlineError`` when ``deadline`` (``time.monotonic()``) has passed.

        Shapes:
            -> (P, 3) float64.
        """
        if deadline is not None and time.monotonic() > deadline:
            raise DeadlineError("deadline_exceeded", "the request's deadline passed before its "
                                "placements were refined")
        if not (self._refines(q.options) and len(placed.rows)):
            return np.zeros((len(placed.rows), 3))
        return self.contact_offsets(q.full, placed.rows, placed.translations, snap.catalog, placed.scales)

    def answer(self, q: Query, placed: Placed, offsets: np.ndarray, mix: QueryMixture, ranked: Ranked,
               snap: CatalogSnapshot, timings: dict[str, float]) -> SuggestResult:
        """A query's result: its placed parts in the caller's frame, its mixture and warnings."""
        return SuggestResult(
            suggestions=self._suggestions(placed, offsets, mix.weights, q.options.frame, snap.catalog),
            mode_weights=mix.weights, frame=q.options.frame, n_input_points=q.n_input,
            candidates=ranked.scored, timings=timings, mode_means=mix.means, mode_sigmas=mix.sigmas,
            inferred_category=q.inferred,
            warnings=q.warnings + self._mode_distance_warnings(ranked, mix.means, mix.sigmas, snap.catalog),
            region=q.region_report)

    def place(self, points: np.ndarray, part_ids: list[str], frame: Frame | None = None,
              refine_contact: bool = True, fit_scale: bool | None = None,
              snapshot: CatalogSnapshot | None = None) -> PlaceResult:
        """Translations (and placed boxes) of chosen parts next to a partial assembly.

        Shapes:
            points: (M, 3) in the caller's frame.
        """
        frame = frame or Frame()
        cat = (snapshot or self.shipped).catalog
        if not part_ids:
            raise InputError("no_parts", "give at least one part id to place")
        if len(part_ids) > self.config.max_place_parts:
            raise InputError("too_many_parts", f"{len(part_ids)} part ids given, at most "
                             f"{self.config.max_place_parts} are accepted")
        idx = np.array([cat.lookup(p) for p in part_ids], dtype=np.int64)
        timer = StageTimer()
        with timer.stage("prepare"):
            full = self.canonical(points, frame)
            canonical = self.resample(full, self.artifacts.placement_points)
        with timer.stage("h_query"):
            qf = self.networks.query_features(canonical[None])
        with timer.stage("h_head"):
            tr, raw_scale = self.networks.place_and_fit(np.repeat(qf, len(idx), axis=0),
                                                        cat.part_features[idx])
            scale = self._fitted(raw_scale, fit_scale)
        with timer.stage("contact"):
            off = (self.contact_offsets(full, idx, tr, cat, scale) if refine_contact
                   else np.zeros((len(idx), 3)))
        trans, lo, hi = _placed_boxes(cat, idx, tr + off, frame, scale)
        off_caller = off @ frame.rotation * frame.radius
        scale_caller = _caller_scale(scale, frame)
        placements = [Placement(int(i), cat.part_ids[i], trans[j], lo[j], hi[j], off_caller[j],
                                scale_caller[j]) for j, i in enumerate(idx)]
        return PlaceResult(placements, frame, len(points), timer.timings)

    def warmup(self) -> SuggestResult:
        """Run one suggestion and one placement on a query made from the first catalog shape;
        the suggestion's result (a test checks it is not empty)."""
        cat = self.catalog
        parts = np.flatnonzero(cat.shape_of == cat.shape_of[0])
        points = np.concatenate([cat.part_points(int(i)) + cat.translations[i] for i in parts])
        result = self.suggest(points, SuggestOptions(k=min(5, self.config.max_k)))
        if result.suggestions:
            self.place(points, [result.suggestions[0].part_id])
        log.info("warm-up passed: %d suggestions in %.1f ms", len(result.suggestions),
                 1000 * result.timings.get("total", 0.0))
        return result

    def contact_offsets(self, full: np.ndarray, rows: np.ndarray, translations: np.ndarray,
                        catalog: Catalog | None = None, scales: np.ndarray | None = None) -> np.ndarray:
        """Contact refinement offsets (canonical) of parts placed next to canonical points, each
        measured at the size it is answered with (``scales``, fitted; None: the catalog's): a leg
        fitted 1.3 times longer and refined at its catalog length would be moved to touch where
        its answered length sinks into the seat.

        Shapes:
            full: (M, 3) canonical query points; rows: (n,); translations: (n, 3); scales: (n, 3)
            canonical axes -> (n, 3) float64.
        """
        assembly = self.contacts.assembly_from_points(full)
        return self.refine_against(assembly, rows, translations, scales, catalog=catalog)

    def refine_against(self, assembly: Assembly, rows: np.ndarray, translations: np.ndarray,
                       scales: np.ndarray | None = None, catalog: Catalog | None = None) -> np.ndarray:
        """Contact refinement offsets of catalog parts placed against an assembly.

        The bounded search first (``contact_max_offset``); a part it leaves floating (apart from
        the assembly, not sunk into it) gets a second search reaching ``contact_reach``, so that
        a part h left hanging in the air is pulled onto what it attaches to. ``scales``: per-axis
        sizes the parts are fitted to (None: as in the catalog). ``catalog``: the one ``rows``
        index (None: the shipped one).

        Shapes:
            rows: (n,); translations: (n, 3) canonical; scales: (n, 3) -> (n, 3) float64 offsets.
        """
        cat = catalog if catalog is not None else self.catalog
        moved = self.contacts.placed(cat, rows, translations, scales)
        # All parts in one search (refine_offsets answers as one part at a time would, faster).
        params = self.contacts.params
        found = refine_offsets(moved, assembly, params)
        offsets = np.array([r.offset for r in found], dtype=np.float64).reshape(-1, 3)
        reach = replace(params, max_offset=self.config.contact_reach)
        if reach.max_offset <= params.max_offset:
            return offsets
        floating = [j for j, r in enumerate(found)
                    if not r.resolved and r.before.depth <= params.tolerance < r.before.gap]
        if floating:
            far = refine_offsets([moved[j] for j in floating], assembly, reach)
            for j, r in zip(floating, far, strict=True):
                offsets[j] = r.offset
        return offsets

    # ---------------------------------------------------------------- steps 3-6
    def search(self, queries: list[Query], means: np.ndarray, snap: CatalogSnapshot) -> list[np.ndarray]:
        """Candidate catalog rows per query: the nearest parts to any of its modes' means
        (``CatalogSearch``: numpy brute force for small flat catalogs, else FAISS).

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
            want = max(self.config.neighbours_per_mode, *(self._per_mode(queries[b]) for b in members))
            nn = min(len(snap.catalog), want)
            flat = np.ascontiguousarray(means[members].reshape(-1, means.shape[2]), dtype=np.float32)
            unions = snap.search.neighbour_union(flat, K, nn, queries[members[0]].allowed)
            for b, ids in zip(members, unions, strict=True):
                found[b] = ids
        return found

    def rank(self, q: Query, cand: np.ndarray, weights: np.ndarray, means: np.ndarray,
             sigmas: np.ndarray, snap: CatalogSnapshot) -> Ranked:
        """Score candidates under the mixture, sort, collapse duplicates, keep the shortlist.

        Shapes:
            cand: (C,) catalog rows; weights: (K,); means, sigmas: (K, D).
        """
        if len(cand) == 0:
            return Ranked.empty()
        cat = snap.catalog
        prefs = q.options.preferences
        emb = cat.embeddings[cand]
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
            _, first = np.unique(cat.group[cand], return_index=True)
            keep = np.sort(first)
        else:
            keep = np.arange(len(cand))
        keep = keep[self._mode_order(q, mode[keep], w, cat.embeddings[cand[keep]], sigmas)]
        keep = keep[:self._shortlist(q)]
        return Ranked(cand[keep], ll[keep], mode[keep], n_scored, w, sigmas)

    def _mode_order(self, q: Query, modes: np.ndarray, w: np.ndarray, emb: np.ndarray,
                    sigmas: np.ndarray | None) -> np.ndarray:
        """Positions into ``modes`` (candidates in likelihood order) in the order the query's
        suggestions are dealt: the diversity round-robin, the share order (not for a region
        query) with its near-copies moved back (``spread_order``), or unchanged.

        Shapes:
            modes: (C,) int64; w: (K,) the (reweighted) mode weights; emb: (C, D) the candidates'
            embeddings; sigmas: (K, D) g's standard deviations (None: no spread) -> (C,) int64.
        """
        c = self.config
        if q.options.preferences.diversity:
            return diverse_order(modes, w, c.diversity_min_mode_weight)
        # A region already names the kind of part the caller wants (what goes at that spot): its
        # parts come in likelihood order, not dealt to the other kinds g expects elsewhere.
        if c.suggest_order == "share" and q.region is None:
            return spread_share_order(modes, w, emb, sigmas, q.k, c.share_min_mode_weight, c.share_order_head,
                                      c.share_spread_sigmas)
        return np.arange(len(modes))

    def _hedges(self, q: Query) -> bool:
        """Whether a query is answered as the diversity gallery because g does not know its shape
        (``unfamiliar_diversity``): its familiarity distance past ``unfamiliar_diversity_ratio``
        times the threshold, and no region (a spot already names the kind of part wanted)."""
        c = self.config
        return (c.unfamiliar_diversity and q.region is None and q.familiarity is not None
                and self.familiarity is not None
                and q.familiarity > c.unfamiliar_diversity_ratio * self.familiarity.threshold)

    def _in_region(self, q: Query, placed: Placed, snap: CatalogSnapshot) -> np.ndarray:
        """Which placed candidates reach into the query's region; records the query's region report.

        Judged on h's placement with the fitted scale, before contact refinement (which moves a
        part by at most ``contact_max_offset``).

        Shapes:
            -> (P,) bool.
        """
        assert q.region is not None
        cat, idx = snap.catalog, placed.rows
        t, sc = placed.translations.astype(np.float64), placed.scales.astype(np.float64)
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

    def _answer_order(self, q: Query, placed: Placed, ranked: Ranked,
                      snap: CatalogSnapshot) -> np.ndarray:
        """A query's ranked, placed candidates in answer order (indices): put back in the order
        of their fit keys (``service.suggest.fit_rank``), covered parts demoted by the complement
        check, each group dealt again (the order past the first k is left undealt: only the top k
        are answered).

        When the suggestions are dealt to modes (diversity, share order), each group (uncovered,
        then covered) is dealt again: demoting a mode's first part must not leave that mode out
        of the first round while another mode shows its second. With the check off and no fit
        penalty the ranked order stands.
        """
        idx = placed.rows
        if len(idx) == 0 or not self._reorders(q.options):
            return np.arange(len(idx))
        weights, emb = ranked.weights, snap.catalog.embeddings
        deal = None if weights is None else (
            lambda g: self._mode_order(q, placed.modes[g], weights, emb[placed.rows[g]], ranked.sigmas))
        # A part not checked (NaN share) is not covered (complement.is_covered): nothing is demoted.
        return complement_order(placed.covered, self.config.complement_cover_share, placed.keys, deal, q.k)

    def _fitted(self, raw: np.ndarray, asked: bool | None) -> np.ndarray:
        """Fitting scales as served: clipped to the settings' range, or ones when fitting is off.

        Shapes:
            raw (P, 3) -> (P, 3) float64.
        """
        if not _or_default(asked, self.config.fit_scale):
            return np.ones((len(raw), 3))
        return self._clipped(raw)

    def _clipped(self, raw: np.ndarray) -> np.ndarray:
        """h's scales clipped to the settings' range (what fitting serves, and what the fit key reads).

        Shapes:
            raw (P, 3) -> (P, 3) float64.
        """
        return np.clip(raw.astype(np.float64), self.config.scale_min, self.config.scale_max)

    def familiarity_distances(self, weights: np.ndarray, means: np.ndarray) -> np.ndarray | None:
        """Distance of g's answer for each query to the nearest answer for a training partial
        assembly (``service.suggest.familiarity``); None when the check is off or the artifacts
        have no bank.

        Shapes:
            weights: (B, K), means: (B, K, D) -> (B,) float64.
        """
        if self.familiarity is None:
            return None
        return self.familiarity.distances(mixture_descriptor(weights, means))

    def _shape_warnings(self, distance: float, hedged: bool) -> list[QueryWarning]:
        """An ``unfamiliar_shape`` warning when g's answer is unlike its answers for training shapes;
        ``hedged``: the answer comes as the diversity gallery (``_hedges``), which it then says."""
        assert self.familiarity is not None
        limit = self.familiarity.threshold
        if distance <= limit:
            return []
        spread = (" (the suggestions come one of each kind g proposes, as a `diversity` gallery)"
                  if hedged else "")
        return [QueryWarning("unfamiliar_shape", (
            f"g's answer for this partial assembly lies {distance:.2f} from its nearest answer for a "
            f"training shape (threshold {limit:.2f}): the shape is unlike anything the model was trained "
            f"on, so the inferred category and the suggestions are guesses{spread}; if it is of a known "
            "kind, check the frame (frame.radius, frame.center, frame.up) or name the category"))]

    def _mode_distance_warnings(self, ranked: Ranked, means: np.ndarray, sigmas: np.ndarray,
                              catalog: Catalog) -> list[QueryWarning]:
        """An ``unfamiliar`` warning when even the candidate closest to its mode's mean is far from it.

        Read on the ranked shortlist, not on the answer: the answer's order (share order, fit
        key, complement check) and its k decide which parts are listed, and that says nothing
        about the query; what does is that the catalog has nothing near what g expects.

        Shapes:
            means, sigmas (K, D).
        """
        if len(ranked.rows) == 0:
            return []
        k = ranked.modes.astype(np.int64)
        # In float64 (paired_sigma_distances): a query in a wrong frame puts candidates so far out that
        # the squares overflow float32.
        distance = float(paired_sigma_distances(catalog.embeddings[ranked.rows], means[k], sigmas[k]).min())
        limit = self.config.ood_max_mode_distance
        if distance <= limit:
            return []
        return [QueryWarning("unfamiliar", f"the closest candidate lies {distance:.1f} sigmas from what the "
                             f"model expects (in-distribution queries stay within {limit:g}): the "
                             "partial assembly is unlike anything the model was trained on; check the "
                             "frame (frame.radius, frame.center, frame.up) and the category")]

    def _suggestions(self, placed: Placed, offsets: np.ndarray, weights: np.ndarray, frame: Frame,
                     catalog: Catalog) -> list[Suggestion]:
        moved = placed.translations + offsets
        trans, lo, hi = _placed_boxes(catalog, placed.rows, moved, frame, placed.scales)
        off_caller = offsets @ frame.rotation * frame.radius
        scale_caller = _caller_scale(placed.scales, frame)
        checked = ~np.isnan(placed.covered)
        covered = is_covered(placed.covered, self.config.complement_cover_share)
        out = []
        for r, i in enumerate(placed.rows.tolist()):
            rec = catalog.records[i]
            mode = int(placed.modes[r])
            out.append(Suggestion(
                rank=r + 1, part_index=i, part_id=rec["part_id"], shape_id=rec["shape_id"],
                category=rec["category"], label=rec["label"], score=float(placed.scores[r]),
                rank_score=float(placed.keys[r]),
                mode=mode, mode_weight=float(weights[mode]),
                duplicates=int(catalog.group_size[i]), translation=trans[r], bbox_min=lo[r], bbox_max=hi[r],
                contact_offset=off_caller[r], scale=scale_caller[r],
                covered_share=float(placed.covered[r]) if checked[r] else None,
                covered=bool(covered[r]) if checked[r] else None))
        return out


def _placed_boxes(catalog: Catalog, idx: np.ndarray, translations: np.ndarray, frame: Frame,
                  scales: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Canonical translations of parts to caller-frame translations and placed boxes.

    The box is the part's catalog box scaled about its centre (the translation) by its fitted
    per-axis scale.

    Shapes:
        idx (P,), translations (P, 3), scales (P, 3) canonical axes -> (P, 3) x 3, caller frame.
    """
    t = translations.astype(np.float64)
    sc = scales.astype(np.float64)
    lo, hi = frame.box_from_canonical(t + sc * catalog.bbox_min[idx], t + sc * catalog.bbox_max[idx])
    return frame.from_canonical(t), lo, hi


@contextmanager
def _own_error(q: Query, errors: dict[int, ServiceError]) -> Iterator[None]:
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


def _or_default(asked: bool | None, setting: bool) -> bool:
    """A request's flag, or the service's setting when the request did not say."""
    return setting if asked is None else asked
