"""`complementme evaluate-real`: the shipped model on shapes nobody here made.

The benchmark (`complementme evaluate`) queries the generator's own held-out shapes. This asks the
same engine about a collection from outside (for example Sweet Home 3D's furniture,
``training.data.sweethome3d``, ingested and preprocessed like any user collection) and, as the
reference, about as many of the catalog's held-out shapes of the same categories, with one
protocol for both:

- a query is a shape with one component taken away, ``n_points`` area-weighted samples of the rest
  (``training.data.sampling.draw_area_weighted``, the benchmark's and training's sampler), in the
  shape's canonical frame; up to ``queries_per_shape`` components per shape, drawn with the seed;
- *named*: the engine is told the shape's category folder (as the page with a category chosen);
  *unnamed*: it is told nothing and infers the category (as a request without one);
- the measures are label-free, because an outside collection's groups carry no part labels: the
  inferred category against the folder; the share of the unnamed top 5 in the folder's category;
  how many answers carry a warning that makes them guesses (``QueryWarning.guess``); and the
  Chamfer distance (mean nearest-neighbour distance both ways, unit radius) between each
  suggestion *as the service places it* (h's translation and scale) and the component taken away,
  for the top 1 and the best of the top 5;
- two references for the distances: five random parts of the category placed by h (chance), and
  the bound: the catalog part of the category nearest the removed component when put at its
  true centre at catalog size (what the catalog could give at best without fitting);
- frames: the query moved into a random caller frame (``frames_eval.random_caller_frame``: units
  of 100-1000 to the radius, y or z up, off centre) and sent without one, category named, as a
  mesh upload is: whether the frame the service fits (``service.suggest.frame_fit``) has the right
  up axis, and whether it is good (``frames_eval.good_frame``).

Categories are read from the folders (for outside shapes) and the catalog records (held out): to
measure only. The catalog's own shapes are never suggested for their own queries.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from service.artifacts.catalog import Catalog, split_shapes
from service.artifacts.layout import write_json_atomic
from service.artifacts.loading import load_served_artifacts
from service.errors import NotFoundError
from service.settings import Settings
from service.suggest.engine import SuggestionEngine, SuggestOptions
from service.suggest.frame_fit import fit_frame
from training.data.processed import ProcessedDataset
from training.data.sampling import draw_area_weighted
from training.evaluate.frames_eval import good_frame, random_caller_frame

SETS = ("outside", "held-out")
# The measures of one query, in the report's row order, with the rows' names.
MEASURES = {
    "category_right": "unnamed: inferred category is the folder's",
    "in_category": "unnamed: share of the top 5 in the folder's category",
    "guess_warned": "unnamed: answers warned as guesses",
    "named_top1": "named: Chamfer, top 1 as placed",
    "named_best5": "named: Chamfer, best of the top 5 as placed",
    "named_top1_centre": "named: Chamfer, top 1 at the true centre (h's scale)",
    "unnamed_best5": "unnamed: Chamfer, best of the top 5 as placed",
    "random_top1": "chance: Chamfer, a random part of the category placed by h",
    "random_best5": "chance: Chamfer, best of 5 random parts placed by h",
    "bound": "bound: Chamfer, the nearest catalog part at the true centre, catalog size",
    "frame_up": "frames: fitted up axis right, from a random caller frame",
    "frame_good": "frames: fitted frame good (up axis, radius within 25%, centre within 0.3)",
}


@dataclass(frozen=True)
class RealEvalSettings:
    data: Path                      # processed folder of the outside collection
    artifacts: Path = Path("exported")
    queries_per_shape: int = 4
    k: int = 5
    n_points: int = 2048
    part_points: int = 512          # samples per part in the distances
    seed: int = 0
    out: Path | None = None


@dataclass(frozen=True)
class Case:
    """One query: the rest of a shape, and the component taken away (canonical frame)."""

    category: str
    shape_id: str
    query: np.ndarray       # (n_points, 3) float32
    removed: np.ndarray     # (part_points, 3) float32, placed in the shape


def chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """Mean nearest-neighbour distance from a to b and from b to a, averaged.

    Shapes:
        a: (N, 3), b: (M, 3) -> float.
    """
    return 0.5 * float(cKDTree(b).query(a)[0].mean() + cKDTree(a).query(b)[0].mean())


def _cases(samples: np.ndarray, translations: np.ndarray, areas: np.ndarray,
           shapes: list[tuple[str, str, np.ndarray]], cfg: RealEvalSettings,
           rng: np.random.Generator) -> list[Case]:
    """Queries of shapes given as (category, shape id, component rows into ``samples``)."""
    cases = []
    for category, shape_id, rows in shapes:
        for gone in rng.permutation(rows)[:cfg.queries_per_shape]:
            rest = np.asarray([r for r in rows if r != gone], dtype=np.int64)
            query = draw_area_weighted(samples, translations, areas, rest, cfg.n_points, rng)
            removed = samples[gone][:cfg.part_points].astype(np.float32) + translations[gone]
            cases.append(Case(category, shape_id, query, removed))
    return cases


def outside_cases(ds: ProcessedDataset, cfg: RealEvalSettings, rng: np.random.Generator) -> list[Case]:
    """Queries of every multi-component shape of a processed collection, in its shapes' order."""
    shapes = [(str(meta["category"]), str(meta["shape_id"]), ds.components_of(s))
              for s, meta in enumerate(ds.shapes) if len(ds.components_of(s)) >= 2]
    return _cases(ds.points, ds.translation, ds.area, shapes, cfg, rng)


def held_out_cases(catalog: Catalog, per_category: dict[str, int], cfg: RealEvalSettings,
                   rng: np.random.Generator) -> list[Case]:
    """Queries of the catalog's held-out shapes: ``per_category[c]`` shapes of each category c."""
    rows_of = split_shapes(catalog, "test", fallback=False)  # no split: no reference, not the training shapes
    by_category: dict[str, list[str]] = {}
    for shape in sorted(rows_of):
        by_category.setdefault(catalog.records[rows_of[shape][0]]["category"], []).append(shape)
    shapes = []
    for category, count in sorted(per_category.items()):
        pool = by_category.get(category, [])
        for j in rng.permutation(len(pool))[:count]:
            shapes.append((category, pool[j], np.asarray(rows_of[pool[j]], dtype=np.int64)))
    areas = np.array([float(r["area"]) for r in catalog.records])
    return _cases(catalog.points, catalog.translations, areas, shapes, cfg, rng)


class _Measurer:
    """The measures of one query through the engine (see the module docstring)."""

    def __init__(self, engine: SuggestionEngine, settings: Settings, cfg: RealEvalSettings,
                 rng: np.random.Generator):
        self.engine, self.settings, self.cfg, self.rng = engine, settings, cfg, rng
        # The caller frames draw from their own stream: the other measures do not move with them.
        self.frame_rng = np.random.default_rng([cfg.seed, 1])
        self.catalog = engine.catalog

    def placed(self, row: int, translation: np.ndarray, scale: np.ndarray) -> np.ndarray:
        pts = self.catalog.part_points(row)[:self.cfg.part_points]
        return pts * np.asarray(scale, np.float32) + np.asarray(translation, np.float32)

    def own_shape(self, shape_id: str) -> int | None:
        """The catalog's code of the query's shape; None for a shape from outside."""
        try:
            return self.catalog.shape_code(shape_id)
        except NotFoundError:
            return None

    def pool(self, category: str, own: int | None) -> np.ndarray:
        """Catalog rows of the category, without the query's own shape."""
        cat = self.catalog
        rows = np.flatnonzero(cat.category_of == cat.categories.index(category))
        return rows if own is None else rows[cat.shape_of[rows] != own]

    def bound(self, case: Case, centre: np.ndarray, pool: np.ndarray) -> float:
        """The nearest pool part (catalog size) put at the removed component's box ``centre``."""
        tree = cKDTree(case.removed)
        best = np.inf
        for row in pool:
            pts = self.catalog.part_points(int(row))[:128] + centre
            a = float(tree.query(pts)[0].mean())
            if a / 2 >= best:  # the other half is >= 0: cannot beat the best
                continue
            best = min(best, 0.5 * (a + float(cKDTree(pts).query(case.removed)[0].mean())))
        return best

    def __call__(self, case: Case) -> dict[str, float]:
        cfg, eng = self.cfg, self.engine
        if case.category not in self.catalog.categories:
            raise ValueError(f"{case.shape_id}: category {case.category!r} is not in the catalog "
                             f"({', '.join(self.catalog.categories)})")
        own = self.own_shape(case.shape_id)
        exclude = () if own is None else (case.shape_id,)
        named = eng.suggest(case.query, SuggestOptions(k=cfg.k, categories=(case.category,),
                                                       exclude_shapes=exclude))
        unnamed = eng.suggest(case.query, SuggestOptions(k=cfg.k, exclude_shapes=exclude))
        if not named.suggestions or not unnamed.suggestions:
            raise ValueError(f"{case.shape_id}: the engine suggested nothing")
        centre = (case.removed.max(axis=0) + case.removed.min(axis=0)) / 2
        d_named = [chamfer(self.placed(s.part_index, s.translation, s.scale), case.removed)
                   for s in named.suggestions]
        d_unnamed = [chamfer(self.placed(s.part_index, s.translation, s.scale), case.removed)
                     for s in unnamed.suggestions]
        top = named.suggestions[0]
        pool = self.pool(case.category, own)
        drawn = self.rng.choice(pool, min(cfg.k, len(pool)), replace=False)
        picks = [self.catalog.part_ids[int(r)] for r in drawn]
        placed = eng.place(case.query, picks, refine_contact=False).placements
        d_random = [chamfer(self.placed(p.part_index, p.translation, p.scale), case.removed) for p in placed]
        inferred = unnamed.inferred_category
        caller = random_caller_frame(self.frame_rng)
        fit = fit_frame(eng, self.settings, caller.from_canonical(case.query.astype(np.float64)),
                        SuggestOptions(k=1, categories=(case.category,)))
        frame_up, frame_ok = good_frame(fit.frame, caller)
        return {
            "category_right": float(inferred is not None and inferred.category == case.category),
            "in_category": float(np.mean([s.category == case.category for s in unnamed.suggestions])),
            "guess_warned": float(any(w.guess for w in unnamed.warnings)),
            "named_top1": d_named[0],
            "named_best5": min(d_named),
            "named_top1_centre": chamfer(self.placed(top.part_index, centre, top.scale), case.removed),
            "unnamed_best5": min(d_unnamed),
            "random_top1": d_random[0],
            "random_best5": min(d_random),
            "bound": self.bound(case, centre, pool),
            "frame_up": float(frame_up),
            "frame_good": float(frame_ok),
        }


def summarise(rows: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Mean of each measure per category and over all queries ("all"), with the query counts."""
    out: dict[str, dict[str, float]] = {}
    for category in [*sorted({r["category"] for r in rows}), "all"]:
        mine = [r for r in rows if category in ("all", r["category"])]
        out[category] = {m: round(float(np.mean([r[m] for r in mine])), 3) for m in MEASURES}
        out[category]["queries"] = len(mine)
        out[category]["shapes"] = len({r["shape_id"] for r in mine})
    return out


def run_real_evaluation(cfg: RealEvalSettings) -> dict[str, Any]:
    """Both sets' queries through the engine on ``cfg.artifacts``; the report (and results.json)."""
    if not (cfg.data / "dataset.json").is_file():
        raise FileNotFoundError(f"{cfg.data} holds no processed collection (dataset.json): make one with "
                                "`complementme data ingest` and `complementme data preprocess`")
    settings = Settings().model_copy(update={"artifacts": cfg.artifacts})
    engine = SuggestionEngine(load_served_artifacts(settings), settings)
    rng = np.random.default_rng(cfg.seed)
    outside = outside_cases(ProcessedDataset.load(cfg.data), cfg, rng)
    shapes: dict[str, set[str]] = {}
    for case in outside:
        shapes.setdefault(case.category, set()).add(case.shape_id)
    held = held_out_cases(engine.catalog, {c: len(s) for c, s in shapes.items()}, cfg, rng)
    measure = _Measurer(engine, settings, cfg, rng)
    results = {}
    for name, cases in zip(SETS, (outside, held), strict=True):
        rows = [{"category": c.category, "shape_id": c.shape_id, **measure(c)} for c in cases]
        results[name] = summarise(rows) if rows else {}
    report = {"artifacts": str(cfg.artifacts), "model_version": engine.model_version, "data": str(cfg.data),
              "settings": {k: str(v) if isinstance(v, Path) else v for k, v in asdict(cfg).items()
                           if k not in ("out",)},
              "results": results}
    if cfg.out is not None:
        cfg.out.mkdir(parents=True, exist_ok=True)
        write_json_atomic(cfg.out / "results.json", report)
    return report


def markdown(report: dict[str, Any]) -> str:
    """One table per set: a row per measure, a column per category and "all"."""
    parts = []
    for name in SETS:
        res = report["results"][name]
        if not res:
            parts.append(f"**{name}**: no queries (the catalog has no held-out split)")
            continue
        cats = [*sorted(c for c in res if c != "all"), "all"]  # results.json keeps its keys sorted
        head = " | ".join(f"{c} ({res[c]['shapes']} shapes, {res[c]['queries']} queries)" if c != "all"
                          else f"all ({res[c]['queries']})" for c in cats)
        lines = [f"**{name}**", "", f"| Measure | {head} |", "|---|" + "---|" * len(cats)]
        for m, title in MEASURES.items():
            lines.append(f"| {title} | " + " | ".join(f"{res[c][m]:.3f}" for c in cats) + " |")
        parts.append("\n".join(lines))
    return "\n\n".join(parts)
