"""The complete object's frame, estimated from a partial one (an upload in its own units).

The networks work in the canonical frame of the *complete* object: its box centred at the
origin, its surface reaching radius 1, y up (``service.geometry.frames``). A designer uploading a chair
without legs, in millimetres and z up, cannot say where the centre and the radius of a chair
that does not exist yet are; scaling the partial mesh by its own box blows the seat and back up
to the size of a whole chair, and the model answers with seats and table tops.

``frame_hypotheses`` proposes frames the partial could sit in: for each allowed up axis, the
partial's box centre moved along the up axis (the missing parts may be below or above it) and
radii from the partial's own radius up to ``fit_frame_max_ratio`` times it. ``choose_frame``
keeps the hypothesis in which the partial looks most like the partial assemblies g was trained
on (``most_familiar``): the smallest familiarity distance of g's answer (``service.suggest.familiarity``: the
distance of its means and weights to the nearest answer for a training partial assembly). All
hypotheses of one upload run as one batch of mixture-only queries (``SuggestOptions.mixture_only``:
g alone, nothing searched or placed), through the micro-batcher for ``/suggest`` like any query.

Why not the model's own confidence (the mixture log-likelihood of the best suggestion, the first
rule): it grows as the partial shrinks in the frame, so it picked the largest radius tried for
most uploads. On 80 held-out shapes missing one part, put in random frames (up axis y or z,
radius 100-1000, anywhere), it found the up axis for 0.66 of them and a frame within 25% in
radius and 0.3 radius in centre for 0.05; the familiarity distance did for 0.88 and 0.56
(``complementme evaluate-frames``; docs/modeling.md "Frames for partial uploads"). The
distance alone still liked a partial at the bottom of a room much larger than the object, so a
prior on the radius is added:
``fit_frame_radius_prior`` (0.8, chosen on training shapes) times the log of the radius over the
partial's own, which raised the good frames to 0.93 of held-out shapes missing one part and 0.80
of those missing every part of one kind. Artifacts without a familiarity bank fall back to the
likelihood (``best_frame``).

Familiarity is what shapes nobody here made lack, so on real furniture the rule found the frame
of under half of the uploads. The category head, refitted on real furniture
(``training.category_head``), knows them better: ``fit_frame_category_weight`` (16) times the log
of its probability of the query's category (the named one, or the most probable) is added to the
score. Chosen on the generator's training shapes and on real furniture of makers the head was not
fitted on (docs/modeling.md "Frames for partial uploads"): good frames 0.888 -> 0.940 and 0.426
-> 0.626 with the category named, 0.888 -> 0.927 and 0.426 -> 0.456 without.

Shapes: points (M, 3) in the caller's units; frames map them to the canonical frame.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from service.errors import ServiceError
from service.geometry.frames import Frame, UpAxis
from service.settings import Settings
from service.suggest.engine import SuggestionEngine, SuggestOptions, SuggestResult
from service.suggest.snapshot import CatalogSnapshot

UP_AXES: tuple[UpAxis, ...] = ("y", "z")
# The smallest category probability the score reads: log(1e-6) * the weight bounds what one
# hypothesis can lose to the category term.
CATEGORY_FLOOR = 1e-6


@dataclass(frozen=True)
class FrameFit:
    """The frame chosen for a partial upload, and how sure the model was under each hypothesis."""

    frame: Frame
    score: float                                   # the chosen hypothesis's score (``choose_frame``)
    hypotheses: int                                # frames scored
    scores: list[float] = field(default_factory=list)


def frame_hypotheses(points: np.ndarray, up_axes: Sequence[UpAxis], ratios: Sequence[float],
                     shifts: Sequence[float]) -> list[Frame]:
    """Frames the partial could sit in (see the module doc).

    Args:
        points: (M, 3) the partial, caller units.
        up_axes: the caller's possible up axes.
        ratios: the complete object's radius over the partial's own radius (>= 1).
        shifts: where the partial sits along the up axis, from -1 (at the bottom of the room the
            radius leaves) to 1 (at the top).

    Shapes:
        points (M, 3) -> len(up_axes) * len(ratios) * len(shifts) frames, fewer when some coincide.
    """
    pts = np.asarray(points, dtype=np.float64)
    out: list[Frame] = []
    seen: set[tuple] = set()
    for up in up_axes:
        rot = Frame(up_axis=up).rotation
        q = pts @ rot.T                                    # caller axes -> canonical axes (y up)
        lo, hi = q.min(axis=0), q.max(axis=0)
        centre = (lo + hi) / 2
        own = float(np.max(np.linalg.norm(q - centre, axis=1)))
        if not own > 0:
            continue
        rel = q - centre
        across = np.linalg.norm(rel[:, [0, 2]], axis=1)    # distance from the up axis
        for ratio in ratios:
            radius = own * ratio
            # The centre may move along the up axis by d as long as every point stays within the
            # radius: (y - d)^2 + across^2 <= radius^2 for all points.
            reach = np.sqrt(np.maximum(radius ** 2 - across ** 2, 0.0))
            low, high = float(np.max(rel[:, 1] - reach)), float(np.min(rel[:, 1] + reach))
            for shift in shifts:
                c = centre.copy()
                # shift 1: the partial at the top of the room, so the centre below it (d = low)
                c[1] += (low + high) / 2 - shift * (high - low) / 2
                key = (up, round(radius / own, 6), round(float(c[1] - centre[1]) / own, 3))
                if key in seen:
                    continue
                seen.add(key)
                out.append(Frame(center=c @ rot, radius=radius, up_axis=up))
    return out


def best_frame(frames: Sequence[Frame], results: Sequence[SuggestResult | ServiceError]) -> FrameFit:
    """The hypothesis whose best suggestion is most likely under its own mixture (the rule for
    artifacts without a familiarity bank).

    A hypothesis whose query failed, or that found no suggestion, scores -inf.
    """
    assert len(frames) == len(results) and frames, f"{len(frames)} frames, {len(results)} results"
    scores = [max((s.score for s in r.suggestions), default=-np.inf) if isinstance(r, SuggestResult)
              else -np.inf for r in results]
    return _chosen(frames, np.asarray(scores, dtype=np.float64))


def most_familiar(frames: Sequence[Frame], distances: np.ndarray, radius_prior: float,
                  category_probabilities: np.ndarray | None = None, category_weight: float = 0.0) -> FrameFit:
    """The hypothesis of the smallest familiarity distance plus ``radius_prior`` times the log of
    its radius over the smallest one tried (the partial's own), less ``category_weight`` times the
    log of the category head's probability of the query's category under it (floored at
    ``CATEGORY_FLOOR``); the score is minus that sum.

    Shapes:
        distances, category_probabilities: (len(frames),).
    """
    assert len(frames) == len(distances) and frames, f"{len(frames)} frames, {len(distances)} distances"
    radii = np.array([f.radius for f in frames], dtype=np.float64)
    prior = radius_prior * np.log(radii / radii.min())
    scores = -np.asarray(distances, dtype=np.float64) - prior
    if category_probabilities is not None and category_weight > 0:
        scores = scores + category_weight * np.log(np.maximum(category_probabilities, CATEGORY_FLOOR))
    return _chosen(frames, scores)


def _chosen(frames: Sequence[Frame], scores: np.ndarray) -> FrameFit:
    best = int(np.argmax(scores))
    return FrameFit(frame=frames[best], score=float(scores[best]), hypotheses=len(frames),
                    scores=[float(s) for s in scores])


def fit_requested(asked: bool | None, framed: bool, upload: bool, settings: Settings) -> bool:
    """Whether a request gets a fitted frame: when it asks; when it does not say, a mesh upload
    sent without a frame does (``fit_frame_uploads``) and JSON points do not."""
    return asked if asked is not None else (upload and not framed and settings.fit_frame_uploads)


def up_axes_for(frame: Frame | None) -> tuple[UpAxis, ...]:
    """The up axes to try: the caller's, when it gave a frame; else every axis the API offers."""
    return UP_AXES if frame is None else (frame.up_axis,)


def hypotheses_of(settings: Settings, points: np.ndarray, up_axes: Sequence[UpAxis]) -> list[Frame]:
    """The frames fitting tries for a partial, from the settings' radii and shifts."""
    s = settings
    return frame_hypotheses(points, up_axes, _ratios(s.fit_frame_max_ratio, s.fit_frame_ratios),
                            np.linspace(-1.0, 1.0, s.fit_frame_shifts).tolist())


def scoring_queries(frames: Sequence[Frame], points: np.ndarray, options: SuggestOptions,
                    mixture_only: bool) -> list[tuple[np.ndarray, SuggestOptions]]:
    """One query per hypothesis: g's answer alone (``mixture_only``: its familiarity is the
    score), or a suggestion query without the costly steps (k = 1: its likelihood is)."""
    scoring = replace(options, k=1, refine_contact=False, complement_check=False, mixture_only=mixture_only)
    return [(points, replace(scoring, frame=f)) for f in frames]


def fit_queries(engine: SuggestionEngine, settings: Settings, points: np.ndarray, options: SuggestOptions,
                up_axes: Sequence[UpAxis]) -> tuple[list[Frame], list[tuple[np.ndarray, SuggestOptions]]]:
    """The hypotheses of one partial and their scoring queries, for ``engine.suggest_batch`` or
    the micro-batcher: mixture-only when the engine has a familiarity bank."""
    frames = hypotheses_of(settings, points, up_axes)
    return frames, scoring_queries(frames, points, options, engine.familiarity is not None)


def choose_frame(frames: Sequence[Frame], results: Sequence[SuggestResult | ServiceError],
                 radius_prior: float, category_weight: float = 0.0) -> FrameFit:
    """The most familiar hypothesis (``most_familiar``) when the answers carry familiarity
    distances (a failed query counts as infinitely far), else the most likely (``best_frame``)."""
    distances = familiarity_of(results)
    if distances is None:
        return best_frame(frames, results)
    return most_familiar(frames, distances, radius_prior, category_probabilities_of(results), category_weight)


def chosen_frame(settings: Settings, frames: Sequence[Frame],
                 results: Sequence[SuggestResult | ServiceError]) -> FrameFit:
    """``choose_frame`` as the service chooses: with the settings' radius prior
    (``fit_frame_radius_prior``) and category weight (``fit_frame_category_weight``)."""
    return choose_frame(frames, results, settings.fit_frame_radius_prior, settings.fit_frame_category_weight)


def category_probabilities_of(results: Sequence[SuggestResult | ServiceError]) -> np.ndarray | None:
    """Each answer's category probability (``CATEGORY_FLOOR`` where its query failed); None when
    no answer carries one (the model has no category head).

    Shapes:
        returns (len(results),) float64.
    """
    found = [r.category_probability if isinstance(r, SuggestResult) else None for r in results]
    if all(p is None for p in found):
        return None
    return np.array([CATEGORY_FLOOR if p is None else p for p in found], dtype=np.float64)


def familiarity_of(results: Sequence[SuggestResult | ServiceError]) -> np.ndarray | None:
    """Each answer's familiarity distance (inf where its query failed); None when no answer
    carries one (the engine has no familiarity bank).

    Shapes:
        returns (len(results),) float64.
    """
    found = [r.familiarity if isinstance(r, SuggestResult) else None for r in results]
    if all(d is None for d in found):
        return None
    return np.array([np.inf if d is None else d for d in found], dtype=np.float64)


def fit_frame(engine: SuggestionEngine, settings: Settings, points: np.ndarray, options: SuggestOptions,
              up_axes: Sequence[UpAxis] = UP_AXES, snapshot: CatalogSnapshot | None = None) -> FrameFit:
    """Estimate the complete object's frame of a partial (see the module doc): one engine batch
    of its scoring queries on ``snapshot`` (None: the shipped catalog)."""
    frames, queries = fit_queries(engine, settings, points, options, up_axes)
    if not frames:
        return FrameFit(frame=options.frame, score=-np.inf, hypotheses=0)
    answers = engine.suggest_batch(queries, snapshot=snapshot)
    return chosen_frame(settings, frames, answers)


def _ratios(max_ratio: float, n: int) -> list[float]:
    """``n`` radius ratios from 1 to ``max_ratio``, evenly spaced in log scale."""
    return np.geomspace(1.0, max_ratio, n).tolist() if n > 1 else [1.0]

