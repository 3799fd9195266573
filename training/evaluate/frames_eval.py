"""`complementme evaluate-frames`: how often frame fitting finds a partial upload's frame.

Held-out shapes of the catalog lose parts (one random part; or every part of one kind, the kind
read from the labels, which this measurement alone reads), are put in a random caller frame (up
axis y or z, radius 100-1000 units, centre anywhere within 2000 of the origin), and are fitted
(``service.suggest.frame_fit``), every hypothesis scored by both measures; each rule then picks
from the same scores:

- ``likelihood``: the best suggestion's mixture log-likelihood (no familiarity bank);
- ``familiarity``: the familiarity distance alone (radius prior 0);
- ``radius prior``: the familiarity distance plus the settings' radius prior (the rule shipped
  before the category term);
- ``shipped``: that, plus the settings' category weight times the log of the category head's
  probability of the query's most probable category (what the service does; no category is
  named here).

A fit is *good* when its up axis is right, its radius within 25% and its centre within 0.3 of the
true radius. The rates go to ``results.json`` and are printed as a Markdown table.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from service.artifacts.catalog import Catalog, partial_assemblies, split_shapes
from service.artifacts.loading import load_served_artifacts
from service.geometry.frames import Frame
from service.settings import Settings
from service.suggest.engine import SuggestionEngine, SuggestOptions
from service.suggest.frame_fit import (
    UP_AXES,
    best_frame,
    chosen_frame,
    familiarity_of,
    hypotheses_of,
    most_familiar,
    scoring_queries,
)

RULES = ("likelihood", "familiarity", "radius prior", "shipped")
SETS = ("one part missing", "one kind missing")


@dataclass(frozen=True)
class FrameEvalSettings:
    artifacts: Path
    shapes: int = 80              # per set
    seed: int = 0
    split: str = "test"
    out: Path | None = None


def kind_missing(catalog: Catalog, count: int, n_points: int, seed: int, split: str) -> list[np.ndarray]:
    """Shapes of one split without every part of one random label (labels read to measure only).

    Shapes:
        returns up to ``count`` arrays of (n_points, 3) float32, canonical frame.
    """
    rng = np.random.default_rng(seed)
    rows_of = split_shapes(catalog, split)
    shapes = sorted(rows_of)
    out: list[np.ndarray] = []
    for j in rng.permutation(len(shapes)):
        rows = rows_of[shapes[j]]
        labels = sorted({catalog.records[i]["label"] for i in rows})
        if len(labels) < 2:
            continue
        gone = labels[int(rng.integers(len(labels)))]
        pts = np.concatenate([catalog.part_points(i) + catalog.translations[i]
                              for i in rows if catalog.records[i]["label"] != gone])
        out.append(pts[rng.choice(len(pts), n_points)].astype(np.float32))
        if len(out) >= count:
            break
    return out


def random_caller_frame(rng: np.random.Generator) -> Frame:
    """A caller's frame as the measurements draw it: up axis y or z, radius 100-1000 units,
    centre anywhere within 2000 of the origin."""
    return Frame(center=rng.uniform(-2000, 2000, 3), radius=float(rng.uniform(100, 1000)),
                 up_axis=str(rng.choice(UP_AXES)))  # type: ignore[arg-type]


def good_frame(fit: Frame, true: Frame) -> tuple[bool, bool]:
    """(up axis right, good frame) of one fit: a good frame has the right up axis, its radius
    within 25% and its centre within 0.3 of the true radius."""
    up = fit.up_axis == true.up_axis
    near = (abs(np.log(fit.radius / true.radius)) < np.log(1.25)
            and float(np.linalg.norm(np.asarray(fit.center) - np.asarray(true.center))) < 0.3 * true.radius)
    return up, up and near


def run_frame_evaluation(cfg: FrameEvalSettings) -> dict[str, Any]:
    """Fit every partial of both sets under every rule; the rates per set and rule."""
    settings = Settings().model_copy(update={"artifacts": cfg.artifacts})
    engine = SuggestionEngine(load_served_artifacts(settings), settings)
    catalog = engine.artifacts.catalog
    sets = {SETS[0]: partial_assemblies(catalog, cfg.shapes, 2000, seed=cfg.seed + 3, split=cfg.split),
            SETS[1]: kind_missing(catalog, cfg.shapes, 2000, cfg.seed + 4, cfg.split)}
    rng = np.random.default_rng(cfg.seed)
    results: dict[str, Any] = {}
    for name, clouds in sets.items():
        counts = {rule: np.zeros(2) for rule in RULES}
        for cloud in clouds:
            true = random_caller_frame(rng)
            points = true.from_canonical(cloud.astype(np.float64))
            frames = hypotheses_of(settings, points, UP_AXES)
            # The k = 1 answers carry both scores: the best suggestion's likelihood and g's familiarity.
            answers = engine.suggest_batch(scoring_queries(frames, points, SuggestOptions(), False))
            distances = familiarity_of(answers)
            if distances is None:
                raise ValueError(f"{cfg.artifacts} has no familiarity bank: run `complementme familiarity`")
            picks = {"likelihood": best_frame(frames, answers),
                     "familiarity": most_familiar(frames, distances, 0.0),
                     "radius prior": most_familiar(frames, distances, settings.fit_frame_radius_prior),
                     "shipped": chosen_frame(settings, frames, answers)}
            for rule, fit in picks.items():
                counts[rule] += good_frame(fit.frame, true)
        results[name] = {rule: {"up_axis_right": round(float(c[0]) / max(len(clouds), 1), 3),
                                "good": round(float(c[1]) / max(len(clouds), 1), 3)}
                         for rule, c in counts.items()}
        results[name]["shapes"] = len(clouds)
    report = {"artifacts": str(cfg.artifacts), "model_version": engine.model_version, "split": cfg.split,
              "seed": cfg.seed, "radius_prior": settings.fit_frame_radius_prior,
              "category_weight": settings.fit_frame_category_weight,
              "hypotheses": (f"{settings.fit_frame_ratios} radii x {settings.fit_frame_shifts} shifts x "
                             f"{len(UP_AXES)} up axes"),
              "results": results}
    if cfg.out is not None:
        cfg.out.mkdir(parents=True, exist_ok=True)
        (cfg.out / "results.json").write_text(json.dumps(report, indent=1) + "\n")
    return report


def markdown(report: dict[str, Any]) -> str:
    """The rates as a table: a row per rule, "up axis / good" per set."""
    lines = ["| Rule | " + " | ".join(f"{s}: up axis / good" for s in SETS) + " |",
             "|---|" + "---|" * len(SETS)]
    for rule in RULES:
        rows = [report["results"][s][rule] for s in SETS]
        cells = [f"{r['up_axis_right']:.2f} / {r['good']:.2f}" for r in rows]
        lines.append(f"| {rule} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
