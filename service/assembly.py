"""Automatic shape synthesis: start from one part (or a cloud, or a mesh), then suggest and place.

The paper's automatic assembly (Section 6.1): "start with a random component, and iteratively
add a component by sampling from the predicted distribution", either the most probable one at
every step or, for a tree of possibilities, several choices per step. Each step here

1. builds the query: the placed parts' catalog samples in the canonical frame, area-weighted
   to the networks' N points (a start cloud counts with the area its points cover);
2. asks the engine for ``assemble_candidates`` suggestions as a mode-balanced gallery (so that
   every kind g proposes has candidates, even when its heaviest mode only offers more of what
   is placed), with the request's filters (by default the start part's category, or the first
   added part's when the start is a cloud or a mesh), placed by h without contact refinement;
3. keeps the *eligible* candidates:
   * likely enough: the part's mode has weight >= ``assemble_min_mode_weight`` and the part's
     embedding lies within ``assemble_max_distance`` root-mean-square standard deviations of
     that mode's mean (a typical draw from the mode is about 1);
   * not a duplicate of a placed part, judged on geometry alone (labels are never used): its
     placed samples within ``assemble_duplicate_distance`` Chamfer distance of a placed part's;
     or its box centred within ``assemble_duplicate_centre`` of a placed part's box (one part
     per spot: a second back where a back is, a tyre on a hub, a longer rod on a shorter one,
     crossing boxes), unless it encloses the placed part's box with at least
     ``assemble_duplicate_contain_ratio`` times its volume and another profile across its
     longest axis (a hull around its deck); boxes of about the same size (every extent within
     ``assemble_duplicate_size_ratio``) are duplicates even then;
   * not redundant: less than ``assemble_cover_share`` of its placed samples lie within
     ``assemble_cover_distance`` of the placed parts' samples (a part lying mostly where the
     assembly already has surface adds nothing: a second seat just above the first, a back
     pressed against the back);
4. picks among them: ``greedy`` takes the most likely (highest mixture log-likelihood);
   ``sample`` draws a mode with
   probability proportional to its weight (sharpened or flattened by ``temperature``) and takes
   that mode's most likely part (seeded);
5. refines the chosen part's placement against the placed parts' oriented samples
   (``service.contact``; off with ``refine_contact=False``).

It stops after ``max_parts`` parts or when no candidate is eligible (``stop_reason`` says which
rule ended it). With ``branching`` b >= 2 every state gets up to b children (different modes
first), expanded breadth-first until ``assemble_max_nodes`` parts are placed over the whole
tree: the paper's binary tree of possibilities for b = 2.

Everything runs in the canonical frame; the API maps translations to the caller's frame.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from scipy.spatial import cKDTree

from service.contact import Assembly, Surface, refine_offset
from service.engine import Suggestion, SuggestionEngine, SuggestOptions, SuggestResult
from service.errors import InputError
from service.frames import Frame
from service.preferences import Preferences

Strategy = Literal["greedy", "sample"]

# Why a chain (or a tree branch) ended.
STOP_REASONS = {
    "max_parts": "max_parts parts were added",
    "no_candidates": "the engine found no candidate part (filters too strict?)",
    "unlikely": "no candidate was likely enough (mode weight or distance to its mode's mean)",
    "duplicates": "every likely candidate duplicates a part already placed",
    "node_budget": "the tree reached assemble_max_nodes parts",
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
    suggestion: Suggestion                   # the engine's suggestion (rank, score, mode, ...)
    translation: np.ndarray
    contact_offset: np.ndarray
    distance: float                          # to its mode's mean, in RMS standard deviations
    stop_reason: str | None = None           # set on leaves: why this branch ended


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
    """One part of a state's assembly, in the canonical frame."""

    points: np.ndarray                       # (S, 3) float64 placed samples (duplicate tests)
    # Oriented samples for contact (normals NaN for a cloud), or how to make them: most
    # candidates are only checked, never placed, so their samples are drawn on first use.
    surface_source: Surface | Callable[[], Surface]
    area: float
    lo: np.ndarray                           # (3,) placed box
    hi: np.ndarray
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
    """Automatic assembly on a loaded engine (its catalog, networks and contact refinement)."""

    def __init__(self, engine: SuggestionEngine):
        self.engine = engine
        self.settings = engine.settings

    # ---------------------------------------------------------------- the parts of a state
    def _start_parts(self, start: Start) -> list[_Placed]:
        cat = self.engine.catalog
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

    def _catalog_part(self, i: int, t: np.ndarray) -> _Placed:
        cat = self.engine.catalog
        pts = cat.part_points(i).astype(np.float64) + t
        contacts = self.engine.contacts

        def surface() -> Surface:
            return contacts.part_surface(cat, i).moved(t)

        return _Placed(pts, surface, max(float(cat.records[i]["area"]), 1e-9),
                       cat.bbox_min[i].astype(np.float64) + t, cat.bbox_max[i].astype(np.float64) + t)

    def _query(self, parts: list[_Placed], seed: int) -> np.ndarray:
        """The state's query: N points over its parts, shares proportional to their areas.

        Shapes:
            returns (N, 3) float32 canonical.
        """
        n = self.engine.artifacts.n_points
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
    def _distance(self, result: SuggestResult, s: Suggestion) -> float:
        """RMS distance of the part's embedding to its mode's mean, in that mode's standard deviations."""
        assert result.mode_means is not None and result.mode_sigmas is not None
        y = self.engine.catalog.embeddings[s.part_index].astype(np.float64)
        z = (y - result.mode_means[s.mode]) / result.mode_sigmas[s.mode]
        return float(np.sqrt(np.mean(z * z)))

    def _redundant(self, cand: _Placed, parts: list[_Placed], surface: cKDTree | None = None) -> bool:
        """A duplicate of a placed part, or a part lying mostly where the assembly already has surface.

        ``surface``: a KD-tree over every placed part's samples (built here when not given).
        """
        s = self.settings
        if self._duplicate(cand, parts):
            return True
        if s.assemble_cover_share >= 1:
            return False
        if surface is None:
            surface = cKDTree(np.concatenate([p.points for p in parts]))
        d, _ = surface.query(cand.points, k=1, distance_upper_bound=s.assemble_cover_distance)
        return bool(np.mean(np.isfinite(d)) >= s.assemble_cover_share)

    def _duplicate(self, cand: _Placed, parts: list[_Placed]) -> bool:
        """Whether the candidate repeats a placed part's geometry at the same spot (see module doc)."""
        s = self.settings
        size = np.maximum(cand.hi - cand.lo, 1e-3)
        centre = (cand.hi + cand.lo) / 2
        margin = s.assemble_duplicate_distance
        for p in parts:
            p_size = np.maximum(p.hi - p.lo, 1e-3)
            if np.linalg.norm(centre - (p.hi + p.lo) / 2) < s.assemble_duplicate_centre:
                ratio = size / p_size
                similar = np.all((ratio <= s.assemble_duplicate_size_ratio)
                                 & (ratio >= 1 / s.assemble_duplicate_size_ratio))
                around = bool(np.all(p.lo >= cand.lo - margin) and np.all(p.hi <= cand.hi + margin))
                # At the same spot only a much larger part of another profile that encloses the
                # placed one is something else (a hull around its deck); a longer rod on a shorter
                # one, a tyre on a hub, a part nested in or crossing the placed one are not.
                across = np.arange(3) != np.argmax(size)
                profile = np.all(ratio[across] <= s.assemble_duplicate_size_ratio)
                enclosing = around and not profile and np.prod(ratio) >= s.assemble_duplicate_contain_ratio
                if similar or not enclosing:
                    return True
            if s.assemble_duplicate_distance > 0:
                box_gap = np.maximum(0, np.maximum(p.lo - cand.hi, cand.lo - p.hi))
                if np.linalg.norm(box_gap) >= s.assemble_duplicate_distance:
                    continue  # boxes apart: the Chamfer distance cannot be small
                d1, _ = p.kdtree().query(cand.points, k=1)
                d2, _ = cand.kdtree().query(p.points, k=1)
                if 0.5 * (d1.mean() + d2.mean()) < s.assemble_duplicate_distance:
                    return True
        return False

    def _eligible(self, result: SuggestResult, parts: list[_Placed]
                  ) -> tuple[list[tuple[Suggestion, _Placed, float]], str]:
        """Candidates that are likely enough and no duplicates, in rank order; else why there are none."""
        s = self.settings
        if not result.suggestions:
            return [], "no_candidates"
        out = []
        likely = 0
        surface = cKDTree(np.concatenate([p.points for p in parts]))
        for sug in result.suggestions:
            dist = self._distance(result, sug)
            if sug.mode_weight < s.assemble_min_mode_weight or dist > s.assemble_max_distance:
                continue
            likely += 1
            placed = self._catalog_part(sug.part_index, np.asarray(sug.translation, dtype=np.float64))
            if not self._redundant(placed, parts, surface):
                out.append((sug, placed, dist))
        out.sort(key=lambda e: -e[0].score)  # most likely first (the list came mode-balanced)
        return out, ("unlikely" if likely == 0 else "duplicates")

    def _choose(self, eligible: list[tuple[Suggestion, _Placed, float]], n: int, strategy: Strategy,
                weights: np.ndarray, temperature: float, rng: np.random.Generator) -> list[int]:
        """Positions in ``eligible`` of up to ``n`` picks (distinct modes first)."""
        modes = np.array([e[0].mode for e in eligible])
        left = list(range(len(eligible)))
        picks: list[int] = []
        used: set[int] = set()
        while left and len(picks) < n:
            fresh = [j for j in left if modes[j] not in used] or left
            if strategy == "greedy":
                j = fresh[0]
            else:
                cand_modes = sorted({int(modes[j]) for j in fresh})
                w = np.array([weights[m] for m in cand_modes], dtype=np.float64) ** (1.0 / temperature)
                w = w / w.sum() if w.sum() > 0 else np.full(len(w), 1.0 / len(w))
                mode = cand_modes[int(rng.choice(len(cand_modes), p=w))]
                j = next(j for j in fresh if modes[j] == mode)  # the mode's most likely part
            picks.append(j)
            used.add(int(modes[j]))
            left.remove(j)
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
        cat = self.engine.catalog
        category: str | None = None
        if options.categories:
            cat.category_codes(list(options.categories))  # unknown names fail here
        elif start.part_index is not None:
            category = cat.records[start.part_index]["category"]
        elif start.parts:
            category = cat.records[start.parts[0]]["category"]
        rng = np.random.default_rng(options.seed)
        base = self._start_parts(start)
        nodes: list[Node] = []
        placed_of: dict[int | None, list[_Placed]] = {None: base}
        queue: deque[tuple[int | None, int]] = deque([(None, 0)])   # (node, depth)
        leaf_reason: dict[int | None, str] = {}
        suggest_time = contact_time = 0.0
        while queue:
            parent, depth = queue.popleft()
            parts = placed_of[parent]
            if depth >= max_parts:
                leaf_reason[parent] = "max_parts"
                continue
            if len(nodes) >= budget:
                leaf_reason[parent] = "node_budget"
                continue
            cats = options.categories or ((category,) if category else ())
            t = time.perf_counter()
            # A mode-balanced list: when g's heaviest mode only offers more of what is placed,
            # the other kinds still have candidates to choose from.
            prefs = replace(options.preferences, diversity=True)
            result = self.engine.suggest(self._query(parts, self.settings.seed + len(nodes)), SuggestOptions(
                k=min(self.settings.assemble_candidates, self.settings.max_k), categories=cats,
                styles=options.styles, exclude_shapes=options.exclude_shapes,
                preferences=prefs, refine_contact=False, complement_check=False))  # own checks, step 3
            suggest_time += time.perf_counter() - t
            eligible, reason = self._eligible(result, parts)
            if not eligible:
                leaf_reason[parent] = reason
                continue
            weights = options.preferences.weights(result.mode_weights)
            n = min(options.branching, budget - len(nodes))
            for j in self._choose(eligible, n, options.strategy, weights, options.temperature, rng):
                sug, placed, dist = eligible[j]
                t = time.perf_counter()
                trans, offset, placed = self._refined(sug, placed, parts, options.refine_contact)
                contact_time += time.perf_counter() - t
                node = Node(node=len(nodes), parent=parent, depth=depth + 1, suggestion=sug,
                            translation=trans, contact_offset=offset, distance=dist)
                nodes.append(node)
                placed_of[node.node] = [*parts, placed]
                queue.append((node.node, depth + 1))
                if category is None and not options.categories:
                    category = sug.category  # a cloud's assembly keeps the first part's category
            del placed_of[parent]  # states are only needed until expanded (trees stay small)
        for n_ in nodes:
            n_.stop_reason = leaf_reason.get(n_.node)
        steps = self._main_chain(nodes)
        stop = leaf_reason.get(steps[-1].node if steps else None, "max_parts")
        start_t = (cat.translations[start.part_index].astype(np.float64) if start.part_index is not None
                   else np.zeros(3))
        timings = {"suggest": suggest_time, "contact": contact_time, "total": time.perf_counter() - t0}
        return AssembleResult(start=start, start_translation=start_t, category=category, steps=steps,
                              nodes=nodes, stop_reason=stop, frame=options.frame, timings=timings)

    def _refined(self, sug: Suggestion, placed: _Placed, parts: list[_Placed], refine: bool
                 ) -> tuple[np.ndarray, np.ndarray, _Placed]:
        """h's translation nudged into contact with the state's parts (unless off or a duplicate then)."""
        t = np.asarray(sug.translation, dtype=np.float64)
        zero = np.zeros(3)
        if not refine:
            return t, zero, placed
        assembly = Assembly(Surface.union([p.surface for p in parts]))
        r = refine_offset(placed.surface, assembly, self.engine.contacts.params)
        if not np.any(r.offset):
            return t, zero, placed
        moved = self._catalog_part(sug.part_index, t + r.offset)
        if self._redundant(moved, parts):
            return t, zero, placed
        return t + r.offset, r.offset, moved

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
