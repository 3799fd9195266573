"""Query generation and candidate filtering of the benchmark (paper Section 6.2).

A query is built from a held-out shape of the shipped catalog (``split == "test"``):

* ``all_but_one``: one *labelled part* is removed (all components of the shape that share one
  semantic label, the paper's "labelled part") and the query is the rest (Tables 1, 2, 3 top).
* ``single``: only one labelled part is present (Table 3, bottom).
* placement queries remove one *component* and keep every other component of the shape
  (Table 4), on the train and the test split.

Query points are ``n_points`` area-weighted samples of the present components, in the shape's
frame (dense surface samples of each part's shipped mesh, moved by the part's translation), drawn
the way the training sampler draws X.

Candidates ("the pool") are catalog parts from *other* shapes only, by default of the query's
category: a query can never retrieve a part of its own shape. Rankings are filtered to the
pool and near-duplicate parts are collapsed to their best-ranked member (as the service does),
before any metric reads them.

Queries are drawn without replacement from every eligible (shape, labelled part) pair of a
category, shuffled with a generator seeded by (seed, category, setting): re-running gives the
same queries, and a category with fewer pairs than requested uses all of them.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.artifacts.catalog import Catalog
from service.geometry.mesh import MeshError, resample_points, sample_surface
from training.data.sampling import draw_area_weighted
from training.evaluate.descriptors import descriptors

SETTINGS = ("all_but_one", "single")
POOL_SCOPES = ("category", "all")
_SETTING_CODE = {"all_but_one": 1, "single": 2, "placement:train": 3, "placement:test": 4, "assembly": 5}


def stable_code(text: str) -> int:
    """A platform-independent integer for a string, to seed per-category generators."""
    return zlib.crc32(text.encode("utf-8"))


@dataclass
class Query:
    """One retrieval query: a partial shape and the part(s) it lacks.

    Shapes:
        present, removed: (r,) int64 catalog rows.   points: (N, 3) float32, shape frame.
    """

    qid: str
    category: str
    shape_id: str
    setting: str
    present: np.ndarray
    removed: np.ndarray
    # Label of the removed part (all_but_one) or of the one present part (single).
    label: str | None
    style: Any
    points: np.ndarray


@dataclass
class PlacementQuery:
    """One placement query: a shape without one component, and that component.

    Shapes:
        present: (r,) int64 catalog rows.   points: (N, 3) float32.   true_translation: (3,).
    """

    qid: str
    category: str
    shape_id: str
    split: str
    target: int
    present: np.ndarray
    points: np.ndarray
    true_translation: np.ndarray


def dense_samples(catalog: Catalog, n: int, seed: int) -> np.ndarray:
    """``n`` surface samples of every catalog part from its shipped mesh (centred, seeded per part).

    The catalog stores only a few points per part (a preview); its meshes ship too, and the
    benchmark needs denser samples for queries, Hausdorff distances and contact tests. A part
    whose mesh has no area keeps its stored points, resampled to ``n``.

    Shapes:
        returns (P, n, 3) float32.
    """
    out = np.empty((len(catalog), n, 3), np.float32)
    for i in range(len(catalog)):
        v, f = catalog.mesh(i)
        try:
            out[i] = sample_surface(v, f, n, seed=int(np.random.SeedSequence([seed, i]).generate_state(1)[0]))
        except MeshError:
            out[i] = resample_points(catalog.part_points(i), n, seed)
    return out


class ShapeIndex:
    """Catalog rows grouped by source shape, with each shape's category, split, style and labels,
    and dense surface samples of every part (``samples``, (P, S, 3) float32, centred)."""

    def __init__(self, catalog: Catalog, dense_points: int = 1024, seed: int = 0):
        self.catalog = catalog
        self.samples = dense_samples(catalog, dense_points, seed)
        recs = catalog.records
        self.rows: dict[str, np.ndarray] = {}
        order = np.argsort(catalog.shape_of, kind="stable")
        bounds = np.searchsorted(catalog.shape_of[order], np.arange(len(catalog.shape_ids) + 1))
        for code, sid in enumerate(catalog.shape_ids):
            self.rows[sid] = np.sort(order[bounds[code]:bounds[code + 1]]).astype(np.int64)
        self.category: dict[str, str] = {}
        self.split: dict[str, str] = {}
        self.style: dict[str, Any] = {}
        for sid, rows in self.rows.items():
            first = recs[int(rows[0])]
            for r in rows.tolist():
                for key in ("category", "split"):
                    if recs[r][key] != first[key]:
                        raise ValueError(f"catalog parts of shape {sid!r} disagree on {key!r}: "
                                         f"{first[key]!r} vs {recs[r][key]!r} (part {recs[r]['part_id']})")
            self.category[sid] = first["category"]
            self.split[sid] = first["split"]
            self.style[sid] = first["style"]
        self.labels = np.array([r["label"] for r in recs], dtype=object)
        self.areas = np.array([float(r["area"]) for r in recs], dtype=np.float64)
        self._descriptors: dict[int, np.ndarray] = {}

    def part_descriptors(self, n_pairs: int) -> np.ndarray:
        """Fixed descriptors of every part's dense samples (computed once; CK10 and the fixed
        embedding share them). Shapes: returns (P, DESCRIPTOR_DIM) float64."""
        if n_pairs not in self._descriptors:
            self._descriptors[n_pairs] = descriptors(self.samples, n_pairs=n_pairs)
        return self._descriptors[n_pairs]

    def shapes(self, category: str, split: str) -> list[str]:
        return sorted(s for s in self.rows if self.category[s] == category and self.split[s] == split)

    def categories(self) -> list[str]:
        return sorted(set(self.category.values()))

    def labelled_parts(self, shape_id: str) -> dict[str, np.ndarray]:
        """Rows of one shape grouped by semantic label (unlabelled components belong to none)."""
        out: dict[str, list[int]] = {}
        for r in self.rows[shape_id].tolist():
            lab = self.labels[r]
            if lab is not None:
                out.setdefault(str(lab), []).append(r)
        return {k: np.asarray(v, np.int64) for k, v in sorted(out.items())}


def sample_rows(index: ShapeIndex, rows: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` points area-weighted over catalog parts, each moved to its place in the shape frame.

    The training sampler (``training.data.sampling.draw_area_weighted``) over the dense samples:
    a part is drawn with probability proportional to its area, then one of its surface samples.

    Shapes:
        rows (r,) -> (n, 3) float32.
    """
    rows = np.asarray(rows, dtype=np.int64)
    if rows.size == 0:
        raise ValueError("cannot sample points from an empty set of parts")
    return draw_area_weighted(index.samples, index.catalog.translations, index.areas, rows, n, rng)


def setting_rng(seed: int, category: str, setting: str, *extra: int) -> np.random.Generator:
    """The generator of one category's draws for one setting (queries, or assembly starts)."""
    return np.random.default_rng([seed, stable_code(category), _SETTING_CODE[setting], *extra])



def make_queries(index: ShapeIndex, setting: str, n_per_category: int, n_points: int, seed: int,
                 split: str = "test", categories: list[str] | None = None) -> list[Query]:
    """Retrieval queries of one setting for every category (see the module docstring)."""
    if setting not in SETTINGS:
        raise ValueError(f"unknown query setting {setting!r}; expected one of {SETTINGS}")
    queries: list[Query] = []
    for cat in categories or index.categories():
        pairs: list[tuple[str, str]] = []
        for sid in index.shapes(cat, split):
            parts = index.labelled_parts(sid)
            for label, rows in parts.items():
                rest = np.setdiff1d(index.rows[sid], rows)
                if rest.size:  # a query must keep something, and remove something
                    pairs.append((sid, label))
        rng = setting_rng(seed, cat, setting)
        order = rng.permutation(len(pairs))[:n_per_category]
        for qi, pi in enumerate(order.tolist()):
            sid, label = pairs[pi]
            part = index.labelled_parts(sid)[label]
            rest = np.setdiff1d(index.rows[sid], part)
            present, removed = (rest, part) if setting == "all_but_one" else (part, rest)
            pts = sample_rows(index, present, n_points, setting_rng(seed, cat, setting, qi, 1))
            queries.append(Query(qid=f"{cat}/{setting}/{qi:03d}", category=cat, shape_id=sid, setting=setting,
                                 present=present, removed=removed, label=label, style=index.style[sid],
                                 points=pts))
    return queries


def make_placement_queries(index: ShapeIndex, split: str, n_per_category: int, n_points: int, seed: int,
                           categories: list[str] | None = None) -> list[PlacementQuery]:
    """One component removed, the rest as query, for shapes of ``split`` (Table 4)."""
    setting = f"placement:{split}"
    if setting not in _SETTING_CODE:
        raise ValueError(f"unknown split {split!r}; expected 'train' or 'test'")
    out: list[PlacementQuery] = []
    cat_list = categories or index.categories()
    for cat in cat_list:
        pairs = [(sid, int(r)) for sid in index.shapes(cat, split) for r in index.rows[sid].tolist()
                 if len(index.rows[sid]) >= 2]
        order = setting_rng(seed, cat, setting).permutation(len(pairs))[:n_per_category]
        for qi, pi in enumerate(order.tolist()):
            sid, target = pairs[pi]
            present = index.rows[sid][index.rows[sid] != target]
            pts = sample_rows(index, present, n_points, setting_rng(seed, cat, setting, qi, 1))
            out.append(PlacementQuery(
                qid=f"{cat}/{setting}/{qi:03d}", category=cat, shape_id=sid, split=split, target=target,
                present=present, points=pts,
                true_translation=index.catalog.translations[target].astype(np.float64)))
    return out


def candidate_pool(index: ShapeIndex, shape_id: str, category: str, scope: str = "category") -> np.ndarray:
    """Catalog rows a query of ``shape_id`` may retrieve: other shapes only (and its category).

    Shapes:
        returns (p,) int64, sorted.
    """
    if scope not in POOL_SCOPES:
        raise ValueError(f"unknown pool scope {scope!r}; expected one of {POOL_SCOPES}")
    cat = index.catalog
    own = cat.shape_code(shape_id)
    mask = cat.shape_of != own
    if scope == "category":
        mask &= cat.category_of == cat.category_codes([category])[0]
    return np.flatnonzero(mask).astype(np.int64)


def finalize_ranking(ranked: np.ndarray, pool: np.ndarray, group: np.ndarray | None,
                     k: int | None) -> np.ndarray:
    """Keep the rows of ``ranked`` that are in ``pool``, collapse near-duplicates, cut at ``k``.

    This is the one filter every method's ranking passes through, so a query's own shape (never
    in the pool) can never be retrieved, whatever a method returns.

    Args:
        ranked: catalog rows, best first (may hold rows outside the pool and repeats).
        pool: allowed rows.
        group: near-duplicate group of every catalog row (``Catalog.group``); None keeps duplicates.
        k: length cut (None = keep all).

    Shapes:
        ranked (r,), pool (p,), group (P,) -> (<= k,) int64.
    """
    ranked = np.asarray(ranked, dtype=np.int64)
    keep = np.isin(ranked, pool)
    ranked = ranked[keep]
    # Keep the first occurrence of each duplicate group (or of each row: a ranking may repeat one).
    key = group[ranked] if group is not None else ranked
    _, first = np.unique(key, return_index=True)
    ranked = ranked[np.sort(first)]
    return ranked if k is None else ranked[:k]


def relevant_in_pool(relevant: np.ndarray, pool: np.ndarray, group: np.ndarray | None) -> int:
    """How many relevant items a collapsed ranking of ``pool`` could show (R of AP@k).

    With duplicate collapse, a group counts once, as relevant if any member is.

    Shapes:
        relevant (p,) bool over ``pool``.
    """
    relevant = np.asarray(relevant, dtype=bool)
    if group is None:
        return int(relevant.sum())
    return len(np.unique(group[pool[relevant]]))
