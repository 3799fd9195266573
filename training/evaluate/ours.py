""""Ours": the shipped model, evaluated through the service's suggestion engine.

Everything goes through ``service.suggest.engine.SuggestionEngine`` on the loaded artifacts, i.e. on
exactly what ships: the ONNX graphs in onnxruntime, the FAISS index, the catalog and the engine's
filters, scoring and duplicate collapse.

* "Ours" runs the engine with the service's settings, complement check included; "Ours
  (likelihood only)" is the same engine without it, the paper's ranking (an ablation).
* Rankings for the tables ask the engine itself to exclude the query's shape
  (``exclude_shapes``) and to keep the pool's category (``categories``), with the shipped
  duplicate collapse; the protocol's ``finalize_ranking`` then re-checks the pool.
* The exact-component recall puts the removed part back into the pool, which no engine filter
  can express (the query's *remaining* parts must stay out), so it asks the engine for its
  top ``max_k`` of the category without collapse and lets ``finalize_ranking`` filter and
  collapse.
* Full rankings (percentile rank) score every pool part with the engine's networks (g) and its
  exact mixture log-likelihood (``service.suggest.mixture``), without the FAISS shortlist.
* Placement uses ``engine.place`` (h_query, the part's precomputed h_part feature, h_head) with
  the service's contact refinement off: h alone. ``refine`` then applies the service's contact
  refinement the way ``POST /assemble`` does for assemblies of catalog parts: against the
  present parts' oriented surface samples (``engine.contacts``).
"""

from __future__ import annotations

import numpy as np

from service.suggest.contact import Assembly, Surface
from service.suggest.engine import SuggestionEngine, SuggestOptions
from service.suggest.mixture import mixture_log_likelihood
from training.evaluate.protocol import Query


class EngineMethod:
    """The shipped joint model behind the ``Method`` interface of the benchmark."""

    name = "Ours"
    per_part_scores = True

    def __init__(self, engine: SuggestionEngine, name: str = "Ours"):
        self.name = name
        self.engine = engine
        self.catalog = engine.catalog
        version = engine.model_version
        check = (", then the complement check (parts h places mostly onto the query's own points go last)"
                 if engine.config.suggest_complement_check else
                 ", without the complement check (the paper's ranking)")
        self.description = (f"the shipped joint model (artifact {version}) through the service's suggestion "
                            "engine: g in onnxruntime, FAISS shortlist of each mode's neighbours, exact "
                            f"mixture log-likelihood, duplicate collapse{check}")
        self._mixture_cache: tuple[str, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None

    def _categories(self, pool: np.ndarray) -> tuple[str, ...]:
        codes = np.unique(self.catalog.category_of[pool])
        if len(codes) == len(self.catalog.categories):
            return ()
        return tuple(self.catalog.categories[int(c)] for c in codes)

    def rank(self, query: Query, pool: np.ndarray, k: int) -> np.ndarray:
        """The engine's ranking of the pool's category; see the module docstring for the two modes."""
        pool = np.asarray(pool, dtype=np.int64)
        if len(pool) == 0:
            return pool
        own = self.catalog.shape_code(query.shape_id)
        max_k = self.engine.config.max_k
        if np.any(self.catalog.shape_of[pool] == own):
            options = SuggestOptions(k=max_k, categories=self._categories(pool), collapse_duplicates=False)
        else:
            options = SuggestOptions(k=min(k, max_k), categories=self._categories(pool),
                                     exclude_shapes=(query.shape_id,), collapse_duplicates=True)
        result = self.engine.suggest(query.points, options)
        return np.array([s.part_index for s in result.suggestions], dtype=np.int64)

    def mixture(self, query: Query) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """g's mixture for one query, through the engine's input preparation and ONNX session.

        Shapes:
            returns weights (K,), means (K, D), sigmas (K, D).
        """
        if self._mixture_cache is None or self._mixture_cache[0] != query.qid:
            pts = self.engine.prepare(query.points, SuggestOptions().frame)
            mix = self.engine.networks.mixture(pts[None])
            self._mixture_cache = (query.qid, (mix.weights[0], mix.means[0], mix.sigmas[0]))
        return self._mixture_cache[1]

    def scores(self, query: Query, rows: np.ndarray) -> np.ndarray:
        w, mu, sd = self.mixture(query)
        ll, _ = mixture_log_likelihood(self.catalog.embeddings[np.asarray(rows, np.int64)], w, mu, sd)
        return ll

    def place(self, points: np.ndarray, rows: list[int]) -> tuple[np.ndarray, np.ndarray]:
        """Where h places catalog parts next to a query (shape frame), unrefined, and the size each
        is answered with (fitted by h's scale head when the service fits, as it does by default).

        Shapes:
            points (N, 3) -> translations (len(rows), 3), scales (len(rows), 3) float64, canonical axes.
        """
        result = self.engine.place(points, [self.catalog.part_ids[r] for r in rows], refine_contact=False)
        return (np.stack([p.translation for p in result.placements]).astype(np.float64),
                np.stack([p.scale for p in result.placements]).astype(np.float64))

    def refine(self, row: int, translation: np.ndarray, present: np.ndarray,
               scale: np.ndarray | None = None) -> np.ndarray:
        """A translation of catalog part ``row`` (at ``scale``, per axis; None: its catalog size)
        after the service's contact refinement against the present catalog parts (at their
        catalog translations), as ``POST /assemble`` refines.

        Shapes:
            translation (3,), present (r,) catalog rows, scale (3,) -> (3,) float64.
        """
        contacts, cat = self.engine.contacts, self.catalog
        surfaces = [contacts.part_surface(cat, int(r)).moved(cat.translations[r]) for r in present.tolist()]
        t = np.asarray(translation, dtype=np.float64)
        scales = None if scale is None else np.asarray(scale, dtype=np.float64).reshape(1, 3)
        return t + self.engine.refine_against(Assembly(Surface.union(surfaces)), np.array([row]), t[None],
                                              scales)[0]
