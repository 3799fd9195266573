"""Automatic shape synthesis: start from one part (or a cloud, or a mesh), then suggest and place.

The paper's automatic assembly (Section 6.1): "start with a random component, and iteratively
add a component by sampling from the predicted distribution", either the most probable one at
every step or, for a tree of possibilities, several choices per step. Each step here

1. builds the query: the placed parts' catalog samples in the canonical frame, area-weighted
   to the networks' N points (a start cloud counts with the area its points cover);
2. asks the engine for ``assemble_candidates`` suggestions as a mode-balanced gallery (so that
   every kind g proposes has candidates, even when its heaviest mode only offers more of what
   is placed), with the request's filters (by default the start part's category, or the first
   added part's when the start is a cloud or a mesh), placed and fitted in size by h, without
   contact refinement;
3. walks the candidates in the order the strategy wants them and keeps the first *eligible*
   ones (a candidate is only tested when it is next in line: a chain step usually tests a few):
   * likely enough: the part's mode has weight >= ``assemble_min_mode_weight`` and the part's
     embedding lies within ``assemble_max_distance`` root-mean-square standard deviations of
     that mode's mean (a typical draw from the mode is about 1);
   * not doing the job of a part already at its spot, judged on geometry and on the model, never
     on labels (``_redundant``):
     - the same geometry at the same spot: its placed samples within
       ``assemble_duplicate_distance`` Chamfer distance of a placed part's;
     - the same spot: its box centred within ``assemble_duplicate_centre`` of a placed part's
       box, unless it encloses that box with at least ``assemble_duplicate_contain_ratio`` times
       its volume and another profile across its longest axis (a hull around its deck); boxes of
       about the same size (every extent within ``assemble_duplicate_size_ratio``) are
       duplicates even then;
     - the same region and the same job: its box overlaps a placed part's with IoU above
       ``assemble_overlap_iou`` and the two parts' embeddings lie within
       ``assemble_same_job_sigmas`` of each other, in the standard deviations g predicts for the
       candidate's mode (g would take either part for the other here: a second shade over the
       shade), or boxes overlapping with IoU above ``assemble_strong_overlap_iou`` and
       embeddings within ``assemble_strong_overlap_sigmas``, or boxes overlapping with IoU above
       ``assemble_overlap_iou`` and the placed part within ``assemble_overlap_mode_distance`` of
       the candidate's mode (the kind of part that mode proposes is there already: a second
       roof shifted along the roof, of another style). Parts of other kinds may overlap
       (the data's own car bodies and wheels, sofa seats and arms overlap with IoU up to 0.5);
     - lying on placed surface: at least ``assemble_cover_share`` of its placed samples within
       ``assemble_cover_distance`` of the placed parts' samples; where the category's own
       training parts lie on each other more (rifle magazines in their bodies), the share its
       parts reach at ``assemble_cover_quantile`` (``own_cover_shares``);
4. stops when the object is *complete*: when no eligible candidate is more likely under g's
   mixture than a part already placed, by ``assemble_complete_margin`` (g's most wanted
   complement is one the assembly has: a chair with a seat, a back and legs asks for one more
   seat or back), unless a mode of weight at least ``assemble_open_mode_weight`` has no placed
   part near its mean (``open_modes``) and an eligible candidate: then that candidate is added
   (in a tree, one per unmet mode, up to the branching); failing that, unless most of the
   category's training shapes nearest to the assembly have a part at a spot it leaves empty
   (``templates.missing_spots``, ``assemble_gap_neighbours``): then the first eligible candidate
   placed at that spot is added (``SuggestOptions.region``);
5. picks: ``greedy`` takes the most likely eligible part; ``sample`` draws a mode with
   probability proportional to its weight (sharpened or flattened by ``temperature``) and takes
   that mode's most likely eligible part (seeded);
6. refines the chosen part's placement (fitted in size) against the placed parts' oriented
   samples (``SuggestionEngine.refine_against``: ``service.suggest.contact``'s bounded search, then a
   longer one for a part left floating; off with ``refine_contact=False``).

The reasons a chain (or a branch) ends are ``STOP_REASONS``. With ``branching`` b >= 2 every
state gets up to b children that differ (other modes first; never two near-identical parts,
never a state another branch already reached), expanded breadth-first until
``assemble_max_nodes`` parts are placed over the whole tree: the paper's binary tree of
possibilities for b = 2 (its Figure 8).

Everything runs in the canonical frame; the API maps translations to the caller's frame.
"""

from __future__ import annotations

import threading
import time
import weakref
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from typing import Literal, TypeVar

import numpy as np
from scipy.spatial import cKDTree

from service.artifacts.catalog import Catalog, drawn_training_shapes, split_shapes
from service.errors import InputError
from service.geometry.boxes import box_iou
from service.geometry.frames import Frame
from service.geometry.pointsets import chamfer_below
from service.geometry.scaling import scaled_area
from service.modeling.templates import ShapeTemplate, missing_spots, shape_templates
from service.settings import Settings
from service.suggest import contact_kernel
from service.suggest.contact import Assembly, Surface
from service.suggest.engine import Suggestion, SuggestionEngine, SuggestOptions, SuggestResult
from service.suggest.mixture import mixture_log_likelihood, sigma_distances
from service.suggest.preferences import Preferences
from service.suggest.region import Region
from service.suggest.snapshot import CatalogSnapshot

Strategy = Literal["greedy", "sample"]

# Why a chain (or a tree branch) ended.
STOP_REASONS = {
    "complete": "the object looks complete: no candidate is more likely than a part already placed",
    "max_parts": "max_parts parts were added",
    "no_candidates": "the engine found no candidate part (filters too strict?)",
    "unlikely": "no candidate was likely enough (mode weight or distance to its mode's mean)",
    "duplicates": "every likely candidate does the job of a part already placed",
    "node_budget": "the tree reached assemble_max_nodes parts",
}

# Why a part was added (``Node.added_by``): which rule of the step chose it.
ADD_REASONS = {
    "likely": "the most likely eligible candidate under g's mixture",
    "unmet_mode": "a heavy mode of g's mixture that no placed part explained offered it",
    "missing_spot": "most of the category's shapes nearest the assembly have a part at its spot",
}


@dataclass(frozen=True)
class AssembleOptions:
    """What a caller may ask of one automatic assembly (all optional)."""

    max_parts: int | None = None             # parts to add to the start (None: the setting)
    strategy: Strategy = "greedy"
    seed: int = 0                            # the sampler's seed
    temperature: float = 1.0                 # sample: mode probabilities ~ phi_k ** (1 / temperature)
    branching: int = 1                       # children per state; >= 2 returns a tree
    categories: tuple[str, ...] = ()         # candidates' categories (empty: the start's)
    styles: tuple[str, ...] = ()
    exclude_shapes: tuple[str, ...] = ()
    preferences: Preferences = field(default_factory=Preferences)
    refine_contact: bool = True
    frame: Frame = field(default_factory=Frame)


@dataclass(frozen=True)
class Start:
    """Where an assembly starts: a catalog part at its place in its source shape, placed catalog
    parts (an assembly being edited), a cloud, or a cloud with placed parts.

    Shapes:
        points: (M, 3) float32 canonical (the cloud; empty for none).
        part_translations: (len(parts), 3) float64 canonical.
    """

    kind: Literal["part", "parts", "points", "mesh"]
    part_index: int | None = None
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.float32))
    area: float | None = None                # surface area of the cloud (None: estimated from it)
    parts: tuple[int, ...] = ()              # catalog rows of already placed parts
    part_translations: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


@dataclass
class Node:
    """One placed part: a step of the chain, or a node of the tree.

    Shapes:
        translation, contact_offset: (3,) float64, canonical frame (translation includes the offset).
    """

    node: int
    parent: int | None                       # None: a child of the start
    depth: int                               # 1 for the first added part
    suggestion: Suggestion                   # the engine's suggestion (rank, score, mode, scale, ...)
    translation: np.ndarray
    contact_offset: np.ndarray
    distance: float                          # to its mode's mean, in RMS standard deviations
    stop_reason: str | None = None           # set on leaves: why this branch ended
    added_by: str = "likely"                 # the rule that chose it (an ``ADD_REASONS`` key)


@dataclass
class AssembleResult:
    start: Start
    start_translation: np.ndarray            # (3,) canonical: where the start sits (0 for a cloud)
    category: str | None                     # the category candidates were restricted to
    steps: list[Node]                        # the main chain: the first child at every depth
    nodes: list[Node]                        # every node (== steps without branching)
    stop_reason: str                         # why the main chain ended
    frame: Frame
    timings: dict[str, float] = field(default_factory=dict)


@dataclass
class _Placed:
    """One part of a state's assembly, in the canonical frame.

    Shapes:
        points: (S, 3) float64 placed samples (duplicate tests).   lo, hi: (3,) placed (scaled) box.
    """

    points: np.ndarray
    # Oriented samples for contact (normals NaN for a cloud), or how to make them: most
    # candidates are only checked, never placed, so their samples are drawn on first use.
    surface_source: Surface | Callable[[], Surface]
    area: float
    lo: np.ndarray
    hi: np.ndarray
    row: int | None = None                   # catalog row (None: a start cloud)
    tree: cKDTree | None = None

    def kdtree(self) -> cKDTree:
        if self.tree is None:
            self.tree = cKDTree(self.points)
        return self.tree

    @property
    def surface(self) -> Surface:
        if not isinstance(self.surface_source, Surface):
            self.surface_source = self.surface_source()
        return self.surface_source


class _State:
    """The parts of one state and what is derived from them, each made once and shared by every
    candidate tested against the state and every child grown from it."""

    def __init__(self, parts: list[_Placed], groups: frozenset[int]):
        self.parts = parts
        self.groups = groups                 # near-duplicate groups of its catalog parts
        self.lo = np.array([p.lo for p in parts])
        self.hi = np.array([p.hi for p in parts])
        self.rows = np.array([p.row for p in parts if p.row is not None], dtype=np.int64)
        self._points: np.ndarray | None = None
        self._tree: cKDTree | None = None
        self._assembly: Assembly | None = None

    def points(self) -> np.ndarray:
        """Every placed part's samples, (S, 3) float64 canonical."""
        if self._points is None:
            self._points = np.concatenate([p.points for p in self.parts])
        return self._points

    def tree(self) -> cKDTree:
        """A KD-tree over every placed part's samples."""
        if self._tree is None:
            self._tree = cKDTree(self.points())
        return self._tree

    def assembly(self) -> Assembly:
        """The contact side: every placed part's oriented samples."""
        if self._assembly is None:
            self._assembly = Assembly(Surface.union([p.surface for p in self.parts]))
        return self._assembly


@dataclass(eq=False)   # compared by identity (its suggestion holds arrays)
class _Candidate:
    suggestion: Suggestion
    distance: float                          # to its nearest heavy mode's mean, RMS standard deviations
    placed: _Placed | None                   # where h puts it (made when the candidate is tested)
    near_mode: int                           # that nearest heavy mode
    redundant: bool | None = None            # the step's verdict once tested (None: not yet)
    added_by: str = "likely"                 # the rule that picks it, when picked (``ADD_REASONS``)


def estimate_area(points: np.ndarray) -> float:
    """Surface area covered by roughly uniform surface samples: about 4 n d^2, d the mean NN distance.

    (For n uniform samples on an area A the mean nearest-neighbour distance is about
    0.5 sqrt(A / n).)
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) < 2:
        return 0.0
    d, _ = cKDTree(pts).query(pts, k=2)
    return float(4.0 * len(pts) * np.mean(d[:, 1]) ** 2)


class Assembler:
    """Automatic assembly on a loaded engine (its networks and contact refinement) and one catalog
    snapshot (None: the engine's shipped catalog)."""

    def __init__(self, engine: SuggestionEngine, settings: Settings, snapshot: CatalogSnapshot | None = None):
        self.engine = engine
        self.snapshot = snapshot or engine.shipped
        self.catalog = self.snapshot.catalog
        self.settings = settings
        self._part_counts: tuple[float, float] = (0.0, np.inf)   # set per assembly (its category)
        self._cover_share = settings.assemble_cover_share          # likewise

    # ---------------------------------------------------------------- the parts of a state
    def _start_parts(self, start: Start) -> list[_Placed]:
        cat = self.catalog
        if start.part_index is not None:
            i = start.part_index
            return [self._catalog_part(i, cat.translations[i].astype(np.float64))]
        out = [self._catalog_part(i, np.asarray(t, dtype=np.float64))
               for i, t in zip(start.parts, start.part_translations, strict=True)]
        if len(start.points):
            pts = np.asarray(start.points, dtype=np.float64)
            area = start.area if start.area is not None else estimate_area(pts)
            if len(pts) > self.settings.contact_assembly_points:
                rng = np.random.default_rng(self.settings.seed)
                pts = pts[np.sort(rng.choice(len(pts), self.settings.contact_assembly_points, replace=False))]
            out.append(_Placed(pts, Surface(pts), max(area, 1e-9), pts.min(axis=0), pts.max(axis=0)))
        return out

    def _catalog_part(self, i: int, t: np.ndarray, scale: np.ndarray | None = None) -> _Placed:
        """Catalog part ``i`` scaled about its centre by ``scale`` (per axis) and moved to ``t``."""
        cat = self.catalog
        sc = np.ones(3) if scale is None else np.asarray(scale, dtype=np.float64)
        pts = cat.part_points(i).astype(np.float64) * sc + t
        contacts = self.engine.contacts

        def surface() -> Surface:
            return contacts.part_surface(cat, i).scaled(sc).moved(t)

        return _Placed(pts, surface, max(scaled_area(float(cat.records[i]["area"]), sc), 1e-9),
                       cat.bbox_min[i].astype(np.float64) * sc + t,
                       cat.bbox_max[i].astype(np.float64) * sc + t,
                       row=i)

    def _query(self, parts: list[_Placed], seed: int) -> np.ndarray:
        """The state's query: Q points over its parts, shares proportional to their areas (Q: the
        artifacts' ``query_points``, enough for every network; the engine resamples for each).

        Shapes:
            returns (Q, 3) float32 canonical.
        """
        n = self.engine.artifacts.query_points
        areas = np.array([p.area for p in parts])
        counts = np.maximum(1, np.floor(n * areas / areas.sum()).astype(int))
        counts[np.argmax(counts)] += n - counts.sum()
        rng = np.random.default_rng(seed)
        chunks = []
        for p, c in zip(parts, counts, strict=True):
            if c <= 0:
                continue
            pick = rng.choice(len(p.points), size=int(c), replace=bool(c > len(p.points)))
            chunks.append(p.points[pick])
        return np.concatenate(chunks).astype(np.float32)

    # ---------------------------------------------------------------- eligibility
    def _nearest_modes(self, result: SuggestResult, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every suggestion's nearest mode among those weighing at least ``assemble_min_mode_weight``,
        and its RMS distance to that mode's mean in the mode's standard deviations (inf: no mode
        is heavy enough).

        A part's ``mode`` (the largest responsibility) can be a mode of negligible weight whose
        narrow Gaussian happens to cover it; the likelihood test asks the modes that count.

        Shapes:
            weights: (K,) -> modes (C,) int64, distances (C,) float64.
        """
        assert result.mode_means is not None and result.mode_sigmas is not None
        heavy = np.flatnonzero(weights >= self.settings.assemble_min_mode_weight)
        n = len(result.suggestions)
        if len(heavy) == 0:
            return np.zeros(n, np.int64), np.full(n, np.inf)
        rows = np.array([sug.part_index for sug in result.suggestions], dtype=np.int64)
        d = sigma_distances(self.catalog.embeddings[rows], result.mode_means[heavy],
                            result.mode_sigmas[heavy])                                  # (C, H)
        best = np.argmin(d, axis=1)
        return heavy[best], d[np.arange(n), best]

    def _redundant(self, cand: _Placed, state: _State, mode: tuple[np.ndarray, np.ndarray] | None = None
                   ) -> bool:
        """Whether the candidate does the job of a part already at its spot (see the module doc).

        ``mode``: (D,) mean and (D,) standard deviations of the candidate's mode (the same-job
        test; None skips it).
        """
        s = self.settings
        if self._duplicate(cand, state.parts):
            return True
        if mode is not None and self._same_job(cand, state, *mode):
            return True
        if self._cover_share >= 1:
            return False
        d, _ = state.tree().query(cand.points, k=1, distance_upper_bound=s.assemble_cover_distance)
        return bool(np.mean(np.isfinite(d)) >= self._cover_share)

    def _same_job(self, cand: _Placed, state: _State, mean: np.ndarray, sigma: np.ndarray) -> bool:
        """A placed part in the same region that g cannot tell apart from the candidate here: boxes
        overlapping with IoU > ``assemble_overlap_iou`` and embeddings within
        ``assemble_same_job_sigmas`` RMS standard deviations of the candidate's mode; or centres
        within half the smaller part's size and embeddings within half that; or boxes overlapping
        with IoU > ``assemble_strong_overlap_iou`` and embeddings within
        ``assemble_strong_overlap_sigmas``; or boxes overlapping with IoU >
        ``assemble_overlap_iou`` and the placed part within ``assemble_overlap_mode_distance`` of
        the candidate's mode (``mean``, ``sigma``: (D,) each)."""
        s = self.settings
        if cand.row is None:
            return False
        rows = np.array([-1 if p.row is None else p.row for p in state.parts])
        emb = self.catalog.embeddings
        z = np.where(rows >= 0, sigma_distances(emb[rows], emb[cand.row][None], sigma[None])[:, 0], np.inf)
        overlap = box_iou(cand.lo, cand.hi, state.lo, state.hi) > s.assemble_overlap_iou
        # A part g sees as (nearly) the same one counts in a wider region: centres closer than
        # half the smaller part's size (two copies of a thin stretcher a little apart have boxes
        # that do not overlap).
        size = np.minimum(np.linalg.norm(cand.hi - cand.lo), np.linalg.norm(state.hi - state.lo, axis=1))
        near = np.linalg.norm((cand.hi + cand.lo) / 2 - (state.hi + state.lo) / 2, axis=1) < size / 2
        same = s.assemble_same_job_sigmas
        # Boxes that mostly coincide (a second roof over the roof) take a wider embedding
        # distance: two styles of one kind of part lie further apart than g's sigmas, and parts of
        # other kinds rarely share most of a box (a car's body pieces overlap less than this).
        strong = box_iou(cand.lo, cand.hi, state.lo, state.hi) > s.assemble_strong_overlap_iou
        # An overlapping part that the candidate's own mode already explains: the kind of part
        # that mode proposes is there (a roof under a second, shifted roof), whatever the two
        # parts' styles.
        met = np.where(rows >= 0, sigma_distances(emb[np.maximum(rows, 0)], mean[None], sigma[None])[:, 0],
                       np.inf) < s.assemble_overlap_mode_distance
        return bool(np.any((overlap & (z < same)) | (near & (z < same / 2))
                           | (strong & (z < s.assemble_strong_overlap_sigmas)) | (overlap & met)))

    def _like_overlapping(self, cand: _Placed, state: _State) -> bool:
        """Whether the candidate's box overlaps a placed part's with IoU above
        ``assemble_overlap_iou`` and about the same extents (each within
        ``assemble_duplicate_size_ratio``), whatever the two parts' embeddings. On training
        starts the missing-spot rule, with every nearest shape voting, gave 86.4% good runs with this
        test, 85.6% without (a second leg through the legs) and 84.7% with any overlap forbidden (a
        sofa's seat overlaps its cushions)."""
        s = self.settings
        overlap = box_iou(cand.lo, cand.hi, state.lo, state.hi) > s.assemble_overlap_iou
        similar = _like_sized(_extents(cand.lo, cand.hi) / _extents(state.lo, state.hi),
                              s.assemble_duplicate_size_ratio)
        return bool(np.any(overlap & similar))

    def _duplicate(self, cand: _Placed, parts: list[_Placed]) -> bool:
        """Whether the candidate repeats a placed part's geometry at the same spot (see module doc)."""
        s = self.settings
        size = _extents(cand.lo, cand.hi)
        centre = (cand.hi + cand.lo) / 2
        margin = s.assemble_duplicate_distance
        for p in parts:
            if np.linalg.norm(centre - (p.hi + p.lo) / 2) < s.assemble_duplicate_centre:
                ratio = size / _extents(p.lo, p.hi)
                similar = bool(_like_sized(ratio, s.assemble_duplicate_size_ratio))
                around = bool(np.all(p.lo >= cand.lo - margin) and np.all(p.hi <= cand.hi + margin))
                # At the same spot only a much larger part of another profile that encloses the
                # placed one is something else (a hull around its deck); a longer rod on a shorter
                # one, a tyre on a hub, a part nested in or crossing the placed one are not.
                across = np.arange(3) != np.argmax(size)
                profile = np.all(ratio[across] <= s.assemble_duplicate_size_ratio)
                enclosing = around and not profile and np.prod(ratio) >= s.assemble_duplicate_contain_ratio
                if similar or not enclosing:
                    return True
            if s.assemble_duplicate_distance > 0 and _samples_within(cand, p, s.assemble_duplicate_distance):
                return True
        return False

    def _likely(self, result: SuggestResult, weights: np.ndarray) -> list[_Candidate]:
        """The suggestions likely enough (near a heavy enough mode), best ``rank_score`` first, unplaced."""
        if not result.suggestions:
            return []
        modes, dist = self._nearest_modes(result, weights)
        out = [_Candidate(sug, float(d), None, int(m))
               for sug, d, m in zip(result.suggestions, dist, modes, strict=True)
               if d <= self.settings.assemble_max_distance]
        # The list came mode-balanced; walk it by the answer's own key (likelihood less the fit
        # penalties): on training starts 80.0% good runs against 77.2% by likelihood (128 engine
        # candidates; docs/modeling.md).
        out.sort(key=lambda c: -c.suggestion.rank_score)
        return out

    def _eligible(self, result: SuggestResult, likely: list[_Candidate], state: _State
                  ) -> Iterator[_Candidate]:
        """The likely candidates that do no placed part's job, best first, tested lazily (each
        once per step: a step that ends in the open-mode rule walks candidates ``_choose`` tested)."""
        assert result.mode_means is not None and result.mode_sigmas is not None
        means = result.mode_means.astype(np.float64)
        sigmas = result.mode_sigmas.astype(np.float64)
        for c in likely:
            if c.redundant is None:
                sug = c.suggestion
                c.placed = self._catalog_part(sug.part_index, np.asarray(sug.translation, dtype=np.float64),
                                              sug.scale)
                c.redundant = self._redundant(c.placed, state, (means[c.near_mode], sigmas[c.near_mode]))
            if not c.redundant:
                yield c

    def _best_placed(self, result: SuggestResult, weights: np.ndarray, state: _State) -> float:
        """The highest log-likelihood of a placed catalog part under the step's mixture (-inf: none)."""
        assert result.mode_means is not None and result.mode_sigmas is not None
        if len(state.rows) == 0:
            return -np.inf
        live = np.flatnonzero(weights > 0)
        ll, _ = mixture_log_likelihood(self.catalog.embeddings[state.rows], weights[live],
                                       result.mode_means[live], result.mode_sigmas[live])
        return float(np.max(ll))

    def _choose(self, eligible: Iterator[_Candidate], n: int, strategy: Strategy, weights: np.ndarray,
                temperature: float, rng: np.random.Generator) -> list[_Candidate]:
        """Up to ``n`` picks that differ (other modes first, no near-identical siblings).

        greedy: the best first (``rank_score``: the likelihood less the fit penalties); sample: a
        mode drawn by weight ** (1 / temperature), then its best part. Candidates are drawn from
        ``eligible`` only as far as needed.
        """
        seen: list[_Candidate] = []
        exhausted = False
        apart = self.settings.assemble_branch_min_distance

        def more() -> bool:
            nonlocal exhausted
            if exhausted:
                return False
            nxt = next(eligible, None)
            if nxt is None:
                exhausted = True
                return False
            seen.append(nxt)
            return True

        picks: list[_Candidate] = []
        used_modes: set[int] = set()
        while len(picks) < n:
            if strategy == "greedy" and n == 1:
                if not seen and not more():
                    break
                picks.append(seen[0])
                break
            while more():  # a tree or a draw by mode needs every eligible candidate's mode
                pass
            left = [c for c in seen if not any(c is p or _near_identical(c, p, apart) for p in picks)]
            if not left:
                break
            fresh = [c for c in left if c.near_mode not in used_modes] or left
            if strategy == "greedy":
                pick = fresh[0]
            else:
                modes = sorted({c.near_mode for c in fresh})
                w = np.array([weights[m] for m in modes], dtype=np.float64) ** (1.0 / temperature)
                w = w / w.sum() if w.sum() > 0 else np.full(len(w), 1.0 / len(w))
                mode = modes[int(rng.choice(len(modes), p=w))]
                pick = next(c for c in fresh if c.near_mode == mode)  # the mode's most likely
            picks.append(pick)
            used_modes.add(pick.near_mode)
        return picks

    # ---------------------------------------------------------------- the search
    def _check(self, start: Start, options: AssembleOptions) -> tuple[int, int]:
        s = self.settings
        max_parts = s.assemble_max_parts if options.max_parts is None else options.max_parts
        if not 1 <= max_parts <= s.max_assemble_parts:
            raise InputError("max_parts_out_of_range", f"max_parts must be between 1 and "
                             f"{s.max_assemble_parts}, found {max_parts}")
        if not 1 <= options.branching <= s.max_assemble_branching:
            raise InputError("branching_out_of_range", f"branching must be between 1 and "
                             f"{s.max_assemble_branching}, found {options.branching}")
        if not options.temperature > 0:
            raise InputError("bad_temperature", f"temperature must be > 0, found {options.temperature}")
        if start.part_index is None and not start.parts and len(start.points) < s.min_points:
            raise InputError("too_few_points", f"{len(start.points)} start points given, at least "
                             f"{s.min_points} are needed")
        if len(start.parts) > s.max_assemble_parts:
            raise InputError("too_many_parts", f"{len(start.parts)} start parts given, at most "
                             f"{s.max_assemble_parts} are accepted")
        options.preferences.check(self.engine.artifacts.n_modes)
        return max_parts, (s.assemble_max_nodes if options.branching > 1 else max_parts)

    def assemble(self, start: Start, options: AssembleOptions | None = None) -> AssembleResult:
        """Grow an assembly from ``start``: a chain of steps, or a tree with ``branching`` >= 2."""
        options = options or AssembleOptions()
        max_parts, budget = self._check(start, options)
        t0 = time.perf_counter()
        cat = self.catalog
        category: str | None = None
        if options.categories:
            cat.category_codes(list(options.categories))  # unknown names fail here
        elif start.part_index is not None:
            category = cat.records[start.part_index]["category"]
        elif start.parts:
            category = cat.records[start.parts[0]]["category"]
        rng = np.random.default_rng(options.seed)
        only = options.categories[0] if len(options.categories) == 1 else None
        self._part_counts = self.part_counts(category or only)
        self._cover_share = self.cover_share(category or only)
        base = self._start_parts(start)
        nodes: list[Node] = []
        states: dict[int | None, _State] = {None: _State(base, frozenset(
            int(cat.group[p.row]) for p in base if p.row is not None))}
        reached: set[frozenset[int]] = {states[None].groups}   # part sets some branch already has
        queue: deque[tuple[int | None, int]] = deque([(None, 0)])   # (node, depth)
        leaf_reason: dict[int | None, str] = {}
        timings = {"suggest": 0.0, "choose": 0.0, "contact": 0.0}
        # A mode-balanced list: when g's heaviest mode only offers more of what is placed, the
        # other kinds still have candidates to choose from.
        suggest_options = SuggestOptions(
            k=min(self.settings.assemble_candidates, self.settings.max_k), styles=options.styles,
            exclude_shapes=options.exclude_shapes, preferences=replace(options.preferences, diversity=True),
            refine_contact=False, complement_check=False)  # own checks (step 3)
        while queue:
            parent, depth = queue.popleft()
            state = states.pop(parent)   # states are only needed until expanded (trees stay small)
            if depth >= max_parts:
                leaf_reason[parent] = "max_parts"
                continue
            if len(nodes) >= budget:
                leaf_reason[parent] = "node_budget"
                continue
            cats = options.categories or ((category,) if category else ())
            query = self._query(state.parts, self.settings.seed + len(nodes))
            picks, reason = self._expand(query, state, options, replace(suggest_options, categories=cats),
                                         min(options.branching, budget - len(nodes)), rng, reached, timings)
            if not picks:
                leaf_reason[parent] = reason
                continue
            for c in picks:
                t = time.perf_counter()
                trans, offset, placed = self._refined(c, state, options.refine_contact)
                timings["contact"] += time.perf_counter() - t
                node = Node(node=len(nodes), parent=parent, depth=depth + 1, suggestion=c.suggestion,
                            translation=trans, contact_offset=offset, distance=c.distance,
                            added_by=c.added_by)
                nodes.append(node)
                group = int(cat.group[c.suggestion.part_index])
                child = _State([*state.parts, placed], state.groups | {group})
                reached.add(child.groups)
                states[node.node] = child
                queue.append((node.node, depth + 1))
                if category is None and not options.categories:
                    category = c.suggestion.category  # a cloud's assembly keeps the first part's category
        for n_ in nodes:
            n_.stop_reason = leaf_reason.get(n_.node)
        steps = self._main_chain(nodes)
        stop = leaf_reason.get(steps[-1].node if steps else None, "max_parts")
        start_t = (cat.translations[start.part_index].astype(np.float64) if start.part_index is not None
                   else np.zeros(3))
        timings["total"] = time.perf_counter() - t0
        return AssembleResult(start=start, start_translation=start_t, category=category, steps=steps,
                              nodes=nodes, stop_reason=stop, frame=options.frame, timings=timings)

    def _expand(self, query: np.ndarray, state: _State, options: AssembleOptions, suggest: SuggestOptions,
                n: int, rng: np.random.Generator, reached: set[frozenset[int]], timings: dict[str, float]
                ) -> tuple[list[_Candidate], str]:
        """The picks for one state, from up to ``assemble_candidate_rounds`` rounds of candidates.

        When every likely candidate of a round does a placed part's job (g's nearest parts are
        more of what is placed: a one-mode mixture offers bodies after the body), the next round
        asks for the following candidates, the tested ones excluded.
        """
        tested: list[str] = []
        for round_ in range(self.settings.assemble_candidate_rounds):
            t = time.perf_counter()
            result = self.engine.suggest(query, replace(
                suggest, exclude_parts=tuple(tested)) if tested else suggest, snapshot=self.snapshot)
            timings["suggest"] += time.perf_counter() - t
            t = time.perf_counter()
            picks, why = self._step(result, state, options, n, rng, reached)
            timings["choose"] += time.perf_counter() - t
            if picks:
                return picks, ""
            if why == "complete":
                return self._missing_spot_picks(query, state, options, suggest, n, rng, reached, timings)
            if why != "duplicates":
                # After a round of duplicates, running out of (likely) candidates still means
                # that every likely one did a placed part's job.
                return [], why if round_ == 0 else "duplicates"
            tested += [sug.part_id for sug in result.suggestions]
        return [], "duplicates"

    def _missing_spot_picks(self, query: np.ndarray, state: _State, options: AssembleOptions,
                            suggest: SuggestOptions, n: int, rng: np.random.Generator,
                            reached: set[frozenset[int]], timings: dict[str, float]
                            ) -> tuple[list[_Candidate], str]:
        """At a step that would end ``complete``: the picks placed at a spot where most of the
        category's training shapes nearest to the state have a part the state lacks
        (``templates.missing_spots``), tried spot by spot, most voted first, among candidates within
        ``assemble_gap_max_distance`` of their mode's mean; none: complete.

        Why: g's mixture can want nothing more while the object lacks a part almost every shape of
        the data has (a rifle's body between its stock and barrel, a sofa's seat under its
        cushions); on training starts 85.3% good runs against 82.2%, held out 83.4% against 82.6%
        (docs/modeling.md).
        """
        s = self.settings
        if (s.assemble_gap_neighbours <= 0 or len(suggest.categories) != 1
                or len(state.parts) >= self._part_counts[1]):
            return [], "complete"
        t = time.perf_counter()
        templates = [tm for tm in self.templates(suggest.categories[0])
                     if tm.shape_id not in options.exclude_shapes]
        spots = missing_spots(state.points(), templates,
                              s.assemble_gap_neighbours, s.assemble_cover_distance, s.assemble_gap_uncovered,
                              s.assemble_gap_share, s.assemble_gap_radius, s.seed, len(state.parts))
        timings["choose"] += time.perf_counter() - t
        for centre, _ in spots:
            t = time.perf_counter()
            spot = Region.ball(centre, s.assemble_gap_radius)
            result = self.engine.suggest(query, replace(suggest, region=spot), snapshot=self.snapshot)
            timings["suggest"] += time.perf_counter() - t
            t = time.perf_counter()
            picks: list[_Candidate] = []
            if result.suggestions:
                weights = options.preferences.weights(result.mode_weights)
                likely = self._unreached(self._likely(result, weights), state, reached, n)
                # The spot is one the state leaves empty: a part as large as a placed one it
                # overlaps is that part again (a second leg through the legs), not the missing one.
                # A part g did not ask for must still be a typical draw of one of its modes (a seat
                # block under a finished chair's seat lies 1.4-1.7 sigmas out, a sofa's missing
                # seat 0.75-0.9).
                likely = [c for c in likely if c.distance <= s.assemble_gap_max_distance]
                fresh = (c for c in self._eligible(result, likely, state)
                         if c.placed is not None and not self._like_overlapping(c.placed, state))
                picks = self._choose(fresh, n, options.strategy, weights,
                                     options.temperature, rng)
            timings["choose"] += time.perf_counter() - t
            if picks:
                for c in picks:
                    c.added_by = "missing_spot"
                return picks, ""
        return [], "complete"

    def _unreached(self, likely: list[_Candidate], state: _State, reached: set[frozenset[int]], n: int
                   ) -> list[_Candidate]:
        """``likely`` without the candidates that would take a tree's branch (``n`` >= 2) to a set
        of parts another branch already has (A then B, B then A); a chain keeps them all."""
        if n == 1:
            return likely
        group = self.catalog.group
        return [c for c in likely if state.groups | {int(group[c.suggestion.part_index])} not in reached]

    def _step(self, result: SuggestResult, state: _State, options: AssembleOptions, n: int,
              rng: np.random.Generator, reached: set[frozenset[int]]) -> tuple[list[_Candidate], str]:
        """The picks of one expansion, or none and the reason (a ``STOP_REASONS`` key)."""
        if not result.suggestions:
            return [], "no_candidates"
        weights = options.preferences.weights(result.mode_weights)
        likely = self._likely(result, weights)
        if not likely:
            return [], "unlikely"
        fresh = self._unreached(likely, state, reached, n)
        least, most = self._part_counts
        if len(state.parts) >= most:
            return [], "complete"
        # Complete when the best pick is no more likely than a placed part. Tested first on the
        # most likely candidate: no pick, nor any candidate of a later round (the next, less
        # likely ones), can beat it, so the rounds that would find only parts doing placed
        # parts' jobs are skipped.
        can_end = len(state.parts) >= least and self._fills_frame(state)
        best = self._best_placed(result, weights, state) if can_end else np.inf
        placed = best + self.settings.assemble_complete_margin
        if can_end and likely[0].suggestion.score < placed:
            return self._open_mode_picks(result, weights, state, fresh, best, n)
        picks = self._choose(self._eligible(result, fresh, state), n, options.strategy, weights,
                             options.temperature, rng)
        if not picks:
            return [], "duplicates"
        if can_end and max(c.suggestion.score for c in picks) < placed:
            return self._open_mode_picks(result, weights, state, fresh, best, n)
        return picks, ""

    def _open_mode_picks(self, result: SuggestResult, weights: np.ndarray, state: _State,
                         likely: list[_Candidate], best_placed: float, n: int = 1
                         ) -> tuple[list[_Candidate], str]:
        """At a step that would end ``complete``: the best eligible candidate of the heaviest mode
        that no placed part explains (``open_modes``) whose log-likelihood is within
        ``assemble_open_mode_margin`` of the most likely placed part's (``best_placed``), and for
        a tree (``n`` >= 2) those of the next unmet modes, up to ``n`` that differ; none: complete.

        Why: "complete" compares likelihoods, and a mixture's heaviest mode can keep offering more
        of what is placed (legs after legs) while a lighter mode of another kind stays unmet
        (a rifle's magazine or body). Chosen on training starts (docs/modeling.md).
        """
        s = self.settings
        if s.assemble_open_mode_weight <= 0 or len(state.rows) == 0:
            return [], "complete"
        assert result.mode_means is not None and result.mode_sigmas is not None
        unmet = open_modes(self.catalog.embeddings[state.rows], weights, result.mode_means,
                           result.mode_sigmas, s.assemble_open_mode_weight, s.assemble_open_mode_distance)
        floor = best_placed - s.assemble_open_mode_margin
        picks: list[_Candidate] = []
        for mode in unmet:
            pick = next(self._eligible(result, [c for c in likely if c.near_mode == mode
                                                and c.suggestion.score >= floor], state), None)
            if pick is not None and not any(
                    _near_identical(pick, p, s.assemble_branch_min_distance) for p in picks):
                pick.added_by = "unmet_mode"
                picks.append(pick)
                if len(picks) >= n:
                    break
        return (picks, "") if picks else ([], "complete")

    def part_counts(self, category: str | None) -> tuple[float, float]:
        """How many parts the catalog's shapes of ``category`` have (all shapes without one): the
        ``assemble_complete_quantiles`` of the count per shape, the data's own statistics."""
        cat = self.catalog
        keep = (np.ones(len(cat), bool) if category is None
                else cat.category_of == cat.category_codes([category])[0])
        counts = np.bincount(cat.shape_of[keep])
        counts = counts[counts > 0]
        if len(counts) == 0:
            return 0.0, np.inf
        lo, hi = self.settings.assemble_complete_quantiles
        return float(np.quantile(counts, lo)), float(np.quantile(counts, hi))

    def cover_share(self, category: str | None) -> float:
        """The cover rule's share for an assembly of ``category`` (see ``assemble_cover_quantile``):
        made once per snapshot and category from the catalog's training shapes."""
        s = self.settings
        if s.assemble_cover_quantile <= 0 or s.assemble_cover_share >= 1:
            return s.assemble_cover_share
        def make() -> float:
            shares = own_cover_shares(self.catalog, category, s.assemble_cover_distance,
                                      s.assemble_cover_shapes, s.seed, self.training_shapes())
            return float(np.quantile(shares, s.assemble_cover_quantile)) if len(shares) else 0.0
        return max(s.assemble_cover_share, _per_snapshot(_COVER_SHARES, self._data_owner(), category, make))

    def templates(self, category: str) -> list[ShapeTemplate]:
        """The category's training shapes as the missing-spot rule reads them
        (``templates.shape_templates``), made once per snapshot and category."""
        def make() -> list[ShapeTemplate]:
            s = self.settings
            return shape_templates(self.catalog, category, s.assemble_cover_shapes, s.seed,
                                   self.training_shapes())
        return _per_snapshot(_TEMPLATES, self._data_owner(), category, make)

    def training_shapes(self) -> dict[str, list[int]]:
        """The rows of each training shape (``split_shapes(catalog, "train")``), walked once per
        snapshot that owns the data (``_data_owner``) for every category's cover share and
        templates: a walk per category and kind was 19 walks over every record at the warm-up
        (3-13 ms each for the shipped catalog's 8,300 records, linear in the records)."""
        shipped = self._shipped_training()
        if shipped:
            return shipped
        own = self.snapshot   # no training split shipped: this snapshot owns its data (_data_owner)
        return _per_snapshot(_TRAINING_SHAPES, own, None, lambda: split_shapes(own.catalog, "train"))

    def _shipped_training(self) -> dict[str, list[int]]:
        """The shipped snapshot's training shapes, without the fallback to every multi-part shape
        (empty when it has no training split): one walk answers both whether it owns the data
        and what the data is."""
        shipped = self.engine.shipped
        return _per_snapshot(_SHIPPED_TRAINING, shipped, None,
                             lambda: split_shapes(shipped.catalog, "train", fallback=False))

    def warm(self) -> None:
        """Make every category's cover share and templates now (the server's warm-up: about 0.5 s
        for the shipped catalog's nine categories), so that the first ``/assemble`` of a category
        costs what the next one does instead of 13-80 ms more."""
        for category in self.catalog.categories:
            self.cover_share(category)
            self.templates(category)

    def _data_owner(self) -> CatalogSnapshot:
        """The snapshot under which the cover shares and templates of this one are kept: the
        shipped one when it has training shapes, since catalog writes add only parts of split
        "added" and never delete a shipped part (``CatalogWriter.delete``), so every later
        snapshot's training shapes are the shipped ones, row for row, and its values the same.
        Kept per snapshot, every catalog write made the next ``/assemble`` of each category pay
        them again (17-68 ms). A catalog with no training split reads all its multi-part shapes,
        added ones too: its own snapshot."""
        return self.engine.shipped if self._shipped_training() else self.snapshot

    def _fills_frame(self, state: _State) -> bool:
        """Whether the state spans the complete object's frame: a complete object's box is centred
        at the origin and its surface reaches radius 1 (the canonical frame's definition), within
        ``assemble_frame_tolerance``. A part missing at an end leaves the box off centre."""
        tol = self.settings.assemble_frame_tolerance
        centre = (state.lo.min(axis=0) + state.hi.max(axis=0)) / 2
        reach = max(float(np.max(np.linalg.norm(p.points, axis=1))) for p in state.parts)
        return bool(np.linalg.norm(centre) <= tol and reach >= 1 - tol)

    def _refined(self, c: _Candidate, state: _State, refine: bool) -> tuple[np.ndarray, np.ndarray, _Placed]:
        """h's translation nudged into contact with the state's parts (``engine.refine_against``),
        unless refinement is off or the moved part would then do a placed part's job."""
        sug, placed = c.suggestion, c.placed
        assert placed is not None
        t = np.asarray(sug.translation, dtype=np.float64)
        zero = np.zeros(3)
        if not refine:
            return t, zero, placed
        offset = self.engine.refine_against(state.assembly(), np.array([sug.part_index]), t[None],
                                            np.asarray(sug.scale, dtype=np.float64)[None],
                                            catalog=self.catalog)[0]
        if not np.any(offset):
            return t, zero, placed
        moved = self._catalog_part(sug.part_index, t + offset, sug.scale)
        if self._redundant(moved, state):
            return t, zero, placed
        return t + offset, offset, moved

    @staticmethod
    def _main_chain(nodes: list[Node]) -> list[Node]:
        """The first child at every depth, from the start down."""
        chain: list[Node] = []
        parent: int | None = None
        while True:
            child = next((n for n in nodes if n.parent == parent), None)
            if child is None:
                return chain
            chain.append(child)
            parent = child.node


def own_cover_shares(catalog: Catalog, category: str | None, distance: float, max_shapes: int,
                     seed: int = 0, rows_of: dict[str, list[int]] | None = None) -> np.ndarray:
    """For each part of the catalog's training shapes of ``category`` (every category: None), the
    share of its stored samples within ``distance`` of the rest of its shape: how much real parts
    lie on each other (labels are not read). At most ``max_shapes`` shapes (a seeded draw), so
    that a catalog grown by writes costs no more on its first ``/assemble`` than the shipped one.
    ``rows_of`` as ``drawn_training_shapes`` takes it.

    Shapes:
        returns (parts,) float64.
    """
    out: list[np.ndarray] = []
    for _, rows in drawn_training_shapes(catalog, category, max_shapes, seed, rows_of):
        clouds = [catalog.part_points(i).astype(np.float64) + catalog.translations[i] for i in rows]
        start = np.concatenate([[0], np.cumsum([len(c) for c in clouds])]).astype(np.int64)
        # Compiled, on contact refinement's grids (contact_kernel.cover_shares): a k-d tree of the
        # rest of the shape for each part made the first /assemble of a category 86-450 ms; the
        # same shares.
        out.append(contact_kernel.cover_shares(np.concatenate(clouds), start, float(distance)))
    return np.concatenate(out) if out else np.zeros(0)


# What each catalog snapshot's data says per category, made on first use: the cover share
# (``Assembler.cover_share``) and the template shapes (``Assembler.templates``), kept under the
# shipped snapshot for the snapshots that share its training shapes (``Assembler._data_owner``).
_COVER_SHARES: weakref.WeakKeyDictionary[CatalogSnapshot, dict[str | None, float]] = (
    weakref.WeakKeyDictionary())
_TEMPLATES: weakref.WeakKeyDictionary[CatalogSnapshot, dict[str | None, list[ShapeTemplate]]] = (
    weakref.WeakKeyDictionary())
_SHIPPED_TRAINING: weakref.WeakKeyDictionary[CatalogSnapshot, dict[str | None, dict[str, list[int]]]] = (
    weakref.WeakKeyDictionary())
_TRAINING_SHAPES: weakref.WeakKeyDictionary[CatalogSnapshot, dict[str | None, dict[str, list[int]]]] = (
    weakref.WeakKeyDictionary())
_CACHE_LOCK = threading.Lock()
_T = TypeVar("_T")


def _per_snapshot(cache: weakref.WeakKeyDictionary[CatalogSnapshot, dict[str | None, _T]],
                  snapshot: CatalogSnapshot, category: str | None, make: Callable[[], _T]) -> _T:
    """``cache[snapshot][category]``, made by ``make`` on first use. Made outside the lock: two
    first requests may both make it (the same value), but no request waits on another's."""
    with _CACHE_LOCK:
        value = cache.setdefault(snapshot, {}).get(category)
    if value is None:
        value = make()
        with _CACHE_LOCK:
            cache.setdefault(snapshot, {})[category] = value
    return value


def open_modes(placed: np.ndarray, weights: np.ndarray, means: np.ndarray, sigmas: np.ndarray,
               min_weight: float, distance: float) -> list[int]:
    """The modes of weight at least ``min_weight`` that no placed part explains, heaviest first:
    no placed embedding lies within ``distance`` of the mode's mean, in root-mean-square standard
    deviations of that mode.

    Shapes:
        placed (P, D), weights (K,), means (K, D), sigmas (K, D) -> mode indices.
    """
    heavy = [int(m) for m in np.argsort(-weights, kind="stable") if weights[m] >= min_weight]
    if not heavy:
        return []
    if len(placed) == 0:
        return heavy
    nearest = sigma_distances(placed, means[heavy], sigmas[heavy]).min(axis=0)             # (H,)
    return [m for m, d in zip(heavy, nearest, strict=True) if d > distance]


def _extents(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Box extents, at least 1e-3 each (a flat part has a thickness to compare).

    Shapes:
        lo, hi: (..., 3) -> (..., 3).
    """
    return np.maximum(hi - lo, 1e-3)


def _like_sized(ratio: np.ndarray, most: float) -> np.ndarray:
    """Whether boxes are about the same size: every extent ratio within ``most`` either way.

    Shapes:
        ratio: (..., 3) extent ratios -> (...) bool.
    """
    return np.all((ratio <= most) & (ratio >= 1 / most), axis=-1)


def _near_identical(a: _Candidate, b: _Candidate, distance: float) -> bool:
    """The same part, or parts whose placed samples lie within ``distance`` Chamfer distance."""
    if a.suggestion.part_index == b.suggestion.part_index:
        return True
    pa, pb = a.placed, b.placed
    assert pa is not None and pb is not None, "candidates are placed when they are tested"
    return _samples_within(pa, pb, distance)


def _samples_within(a: _Placed, b: _Placed, distance: float) -> bool:
    """Whether two placed parts' samples lie within ``distance`` Chamfer distance; ``a`` is the
    one whose KD-tree is asked for last (``chamfer_below``)."""
    gap = np.maximum(0, np.maximum(a.lo - b.hi, b.lo - a.hi))
    if np.linalg.norm(gap) >= distance:
        return False  # boxes apart: every nearest neighbour is at least that far
    return chamfer_below(a.points, b.points, distance, a.kdtree, b.kdtree)
