"""The framework peer's model: the exported graphs, FAISS index and catalog, one batch at a time.

What a user of a serving framework would write around the shipped artifacts, framework-neutral
so that the BentoML service (``bench.framework.bentoml_service``) and the LitServe API
(``bench.framework.litserve_api``) wrap the same code:

- ONNX Runtime sessions of g, h_query and h_head opened here (one intra-op thread: one worker
  process per core), the FAISS index read with ``faiss.read_index``;
- the catalog read through the artifact format's own reader (``service.artifacts.catalog``: one
  owner per file format), and the service's pure maths reused: seeded resampling
  (``service.geometry.mesh``), the mixture log-likelihood (``service.suggest.mixture``) and the
  complement check (``service.suggest.complement``);
- per batch: g and h_query once on all queries (h_query on its own count of each query's points
  when the manifest gives one), one FAISS search per filter, the exact mixture
  score, near-duplicates collapsed, the service's order (``service.suggest.preferences.spread_share_order``
  by default), h_head once on every kept candidate of the batch, covered parts demoted
  (``service.suggest.complement.complement_order``) in the order of their fit keys
  (``service.suggest.fit_rank``), the top k returned.

That is the default ``/suggest`` of the service (no contact refinement, the complement check on,
the category read from g's head when it has one). None of the service's serving code runs here:
not its micro-batcher, engine, settings class or HTTP layer. Settings come in as a ``PeerConfig``
(the bench fills it from the service's settings, so both sides use the same numbers).

Runs in the peer's own virtual environment (``bench.framework.venv``): numpy, ONNX Runtime,
FAISS, SciPy and trimesh at the project's pinned versions, plus the framework.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import faiss
import numpy as np
import onnxruntime as ort

from service.artifacts.catalog import Catalog, load_catalog
from service.artifacts.layout import CATALOG_ARRAYS, CATALOG_JSON, GRAPH_FILES, INDEX_FILE, MANIFEST
from service.artifacts.models import scales_of
from service.geometry.mesh import resample_points
from service.suggest.complement import complement_order, covered_share
from service.suggest.fit_rank import fit_keys
from service.suggest.mixture import mixture_log_likelihood
from service.suggest.preferences import spread_share_order

CONFIG_ENV = "FRAMEWORK_PEER_CONFIG"  # the JSON of a PeerConfig, set by the bench for the peer process


@dataclass(frozen=True)
class PeerConfig:
    """What the peer serves and how it batches (the bench copies the numbers from ``Settings``)."""

    artifacts: str                    # exported folder
    seed: int                         # resampling seed (settings.seed)
    neighbours_per_mode: int          # nearest parts searched per mixture mean
    complement_candidates: int        # ranked candidates placed and checked before the top k
    complement_part_samples: int      # samples per placed part in the complement check
    complement_cover_distance: float  # a sample within this of the query is on its surface
    complement_cover_share: float     # a part with this share of samples on it is demoted
    suggest_order: str                # "share" (slots after the head dealt to modes) or "likelihood"
    share_min_mode_weight: float      # lighter modes get slots only after the others ran out
    share_order_head: int             # first slots kept in likelihood order
    share_spread_sigmas: float        # after the head, near-copies within this many sigmas wait
    scale_min: float                  # h's fitting scales are clipped to scale_min..scale_max
    scale_max: float
    rank_scale_weight: float          # the answer key's penalty on |log scale| (suggest.fit_rank)
    rank_move_weight: float           # and on the distance from the part's own centre
    infer_category: bool              # read the category from g's head (when the graph has one)
    category_min_confidence: float    # and keep suggestions in it from this probability on
    faiss_blas_threshold: int         # FAISS switches exact distances to BLAS past this many queries
    max_k: int                        # largest k a request may ask for
    default_k: int                    # k when a request gives none
    min_points: int                   # fewest points a request may send
    max_points: int                   # most points a request may send
    max_batch_size: int               # the framework's batching: most requests per batch
    max_latency_ms: float             # and the longest a request waits for its batch
    workers: int                      # worker processes (one per core)

    def to_json(self) -> str:
        return json.dumps(asdict(self))

    @classmethod
    def from_env(cls) -> PeerConfig:
        """The config the bench passed in ``FRAMEWORK_PEER_CONFIG``; a clear error when it is missing."""
        text = os.environ.get(CONFIG_ENV)
        if not text:
            raise RuntimeError(f"{CONFIG_ENV} is not set: start the peer through the bench "
                               "(python -m bench framework), which passes its configuration")
        return cls(**json.loads(text))


@dataclass(frozen=True)
class Query:
    """One decoded request.

    Shapes:
        points: (M, 3) float32, canonical frame.
    """

    points: np.ndarray
    k: int


class RequestError(ValueError):
    """A request the peer refuses (the framework wrapper answers 4xx with this message)."""


def parse_request(body: Any, cfg: PeerConfig) -> Query:
    """A /suggest body (``{"points": [[x, y, z], ...], "k": 10}``) as a checked ``Query``."""
    if not isinstance(body, dict) or "points" not in body:
        raise RequestError('the body must be a JSON object with "points": [[x, y, z], ...]')
    k = body.get("k", cfg.default_k)
    if not isinstance(k, int) or isinstance(k, bool) or not 1 <= k <= cfg.max_k:
        raise RequestError(f"k must be an integer between 1 and {cfg.max_k}, found {k!r}")
    try:
        points = np.asarray(body["points"], dtype=np.float32)
    except (TypeError, ValueError):
        raise RequestError("points must be a list of [x, y, z] numbers") from None
    if points.ndim != 2 or points.shape[1] != 3:
        raise RequestError(f"points must have shape (N, 3), found {points.shape}")
    if not cfg.min_points <= len(points) <= cfg.max_points:
        raise RequestError(f"between {cfg.min_points} and {cfg.max_points} points are accepted, "
                           f"found {len(points)}")
    if not np.isfinite(points).all():
        raise RequestError("points must be finite numbers")
    return Query(points, k)


class PeerModel:
    """The shipped artifacts, loaded once per worker process, answering batches of queries."""

    def __init__(self, cfg: PeerConfig):
        self.cfg = cfg
        folder = Path(cfg.artifacts)
        self.manifest = json.loads((folder / MANIFEST).read_text())
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = 1  # one worker process per core: no thread teams competing
        opts.inter_op_num_threads = 1

        def session(graph: str) -> ort.InferenceSession:
            return ort.InferenceSession(str(folder / GRAPH_FILES[graph]), opts,
                                        providers=["CPUExecutionProvider"])

        self.g, self.h_query, self.h_head = session("g"), session("h_query"), session("h_head")
        self.h_outputs = {o.name for o in self.h_head.get_outputs()}
        self.g_outputs = [o.name for o in self.g.get_outputs()]
        self.index = faiss.read_index(str(folder / INDEX_FILE))
        faiss.omp_set_num_threads(1)
        faiss.cvar.distance_compute_blas_threshold = cfg.faiss_blas_threshold
        self.catalog: Catalog = load_catalog(folder / CATALOG_JSON, folder / CATALOG_ARRAYS,
                                             int(self.manifest["part_count"]),
                                             int(self.manifest["embedding_dim"]))
        self.n_points = int(self.manifest["n_points"])
        # h may take more points than f and g (the manifest's placement_points; format 2).
        self.placement_points = int(self.manifest.get("placement_points", self.n_points))
        self.categories: list[str] = list(self.manifest.get("categories") or [])

    def suggest_batch(self, queries: list[Query]) -> list[list[dict[str, Any]]]:
        """Ranked, placed suggestions for every query of a batch, in order.

        Each suggestion is ``{"rank", "part_id", "score", "translation"}`` (canonical frame).
        """
        if not queries:
            return []
        cfg, cat = self.cfg, self.catalog
        points = np.stack([resample_points(q.points, self.n_points, cfg.seed) for q in queries])  # (B, N, 3)
        points = np.ascontiguousarray(points, dtype=np.float32)
        out = dict(zip(self.g_outputs, self.g.run(self.g_outputs, {"points": points}), strict=True))
        weights, means, sigmas = out["weights"], out["means"], out["sigmas"]  # (B, K), (B, K, D) x 2
        h_points = points if self.placement_points == self.n_points else np.ascontiguousarray(np.stack(
            [resample_points(q.points, self.placement_points, cfg.seed) for q in queries]), dtype=np.float32)
        query_features = self.h_query.run(["query_feature"], {"points": h_points})[0]  # (B, Fq)
        filters = [self._category(out.get("category_probs"), b) for b in range(len(queries))]
        candidates = self._search(means, filters, max(q.k for q in queries))
        ranked = [self._rank(candidates[b], weights[b], means[b], sigmas[b], q.k)
                  for b, q in enumerate(queries)]
        rows = np.concatenate([np.full(len(r[0]), b) for b, r in enumerate(ranked)]).astype(np.int64)
        parts = np.concatenate([r[0] for r in ranked]).astype(np.int64)
        feed = {"query_feature": np.ascontiguousarray(query_features[rows]),
                "part_feature": np.ascontiguousarray(cat.part_features[parts])}
        if "log_scale" in self.h_outputs:
            translations, log_scale = self.h_head.run(["translation", "log_scale"], feed)  # (R, 3) x 2
            scales = np.clip(scales_of(log_scale).astype(np.float64), cfg.scale_min, cfg.scale_max)
        else:
            translations = self.h_head.run(["translation"], feed)[0]
            scales = np.ones_like(translations, dtype=np.float64)
        answers = []
        for b, (q, (idx, scores, modes)) in enumerate(zip(queries, ranked, strict=True)):
            tr = translations[rows == b]
            share = covered_share(points[b], cat.part_samples(idx, cfg.complement_part_samples),
                                  tr.astype(np.float32), cfg.complement_cover_distance)
            keys = fit_keys(scores, scales[rows == b], tr, cat.translations[idx], cfg.rank_scale_weight,
                            cfg.rank_move_weight)
            deal = self._deal(idx, modes, weights[b], sigmas[b], q.k)
            top = complement_order(share, cfg.complement_cover_share, keys, deal, q.k)[:q.k]
            answers.append([{"rank": r + 1, "part_id": cat.part_ids[int(idx[j])], "score": float(scores[j]),
                             "translation": tr[j].astype(np.float64).tolist()}
                            for r, j in enumerate(top.tolist())])
        return answers

    def _category(self, probs: np.ndarray | None, b: int) -> int | None:
        """The catalog category code a query's suggestions are kept in (None: all), from g's head."""
        if probs is None or not self.cfg.infer_category or len(self.categories) != probs.shape[1]:
            return None
        best = int(np.argmax(probs[b]))
        name = self.categories[best]
        if probs[b, best] < self.cfg.category_min_confidence or name not in self.catalog.categories:
            return None
        return self.catalog.categories.index(name)

    def _search(self, means: np.ndarray, filters: list[int | None], k: int) -> list[np.ndarray]:
        """Distinct catalog rows near any of each query's means; one FAISS search per filter.

        Shapes:
            means: (B, K, D) -> B sorted int64 arrays.
        """
        B, K, D = means.shape
        nn = min(len(self.catalog), max(self.cfg.neighbours_per_mode, k))
        found: list[np.ndarray] = [np.zeros(0, np.int64)] * B
        for code in set(filters):
            members = [b for b in range(B) if filters[b] == code]
            x = np.ascontiguousarray(means[members].reshape(-1, D), dtype=np.float32)
            params = None
            if code is not None:  # an exact (flat) index checks the selector on every part
                selector = faiss.IDSelectorBatch(np.flatnonzero(self.catalog.category_of == code))
                params = faiss.SearchParameters()
                params.sel = selector
            labels = self.index.search(x, nn, params=params)[1]
            for j, b in enumerate(members):
                ids = labels[j * K:(j + 1) * K].ravel()
                found[b] = np.unique(ids[ids >= 0])
        return found

    def _rank(self, cand: np.ndarray, weights: np.ndarray, means: np.ndarray, sigmas: np.ndarray,
              k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Candidates scored by the mixture, near-duplicates collapsed, the best ones kept.

        Returns kept rows, their log-likelihoods and modes in the service's order (likelihood, or
        the share order): at most max(k, complement_candidates) of them (the complement check
        reorders those).
        """
        live = np.flatnonzero(weights > 0)  # as the service: a mode weighted 0 contributes nothing
        emb = self.catalog.embeddings[cand]
        ll, best = mixture_log_likelihood(emb, weights[live], means[live], sigmas[live])
        mode = live[best]
        order = np.argsort(-ll, kind="stable")
        cand, ll, mode = cand[order], ll[order], mode[order]
        _, first = np.unique(self.catalog.group[cand], return_index=True)
        keep = np.sort(first)
        deal = self._deal(cand[keep], mode[keep], weights, sigmas, k)
        if deal is not None:
            keep = keep[deal(np.arange(len(keep)))]
        keep = keep[:max(k, self.cfg.complement_candidates)]
        return cand[keep], ll[keep], mode[keep]

    def _deal(self, rows: np.ndarray, modes: np.ndarray, weights: np.ndarray, sigmas: np.ndarray, k: int
              ) -> Callable[[np.ndarray], np.ndarray] | None:
        """The service's order of suggestions over these parts (None: likelihood order).

        Shapes:
            rows: (C,) catalog rows; modes: (C,) the mode that explains each part best;
            weights: (K,); sigmas: (K, D).
        """
        if self.cfg.suggest_order != "share":
            return None
        cfg, emb = self.cfg, self.catalog.embeddings
        return lambda g: spread_share_order(modes[g], weights, emb[rows[g]], sigmas, k,
                                            cfg.share_min_mode_weight, cfg.share_order_head,
                                            cfg.share_spread_sigmas)
