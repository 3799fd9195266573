"""Per-query evaluation of every metric, and aggregation into per-category tables.

Each ``evaluate_*`` function walks a list of queries, asks one method for its ranking (always
passed through ``protocol.finalize_ranking``) and returns one plain dict per query, so the JSON
output can keep them and the tables are simple means over them.

Aggregation: a category's value is the mean over its queries where the metric is defined (for
example, style AP is undefined when the shape has no style annotation); the "mean" column is the
mean of the category values, as in the paper's tables (each category weighs the same).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from tqdm import tqdm

from service.artifacts.catalog import Catalog
from service.geometry.boxes import box_iou
from service.suggest.engine import Placement
from training.evaluate.baselines import Method, rank_by_scores
from training.evaluate.contact import Mesh, contact
from training.evaluate.metrics import (
    average_precision_at_k,
    bbox_centred,
    first_hit_rank,
    hausdorff_distance,
    nanmean,
    nanmedian,
    percentile_rank,
    placement_error,
    recall_at_k,
    stratified_interval,
    style_set,
    styles_match,
)
from training.evaluate.ours import EngineMethod
from training.evaluate.protocol import (
    PlacementQuery,
    Query,
    ShapeIndex,
    candidate_pool,
    finalize_ranking,
    relevant_in_pool,
)

log = logging.getLogger(__name__)


@dataclass
class RetrievalSettings:
    """How rankings are cut and compared."""

    top_k: int = 5                      # k of mAP@k and of the mean Hausdorff distance (paper: 5)
    recall_ks: tuple[int, ...] = (1, 10)
    pool_scope: str = "category"        # "category": other shapes of the query's category; "all"
    collapse_duplicates: bool = True    # one part per near-duplicate group, as the service shows


def removed_part_points(index: ShapeIndex, rows: np.ndarray) -> np.ndarray:
    """The removed labelled part as one point set: its components in place, then centred.

    Shapes:
        rows (r,) -> (r * S, 3) float64, bounding-box centred.
    """
    cat = index.catalog
    pts = np.concatenate([index.samples[r].astype(np.float64) + cat.translations[r] for r in rows])
    return bbox_centred(pts)


def top_hausdorff(index: ShapeIndex, removed: np.ndarray, rows: np.ndarray,
                  scales: np.ndarray | None = None) -> float:
    """Table 2's measure: the mean symmetric Hausdorff distance between the removed labelled part
    and each of the parts ``rows``, both centred at their bounding-box centres; each part scaled
    per axis about its centre by ``scales`` (None: its catalog size). NaN for no rows.

    Shapes:
        removed (r,), rows (k,) catalog rows; scales (k, 3) or None.
    """
    if len(rows) == 0:
        return math.nan
    removed_pts = removed_part_points(index, removed)
    sc = np.ones((len(rows), 3)) if scales is None else np.asarray(scales, np.float64).reshape(-1, 3)
    # index.samples are bounding-box centred (as the catalog's meshes are): scaling about the
    # centre is a product.
    return float(np.mean([hausdorff_distance(removed_pts, index.samples[r].astype(np.float64) * s)
                          for r, s in zip(np.asarray(rows).tolist(), sc, strict=True)]))


def _label_pool(index: ShapeIndex, query: Query) -> np.ndarray:
    """The query's pool rows (other shapes of its category) that hold the removed label: what a
    method that always found the label could choose from (labels read to measure only)."""
    pool = candidate_pool(index, query.shape_id, query.category)
    return np.array([r for r in pool.tolist() if index.labels[r] == query.label], np.int64)


def hausdorff_bound(index: ShapeIndex, query: Query, k: int) -> float:
    """What Table 2 could reach with the right label: the mean Hausdorff distance (as
    ``top_hausdorff`` measures it) of the ``k`` pool parts of the removed label nearest to the
    removed part, one per near-duplicate group. NaN when the pool holds no part of that label.

    Shapes:
        query.removed (r,) catalog rows.
    """
    cat = index.catalog
    rows = _label_pool(index, query)
    if len(rows) == 0:
        return math.nan
    removed_pts = removed_part_points(index, query.removed)
    nearest: dict[int, float] = {}   # near-duplicate group -> its member nearest the removed part
    for r in rows.tolist():
        d = hausdorff_distance(removed_pts, index.samples[r])
        g = int(cat.group[r])
        nearest[g] = min(d, nearest.get(g, math.inf))
    return float(np.mean(np.sort(list(nearest.values()))[:k]))


def iou_bound(index: ShapeIndex, query: Query, true_lo: np.ndarray, true_hi: np.ndarray) -> float:
    """What the placed-box IoU could reach unfitted with the right label and the right centre: the
    best IoU with the removed part's box of any pool part of the removed label, its catalog-size
    box centred on the true one. NaN when the pool holds no part of that label.

    Shapes:
        true_lo, true_hi (3,): the removed part's box.
    """
    rows = _label_pool(index, query)
    if len(rows) == 0:
        return math.nan
    cat = index.catalog
    centre = (true_lo + true_hi) / 2
    half = (cat.bbox_max[rows] - cat.bbox_min[rows]).astype(np.float64) / 2
    return float(np.nanmax(box_iou(true_lo, true_hi, centre - half, centre + half)))


def _target_hit(catalog: Catalog, rows: np.ndarray, removed: np.ndarray, collapse: bool) -> np.ndarray:
    """Whether each row is "the exact removed component": one of the removed components, or
    (with duplicate collapse) a near-duplicate of one, which the service shows in its place."""
    hit = np.isin(rows, removed)
    if collapse:
        hit |= np.isin(catalog.group[rows], catalog.group[removed])
    return hit


def functional_hits(index: ShapeIndex, q: Query, rows: np.ndarray) -> np.ndarray:
    """Which of ``rows`` carry the removed part's label (labels read to measure only).

    Shapes:
        rows (R,) catalog rows -> (R,) bool.
    """
    labels = index.labels
    return np.array([labels[r] == q.label for r in np.asarray(rows).tolist()], dtype=bool)


def functional_scores(index: ShapeIndex, q: Query, pool: np.ndarray, top: np.ndarray,
                      group: np.ndarray | None, k: int, top_hits: np.ndarray | None = None
                      ) -> dict[str, float]:
    """Table 1's functional AP@k of an all-but-one query's final top ``k`` (of ``pool``), and the
    share of it from the query's category (with the pool "all" the method must find the category
    itself, as the service infers it). ``top_hits``: ``functional_hits`` of ``top`` when the caller
    has them already."""
    cat = index.catalog
    n_func = relevant_in_pool(functional_hits(index, q, pool), pool, group)
    hits = functional_hits(index, q, top) if top_hits is None else top_hits
    return {"functional_ap": average_precision_at_k(hits, n_func, k),
            "in_category": (float(np.mean(cat.category_of[top] == cat.category_codes([q.category])[0]))
                            if len(top) else math.nan)}


def evaluate_retrieval(method: Method, queries: list[Query], index: ShapeIndex,
                       settings: RetrievalSettings, progress: bool = False) -> list[dict[str, Any]]:
    """Functional AP, Hausdorff, style AP and exact-component recall of one method, per query."""
    cat = index.catalog
    group = cat.group if settings.collapse_duplicates else None
    k = settings.top_k
    out: list[dict[str, Any]] = []
    style_cache: dict[frozenset[str], np.ndarray] = {}
    desc = f"{method.name} {queries[0].setting if queries else ''}"
    for q in tqdm(queries, desc=desc, disable=not progress, leave=False):
        pool = candidate_pool(index, q.shape_id, q.category, settings.pool_scope)
        top = finalize_ranking(method.rank(q, pool, k), pool, group, k)
        own = cat.shape_code(q.shape_id)
        if np.any(cat.shape_of[top] == own):  # finalize_ranking makes this impossible; say so loudly
            raise AssertionError(f"{method.name} retrieved a part of the query's own shape for {q.qid}")
        rec: dict[str, Any] = {"qid": q.qid, "category": q.category, "shape_id": q.shape_id,
                               "top": [cat.part_ids[r] for r in top.tolist()]}
        # Style (both settings): a hit is a part from a shape of an overlapping fine-grained class.
        key = style_set(q.style)
        if key not in style_cache:  # a few distinct styles: match every shape once per style
            style_cache[key] = np.array([styles_match(index.style[sid], q.style) for sid in cat.shape_ids],
                                        dtype=bool)
        same_style = style_cache[key]
        pool_style, top_style = same_style[cat.shape_of[pool]], same_style[cat.shape_of[top]]
        rec["style_ap"] = (average_precision_at_k(top_style, relevant_in_pool(pool_style, pool, group), k)
                           if pool_style.size else math.nan)
        if q.setting == "all_but_one":
            top_func = functional_hits(index, q, top)
            rec.update(functional_scores(index, q, pool, top, group, k, top_hits=top_func))
            rec["hausdorff"] = top_hausdorff(index, q.removed, top)
            # The same where the removed label is one component: a label of several (a pair of
            # engines, a set of legs) is one point set, farther from any single catalog part.
            rec["hausdorff_one_component"] = rec["hausdorff"] if len(q.removed) == 1 else None
            # The same over the top parts of the removed label only: how close the right parts the
            # method picks are (against ``hausdorff_bound``, the closest the pool holds).
            rec["hausdorff_right_label"] = (top_hausdorff(index, q.removed, top[top_func]) if top_func.any()
                                            else None)
            rec.update(_exact_recall(method, q, pool, index, settings))
        out.append(rec)
    return out


def _exact_recall(method: Method, q: Query, pool: np.ndarray, index: ShapeIndex,
                  settings: RetrievalSettings) -> dict[str, Any]:
    """Recall@k and percentile rank of the removed component(s), put back into the pool."""
    cat = index.catalog
    names = [f"recall@{k}" for k in settings.recall_ks]
    if not method.per_part_scores:
        return {**dict.fromkeys(names), "percentile": None}
    group = cat.group if settings.collapse_duplicates else None
    pool_plus = np.union1d(pool, q.removed)
    kmax = max(settings.recall_ks)
    ranked = finalize_ranking(method.rank(q, pool_plus, kmax), pool_plus, group, kmax)
    rank = first_hit_rank(_target_hit(cat, ranked, q.removed, settings.collapse_duplicates).tolist())
    rec: dict[str, Any] = {n: recall_at_k(rank, k) for n, k in zip(names, settings.recall_ks, strict=True)}
    full = finalize_ranking(rank_by_scores(method.scores(q, pool_plus), pool_plus), pool_plus, group, None)
    full_rank = first_hit_rank(_target_hit(cat, full, q.removed, settings.collapse_duplicates).tolist())
    rec["percentile"] = percentile_rank(full_rank, len(full)) if full_rank is not None else math.nan
    return rec


def evaluate_placement(ours: EngineMethod, queries: list[PlacementQuery],
                       progress: bool = False) -> list[dict[str, Any]]:
    """Placement error of h for the true missing component, per query (Table 4), without and with
    the service's contact refinement (``error``, ``error_refined``)."""
    out = []
    for q in tqdm(queries, desc="placement", disable=not progress, leave=False):
        pred = ours.place(q.points, [q.target])[0][0]
        refined = ours.refine(q.target, pred, q.present)
        out.append({"qid": q.qid, "category": q.category, "shape_id": q.shape_id, "split": q.split,
                    "part_id": ours.catalog.part_ids[q.target],
                    "error": placement_error(pred, q.true_translation),
                    "error_refined": placement_error(refined, q.true_translation),
                    "predicted": [round(float(v), 5) for v in pred],
                    "refined": [round(float(v), 5) for v in refined]})
    return out


@dataclass
class ContactSettings:
    tolerance: float = 0.02   # fraction of the shape radius (the unit) beyond which a gap or depth counts
    samples: int = 256        # surface samples per part used for the test (the catalog's first ones)
    candidates: int = 32      # samples per side measured exactly (see contact.contact)


def _placed_mesh(index: ShapeIndex, row: int, translation: np.ndarray, samples: int,
                 scale: np.ndarray | None = None) -> Mesh:
    """Catalog part ``row`` scaled per axis about its centre (``scale``; None: its catalog size,
    as the service fits a part) and moved to ``translation``."""
    v, f = index.catalog.mesh(row)
    t = np.asarray(translation, dtype=np.float64).reshape(1, 3)
    s = np.ones((1, 3)) if scale is None else np.asarray(scale, dtype=np.float64).reshape(1, 3)
    pts = index.samples[row][:samples].astype(np.float64)
    return Mesh(v.astype(np.float64) * s + t, f.astype(np.int64), pts * s + t)


def _union(meshes: list[Mesh]) -> Mesh:
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return Mesh(np.concatenate([m.vertices for m in meshes]),
                np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)]),
                np.concatenate([m.samples for m in meshes]))


def evaluate_plausibility(ours: EngineMethod, index: ShapeIndex, queries: list[Query],
                          retrieval: list[dict[str, Any]],
                          placement: list[dict[str, Any]], placement_queries: list[PlacementQuery],
                          settings: ContactSettings,
                          progress: bool = False) -> dict[str, list[dict[str, Any]]]:
    """Gap and penetration of placed parts against the query's assembly (see ``contact``).

    Cases per query:
      * ``top1``: Ours' top-1 suggestion (all-but-one queries), placed by h at the size the
        service answers it with (h's fitted scale; ``EngineMethod.place``);
      * ``true_h``: the true missing component placed by h (the test-split placement queries),
        also compared with the same component at its true place: ``worse_than_truth`` when h's
        gap or depth exceeds the true placement's by more than the tolerance (the data's own
        overlaps, e.g. legs sunk into a seat, do not count against h);
      * ``top1_refined``, ``true_h_refined``: the same placements after the service's contact
        refinement against the present parts (``EngineMethod.refine``, as ``POST /assemble``);
      * ``true_gt``: the removed labelled part at its true place: the data's own rate, a floor.
    """
    cat = ours.catalog
    by_qid = {r["qid"]: r for r in retrieval}
    cases = ("top1", "top1_refined", "true_h", "true_h_refined", "true_gt")
    out: dict[str, list[dict[str, Any]]] = {case: [] for case in cases}

    def assembly(rows: np.ndarray) -> list[Mesh]:
        return [_placed_mesh(index, int(r), cat.translations[r], settings.samples) for r in rows.tolist()]

    def record(case: str, q: Any, part: Mesh, rows: np.ndarray, truth: Mesh | None = None) -> None:
        asm = assembly(rows)
        c = contact(part, asm, settings.candidates)
        rec = {"qid": q.qid, "category": q.category, "gap": round(c.gap, 6), "depth": round(c.depth, 6),
               "floating": c.floating(settings.tolerance),
               "interpenetrating": c.interpenetrating(settings.tolerance)}
        if truth is not None:
            t = contact(truth, asm, settings.candidates)
            tol = settings.tolerance
            rec.update({"true_gap": round(t.gap, 6), "true_depth": round(t.depth, 6),
                        "worse_than_truth": c.gap > t.gap + tol or c.depth > t.depth + tol})
        out[case].append(rec)

    for q in tqdm(queries, desc="plausibility", disable=not progress, leave=False):
        top = by_qid[q.qid]["top"]
        if top:
            row = cat.lookup(top[0])
            where, scales = ours.place(q.points, [row])
            t, scale = where[0], scales[0]
            record("top1", q, _placed_mesh(index, row, t, settings.samples, scale), q.present)
            t = ours.refine(row, t, q.present, scale)
            record("top1_refined", q, _placed_mesh(index, row, t, settings.samples, scale), q.present)
        record("true_gt", q, _union(assembly(q.removed)), q.present)
    pred = {r["qid"]: r for r in placement}
    for pq in placement_queries:
        if pq.split == "test" and pq.qid in pred:
            truth = _placed_mesh(index, pq.target, pq.true_translation, settings.samples)
            for case, key in (("true_h", "predicted"), ("true_h_refined", "refined")):
                placed = _placed_mesh(index, pq.target, np.asarray(pred[pq.qid][key]), settings.samples)
                record(case, pq, placed, pq.present, truth)
    return out


def category_values(per_query: list[dict[str, Any]], key: str, categories: list[str]) -> dict[str, list[Any]]:
    """The defined values of one per-query metric, per category (None and NaN left out)."""
    out: dict[str, list[Any]] = {}
    for c in categories:
        vals = [r[key] for r in per_query if r["category"] == c and r.get(key) is not None]
        out[c] = [v for v in vals if not (isinstance(v, float) and math.isnan(v))]
    return out


def table(per_query: list[dict[str, Any]], key: str, categories: list[str]) -> dict[str, Any]:
    """Per-category means of one per-query metric, their mean ("mean"), and the query counts ("n")."""
    values = category_values(per_query, key, categories)
    row: dict[str, Any] = {c: nanmean(values[c]) for c in categories}
    row["mean"] = nanmean(row[c] for c in categories)
    row["n"] = {c: len(values[c]) for c in categories}
    return row


def interval(per_query: list[dict[str, Any]], key: str, categories: list[str], seed: int) -> list[float]:
    """95% bootstrap interval of ``table``'s "mean" (queries resampled within their category)."""
    values = category_values(per_query, key, categories)
    return list(stratified_interval([np.asarray(values[c], dtype=np.float64) for c in categories], seed))


def median_table(per_query: list[dict[str, Any]], key: str, categories: list[str]) -> dict[str, Any]:
    """Like ``table`` with medians per category (the "mean" column is still the mean of them)."""
    row: dict[str, Any] = {}
    counts: dict[str, int] = {}
    for c in categories:
        vals = [r[key] for r in per_query if r["category"] == c and r.get(key) is not None]
        row[c] = nanmedian(vals)
        counts[c] = len([v for v in vals if not math.isnan(v)])
    row["mean"] = nanmean(row[c] for c in categories)
    row["n"] = counts
    return row


def plausibility_table(records: list[dict[str, Any]], categories: list[str]) -> dict[str, Any]:
    """Per category: share floating, share interpenetrating, median gap and depth, count, and
    (when the records compare with the truth) the share placed worse than the truth."""
    out: dict[str, Any] = {}
    for c in [*categories, "all"]:
        rs = [r for r in records if c == "all" or r["category"] == c]
        n = len(rs)
        out[c] = {
            "n": n,
            "floating": float(np.mean([r["floating"] for r in rs])) if n else math.nan,
            "interpenetrating": float(np.mean([r["interpenetrating"] for r in rs])) if n else math.nan,
            "median_gap": nanmedian(r["gap"] for r in rs),
            "median_depth": nanmedian(r["depth"] for r in rs),
            "worse_than_truth": (float(np.mean([r["worse_than_truth"] for r in rs]))
                                 if n and all("worse_than_truth" in r for r in rs) else None),
        }
    return out


def evaluate_coverage(method: Method, queries: list[Query], index: ShapeIndex, settings: RetrievalSettings,
                      k: int = 10, min_missing: int = 2, progress: bool = False) -> list[dict[str, Any]]:
    """What a designer sees first for "one part, several missing": coverage of the missing labels.

    For each ``single`` query (one labelled part present) whose shape lacks at least
    ``min_missing`` labels: the share of those labels among the labels of the top ``k``, the
    number of distinct labels there, and (for a method with a mixture) how many of g's modes
    weigh at least 0.05. The pool is the settings' (the query's category, or all).
    """
    cat = index.catalog
    group = cat.group if settings.collapse_duplicates else None
    out: list[dict[str, Any]] = []
    mixture = getattr(method, "mixture", None)
    for q in tqdm(queries, desc=f"{method.name} coverage", disable=not progress, leave=False):
        missing = {index.labels[r] for r in q.removed.tolist()} - {None, q.label}
        if len(missing) < min_missing:
            continue
        pool = candidate_pool(index, q.shape_id, q.category, settings.pool_scope)
        top = finalize_ranking(method.rank(q, pool, k), pool, group, k)
        shown = [index.labels[r] for r in top.tolist()]
        rec: dict[str, Any] = {"qid": q.qid, "category": q.category, "shape_id": q.shape_id,
                               "top": [cat.part_ids[r] for r in top.tolist()],
                               "coverage": len(missing & set(shown)) / len(missing),
                               "distinct_labels": float(len({lab for lab in shown if lab is not None}))}
        if mixture is not None:
            weights = mixture(q)[0]
            rec["live_modes"] = float(np.sum(np.asarray(weights) >= 0.05))
        out.append(rec)
    return out


def _like_diagnostics(placed: Placement, true_lo: np.ndarray, true_hi: np.ndarray, source: np.ndarray
                      ) -> dict[str, float]:
    """Where a like-with-like placed box loses IoU (see ``evaluate_size_fit``).

    Shapes:
        true_lo, true_hi, source: (3,) in the shape frame.
    """
    lo, hi = np.asarray(placed.bbox_min, np.float64), np.asarray(placed.bbox_max, np.float64)
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    true_centre, true_half = (true_lo + true_hi) / 2, (true_hi - true_lo) / 2

    def iou(c: np.ndarray, h: np.ndarray) -> float:
        return float(box_iou(c - h, c + h, true_lo, true_hi)[0])

    return {"iou_like_true_centre": iou(true_centre, half), "iou_like_true_extents": iou(centre, true_half),
            "centre_error_like": float(np.linalg.norm(centre - true_centre)),
            "centre_to_source_like": float(np.linalg.norm(centre - source))}


def evaluate_size_fit(ours: Any, queries: list[Query], per_query: list[dict[str, Any]], index: ShapeIndex,
                      progress: bool = False) -> list[dict[str, Any]]:
    """Size fitting of the top suggestion of each all-but-one query, on and off.

    The top-ranked part is placed next to the query by the engine (``place``, contact
    refinement off) with and without the fitting scale, and as ``/place`` answers by default
    (fitted, then contact-refined: ``iou_refined``); its placed box is compared with the
    removed part's true box (the union of its components' boxes at their catalog translations):
    box IoU, and the scale error ``mean |log(placed extents / true extents)|`` over the axes.
    ``iou_like`` repeats the IoU with fitting on only where the two boxes are of one kind: the
    top part has the removed label and that label is one component (a pair of engines or a set of
    legs is one labelled part whose box spans several components, which no single part can fill).
    On those queries, where the IoU is lost: ``iou_like_true_centre`` keeps the fitted extents at
    the true box's centre, ``iou_like_true_extents`` the true extents at the placed centre;
    ``centre_error_like`` is the placed centre's distance to the true one and
    ``centre_to_source_like`` its distance to the part's centre in its own shape (how much of
    where h puts a part is where that part came from). ``hausdorff_on`` is Table 2's distance for
    the query's top parts (all of them, not only the first) at the size the service answers each
    with (h's fitting scale), ``hausdorff_off`` the same at catalog size (Table 2's own figure),
    ``hausdorff_bound`` what the same number of parts of the removed label could reach
    (the function ``hausdorff_bound``), ``iou_bound`` the best box of such a part at the true
    centre and catalog size (``iou_bound``).
    """
    cat = index.catalog
    retrieved = {r["qid"]: r for r in per_query}   # Ours' retrieval records: the top parts, Table 2
    out: list[dict[str, Any]] = []
    for q in tqdm(queries, desc="size fit", disable=not progress, leave=False):
        top = retrieved[q.qid]["top"] if q.qid in retrieved else []
        if not top:
            continue
        rows = q.removed
        true_lo = np.min(cat.translations[rows] + cat.bbox_min[rows], axis=0).astype(np.float64)
        true_hi = np.max(cat.translations[rows] + cat.bbox_max[rows], axis=0).astype(np.float64)
        rec: dict[str, Any] = {"qid": q.qid, "category": q.category, "part_id": top[0]}
        like = len(rows) == 1 and index.labels[cat.lookup(top[0])] == index.labels[rows[0]]
        true_ext = np.maximum(true_hi - true_lo, 1e-6)
        placed: dict[str, Placement] = {}
        for name, fit in (("on", True), ("off", False)):
            p = placed[name] = ours.engine.place(q.points, [top[0]], refine_contact=False,
                                                 fit_scale=fit).placements[0]
            rec[f"iou_{name}"] = float(box_iou(p.bbox_min, p.bbox_max, true_lo, true_hi)[0])
            ext = np.maximum(np.asarray(p.bbox_max) - np.asarray(p.bbox_min), 1e-6)
            rec[f"scale_error_{name}"] = float(np.mean(np.abs(np.log(ext / true_ext))))
        # As /place answers by default: fitted, then refined into contact with the query's points.
        served = ours.engine.place(q.points, [top[0]]).placements[0]
        rec["iou_refined"] = float(box_iou(served.bbox_min, served.bbox_max, true_lo, true_hi)[0])
        rec["iou_like"] = rec["iou_on"] if like else None
        # Table 2's measure over the same top parts at the size the service answers them with.
        top_rows = np.array([cat.lookup(pid) for pid in top], np.int64)
        fitted = ours.engine.place(q.points, list(top), refine_contact=False).placements
        rec["hausdorff_on"] = top_hausdorff(index, rows, top_rows, np.stack([f.scale for f in fitted]))
        rec["hausdorff_off"] = retrieved[q.qid]["hausdorff"]   # measured by the retrieval already
        rec["hausdorff_bound"] = hausdorff_bound(index, q, len(top))
        rec["iou_bound"] = iou_bound(index, q, true_lo, true_hi)
        if like:
            rec.update(_like_diagnostics(placed["on"], true_lo, true_hi,
                                         cat.translations[cat.lookup(top[0])].astype(np.float64)))
        out.append(rec)
    return out
