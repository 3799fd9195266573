"""The catalog's FAISS index, chosen by catalog size: exact below a threshold, approximate above.

A flat (exact) index searches every vector: about 0.4 ms for 8 queries over 10k parts, but
37 ms over 1M on this project's machines, which would dominate a /suggest. Above ``flat_max``
parts ``build_index`` builds an approximate index instead (IVF-Flat by default, HNSW on
request) and *tunes its search breadth on the data*: it searches tuning queries and raises
``nprobe`` (IVF) or ``efSearch`` (HNSW) until recall@k against exact search reaches the target.
The tuning queries should be what the service searches: g's mixture means of partial assemblies
(the export passes those of training shapes). Without them, jittered copies of catalog
embeddings stand in; they lie about twice as close to the catalog as real means (median distance
to the nearest part 0.20 against 0.38 on the shipped model at 100k parts), and recall tuned to
0.957 on them was 0.909 on held-out queries' means.
The chosen parameters, and the recall measured with them, come back as a JSON-able dict that
the export records in ``manifest.json`` (``"index"``) and that ``configure_search`` applies to
the loaded index, so the server searches exactly as the export measured.

Manifest entry: ``{"type": "IndexIVFFlat", "params": {"metric": "l2", "dim": 50, "nlist": 1024,
"nprobe": 16, "recall": 0.97, "recall_k": 64, ...}}``; ``index_entry`` / ``params_from_entry``
convert between it and the flat params dict. Older manifests (``IndexFlatL2`` with only metric
and dim) load unchanged.

Torch-free: used by ``training/export.py``, the service's loader and the benchmark.
"""

from __future__ import annotations

import logging
import math
from typing import Any, Literal

import faiss
import numpy as np

log = logging.getLogger(__name__)

IndexKind = Literal["auto", "flat", "ivf", "hnsw"]

_METRICS = {"l2": faiss.METRIC_L2, "ip": faiss.METRIC_INNER_PRODUCT}


def build_index(embeddings: np.ndarray, *, flat_max: int = 50_000, kind: IndexKind = "auto",
                metric: str = "l2", target_recall: float = 0.95, recall_k: int = 64,
                queries: np.ndarray | None = None, tuning_queries: int = 1000, query_jitter: float = 0.5,
                seed: int = 0,
                nlist: int | None = None, train_points_per_list: int = 64, hnsw_m: int = 32,
                ef_construction: int = 80) -> tuple[faiss.Index, dict[str, Any]]:
    """An index over ``embeddings`` (row i = catalog part i) and the parameters to search it with.

    Args:
        embeddings: the catalog's part embeddings.
        flat_max: catalogs of at most this many parts get an exact flat index (``kind="auto"``).
        kind: ``"auto"`` (flat up to ``flat_max``, IVF above), or force ``"flat"``, ``"ivf"``,
            ``"hnsw"``.
        metric: ``"l2"`` or ``"ip"`` (inner product).
        target_recall: the approximate index's search breadth is raised until recall@``recall_k``
            against exact search reaches this on the tuning queries (or the breadth is exhausted).
        recall_k: neighbours per query the recall is measured at (the service asks for
            ``neighbours_per_mode``, 64 by default).
        queries: the tuning queries, (m, d): vectors like those the service will search (g's
            mixture means); at most ``tuning_queries`` of them are used. None: jittered catalog
            embeddings.
        tuning_queries: how many tuning queries are searched to measure recall.
        query_jitter: the jittered embeddings' Gaussian noise, per dimension, as a fraction of
            the embeddings' own standard deviation in that dimension.
        seed: seed of the tuning queries, the IVF training sample and k-means.
        nlist: IVF lists (None: about ``4 sqrt(n)``, a power of two).
        train_points_per_list: IVF k-means trains on this many points per list (a subsample).
        hnsw_m, ef_construction: HNSW graph degree and build breadth.

    Returns:
        ``(index, params)``; ``params`` has ``type``, ``metric``, ``dim``, the type's build and
        search parameters and, for approximate indexes, the measured ``recall`` at ``recall_k``.

    Shapes:
        embeddings: (n, d) float32.
    """
    x = np.ascontiguousarray(embeddings, dtype=np.float32)
    if x.ndim != 2 or len(x) == 0:
        raise ValueError(f"embeddings must be a non-empty (n, d) array, found shape {x.shape}")
    if not np.isfinite(x).all():
        raise ValueError("embeddings contain NaN or infinite values")
    if metric not in _METRICS:
        raise ValueError(f"metric must be one of {sorted(_METRICS)}, found {metric!r}")
    n, d = x.shape
    if kind == "auto":
        kind = "flat" if n <= flat_max else "ivf"
    base: dict[str, Any] = {"metric": metric, "dim": int(d)}
    index: faiss.Index
    if kind == "flat":
        index = faiss.IndexFlat(d, _METRICS[metric])
        index.add(x)
        name = "IndexFlatL2" if metric == "l2" else "IndexFlatIP"
        return index, {"type": name, **base}
    if kind == "ivf":
        index, built = _build_ivf(x, metric, nlist, train_points_per_list, seed)
    elif kind == "hnsw":
        index, built = _build_hnsw(x, metric, hnsw_m, ef_construction)
    else:
        raise ValueError(f"index kind must be auto, flat, ivf or hnsw, found {kind!r}")
    params = {**base, **built}
    source = "jittered_embeddings" if queries is None else "given"
    queries = (jittered_queries(x, min(tuning_queries, n), query_jitter, seed) if queries is None
               else _tuning_subset(queries, d, tuning_queries, seed))
    k = min(recall_k, n)
    exact = exact_search(x, queries, k, metric)
    params.update(_tune(index, params, queries, exact, k, target_recall))
    params["tuning_source"] = source
    log.info("index %s over %d parts: %s", params["type"], n, params)
    return index, params


def configure_search(index: faiss.Index, params: dict[str, Any]) -> None:
    """Apply recorded search parameters (``nprobe``, ``efSearch``) to a loaded index.

    ``params`` is the flat dict ``build_index`` returned, or a manifest ``"index"`` entry
    (``{"type": ..., "params": {...}}``). Parameters the index does not have are an error
    naming them; a flat index needs none.
    """
    p = params_from_entry(params)
    ivf = _ivf_of(index)
    hnsw = _hnsw_of(index)
    if "nprobe" in p:
        if ivf is None:
            raise ValueError(f"index parameters give nprobe, but the index is {type(index).__name__}, "
                             "not IVF")
        ivf.nprobe = int(p["nprobe"])
    if "efSearch" in p:
        if hnsw is None:
            raise ValueError(f"index parameters give efSearch, but the index is {type(index).__name__}, "
                             "not HNSW")
        hnsw.hnsw.efSearch = int(p["efSearch"])


def index_entry(params: dict[str, Any]) -> dict[str, Any]:
    """The manifest's ``"index"`` entry for ``build_index``'s params: ``{"type", "params"}``."""
    rest = {k: v for k, v in params.items() if k != "type"}
    return {"type": params["type"], "params": rest}


def params_from_entry(entry: dict[str, Any]) -> dict[str, Any]:
    """The flat params dict of a manifest ``"index"`` entry (a flat dict passes through)."""
    if isinstance(entry.get("params"), dict):
        return {"type": entry.get("type"), **entry["params"]}
    return dict(entry)


def jittered_queries(x: np.ndarray, m: int, jitter: float, seed: int) -> np.ndarray:
    """``m`` random rows of ``x`` with Gaussian noise of ``jitter`` times each dimension's std.

    Shapes:
        x: (n, d) -> (m, d) float32.
    """
    rng = np.random.default_rng(seed)
    rows = rng.choice(len(x), size=m, replace=len(x) < m)
    scale = jitter * x.std(axis=0, keepdims=True)
    return np.ascontiguousarray(x[rows] + rng.standard_normal((m, x.shape[1])) * scale, dtype=np.float32)


def _tuning_subset(queries: np.ndarray, d: int, m: int, seed: int) -> np.ndarray:
    """At most ``m`` of the given tuning queries (a seeded sample), checked and as float32."""
    q = np.asarray(queries, dtype=np.float32)
    if q.ndim != 2 or q.shape[1] != d or len(q) == 0:
        raise ValueError(f"tuning queries must be a non-empty (m, {d}) array, found shape {q.shape}")
    if not np.isfinite(q).all():
        raise ValueError("tuning queries contain NaN or infinite values")
    if len(q) > m:
        q = q[np.sort(np.random.default_rng(seed).choice(len(q), size=m, replace=False))]
    return np.ascontiguousarray(q)


def exact_search(x: np.ndarray, queries: np.ndarray, k: int, metric: str = "l2") -> np.ndarray:
    """Labels of the exact ``k`` nearest rows of ``x`` for each query (flat search).

    Shapes:
        x: (n, d); queries: (q, d) -> (q, k) int64.
    """
    flat = faiss.IndexFlat(x.shape[1], _METRICS[metric])
    flat.add(np.ascontiguousarray(x, dtype=np.float32))
    return flat.search(np.ascontiguousarray(queries, dtype=np.float32), k)[1]


def recall_at_k(found: np.ndarray, exact: np.ndarray) -> float:
    """Mean share of each query's exact neighbours that the approximate search found.

    Shapes:
        found, exact: (q, k) labels (-1 for missing entries in ``found``).
    """
    hits = sum(len(np.intersect1d(f[f >= 0], e)) for f, e in zip(found, exact, strict=True))
    return hits / exact.size


def _build_ivf(x: np.ndarray, metric: str, nlist: int | None, per_list: int,
               seed: int) -> tuple[faiss.Index, dict[str, Any]]:
    n, d = x.shape
    if nlist is None:  # about 4 sqrt(n) lists (FAISS's guideline), a power of two
        nlist = 2 ** round(math.log2(max(1.0, 4 * math.sqrt(n))))
    nlist = max(1, min(int(nlist), n // 39))  # k-means wants at least 39 points per centroid
    quantizer = faiss.IndexFlat(d, _METRICS[metric])
    index = faiss.IndexIVFFlat(quantizer, d, nlist, _METRICS[metric])
    index.cp.seed = seed
    index.cp.max_points_per_centroid = per_list  # FAISS would subsample silently; say so here
    rng = np.random.default_rng(seed)
    m = min(n, max(nlist, per_list * nlist))
    train = x if m == n else x[np.sort(rng.choice(n, size=m, replace=False))]
    index.train(train)
    index.add(x)  # (faiss's Python wrapper keeps ``quantizer`` alive as long as ``index``)
    return index, {"type": "IndexIVFFlat", "nlist": nlist, "train_points": m}


def _build_hnsw(x: np.ndarray, metric: str, m: int, ef_construction: int
                ) -> tuple[faiss.Index, dict[str, Any]]:
    index = faiss.IndexHNSWFlat(x.shape[1], m, _METRICS[metric])
    index.hnsw.efConstruction = ef_construction
    index.add(x)
    return index, {"type": "IndexHNSWFlat", "M": m, "efConstruction": ef_construction}


def _tune(index: faiss.Index, params: dict[str, Any], queries: np.ndarray, exact: np.ndarray, k: int,
          target: float) -> dict[str, Any]:
    """The smallest search breadth (doubling, then refined) whose recall@k reaches ``target``."""
    if params["type"] == "IndexIVFFlat":
        name, lo, hi = "nprobe", 1, int(params["nlist"])
    else:
        name, lo, hi = "efSearch", k, max(k, 4096)

    def recall(breadth: int) -> float:
        configure_search(index, {name: breadth})
        return recall_at_k(index.search(queries, k)[1], exact)

    measured: dict[int, float] = {}
    breadth = lo
    while True:
        measured[breadth] = recall(breadth)
        if measured[breadth] >= target or breadth >= hi:
            break
        breadth = min(hi, breadth * 2)
    # Refine between the last failing breadth and the first passing one (binary search).
    if measured[breadth] >= target:
        bad = max((b for b, r in measured.items() if r < target), default=None)
        good = breadth
        while bad is not None and good - bad > max(1, good // 8):
            mid = (bad + good) // 2
            measured[mid] = recall(mid)
            if measured[mid] >= target:
                good = mid
            else:
                bad = mid
        breadth = good
    else:
        log.warning("index %s: recall@%d %.3f at the largest %s=%d, below the target %.2f",
                    params["type"], k, measured[breadth], name, breadth, target)
    configure_search(index, {name: breadth})
    return {name: breadth, "recall": round(measured[breadth], 4), "recall_k": k,
            "recall_target": target, "tuning_queries": len(queries)}


def _ivf_of(index: faiss.Index) -> Any:
    try:
        return faiss.extract_index_ivf(index)
    except RuntimeError:
        return None


def _hnsw_of(index: faiss.Index) -> Any:
    return index if isinstance(index, faiss.IndexHNSW) else None
