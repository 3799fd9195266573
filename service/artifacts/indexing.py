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

For millions of parts an IVF-Flat index would hold every float32 vector in memory (2 GB at 10M
parts). Above ``compressed_min`` parts ``build_index`` builds an IVF index over 8-bit scalar-
quantised codes (zero-padded to a multiple of 16 dimensions, which FAISS scans with SIMD) inside
an ``IndexRefineFlat``: the codes give a shortlist of ``rerank`` x k, re-ranked by exact distance,
and the tuned recall is that after the re-rank. ``read_flags`` reads such a file with its exact
vectors memory-mapped, so they stay in the page cache, not in the worker's own memory. At 1M
replicated parts, product quantisation needed a larger shortlist for the same held-out recall
(8-bit codes: 8 x k for 0.948, as SQ8 at 4 x k; 4-bit fast-scan codes reached only 0.53 at
16 x k: copies 0.05 std apart are finer than its codes), and 50-D SQ8 without the padding was
scanned 10x slower. HNSW over compressed vectors was not measured: its graph alone needs 256
bytes of links per part at M = 32 (2.5 GB at 10M, most of a 3 GB worker), and HNSW-Flat took
about 100 s per million parts to build on these machines.

Manifest entry: ``{"type": "IndexIVFFlat", "params": {"metric": "l2", "dim": 50, "nlist": 1024,
"nprobe": 16, "recall": 0.97, "recall_k": 64, ...}}``; ``index_entry`` / ``params_from_entry``
convert between it and the flat params dict. Older manifests (``IndexFlatL2`` with only metric
and dim) load unchanged.

Torch-free: used by ``training/export.py``, the service's loader and the benchmark.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from typing import Any, Literal

import faiss
import numpy as np

log = logging.getLogger(__name__)

Progress = Callable[[Iterable[int]], Iterable[int]]

IndexKind = Literal["auto", "flat", "ivf", "hnsw", "ivf_sq8", "ivf_pq", "ivf_pqfs", "hnsw_sq8"]

# Compressed kinds: an IndexRefineFlat whose base keeps codes, not float32 vectors, and whose
# shortlist of ``rerank`` x k is re-ranked by exact distances to the vectors of its refine index,
# which ``read_index`` memory-maps from the file instead of loading.
COMPRESSED_KINDS = ("ivf_sq8", "ivf_pq", "ivf_pqfs", "hnsw_sq8")

_METRICS = {"l2": faiss.METRIC_L2, "ip": faiss.METRIC_INNER_PRODUCT}


def build_index(embeddings: np.ndarray, *, flat_max: int = 50_000, kind: IndexKind = "auto",
                metric: str = "l2", target_recall: float = 0.95, recall_k: int = 64,
                queries: np.ndarray | None = None, tuning_queries: int = 1000, query_jitter: float = 0.5,
                seed: int = 0,
                nlist: int | None = None, train_points_per_list: int = 64, hnsw_m: int = 32,
                ef_construction: int = 80, compressed_min: int = 2_000_000, rerank: int = 4,
                pq_m: int = 25, progress: Progress | None = None
                ) -> tuple[faiss.Index, dict[str, Any]]:
    """An index over ``embeddings`` (row i = catalog part i) and the parameters to search it with.

    Args:
        embeddings: the catalog's part embeddings.
        flat_max: catalogs of at most this many parts get an exact flat index (``kind="auto"``).
        kind: ``"auto"`` (flat up to ``flat_max``, IVF-Flat up to ``compressed_min``, IVF-SQ8
            with an exact re-rank above), or force ``"flat"``, ``"ivf"``, ``"hnsw"`` or a
            compressed kind: ``"ivf_sq8"``, ``"ivf_pq"``, ``"hnsw_sq8"``.
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
        compressed_min: ``kind="auto"`` builds a compressed index above this many parts (float32
            vectors in an IVF-Flat index would take 2 GB of memory at 10M parts).
        rerank: compressed kinds search ``rerank`` x k neighbours and keep the k nearest by
            exact distance (IndexRefineFlat's ``k_factor``).
        pq_m: product quantiser's sub-vectors (``"ivf_pq"``; 8 bits each; must divide d).
        progress: wraps the iterable of row offsets the vectors are added in (e.g. tqdm).

    Returns:
        ``(index, params)``; ``params`` has ``type`` (the FAISS index type of the file written),
        ``metric``, ``dim``, the type's build and search parameters (a compressed kind's
        ``base`` type, ``quantizer`` and ``rerank``) and, for approximate indexes, the measured
        ``recall`` at ``recall_k`` (after the re-rank). Read a written index back with
        ``faiss.read_index(path, read_flags(params))``: a compressed kind's vectors are mapped.

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
        kind = "flat" if n <= flat_max else "ivf" if n <= compressed_min else "ivf_sq8"
    base: dict[str, Any] = {"metric": metric, "dim": int(d)}
    index: faiss.Index
    if kind == "flat":
        index = faiss.IndexFlat(d, _METRICS[metric])
        index.add(x)
        name = "IndexFlatL2" if metric == "l2" else "IndexFlatIP"
        return index, {"type": name, **base}
    if kind in ("ivf", "ivf_sq8", "ivf_pq", "ivf_pqfs"):
        index, built = _build_ivf(x, metric, nlist, train_points_per_list, seed, kind, pq_m)
    elif kind in ("hnsw", "hnsw_sq8"):
        index, built = _build_hnsw(x, metric, hnsw_m, ef_construction, kind)
    else:
        raise ValueError(f"index kind must be auto, flat, ivf, hnsw, {', '.join(COMPRESSED_KINDS)}; "
                         f"found {kind!r}")
    compressed = kind in COMPRESSED_KINDS
    index = _add_refined(index, x, rerank if compressed else None, progress)
    if compressed:
        built = {"type": "IndexRefineFlat", "base": built.pop("type"), **built, "rerank": int(rerank)}
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
    naming them; a flat index needs none. An IndexRefine's base is configured, and its
    ``k_factor`` set from ``rerank``.
    """
    p = params_from_entry(params)
    if "rerank" in p:
        if not isinstance(index, faiss.IndexRefine):
            raise ValueError(f"index parameters give rerank, but the index is {type(index).__name__}, "
                             "not IndexRefine")
        index.k_factor = float(p["rerank"])
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


def read_flags(params: dict[str, Any] | None) -> int:
    """``faiss.read_index`` flags for an index file with these params (a manifest entry or flat).

    A compressed kind's file (``IndexRefineFlat``) is memory-mapped (``IO_FLAG_MMAP_IFC``): its
    float32 vectors for the re-rank (2 GB at 10M parts) stay in the file and the page cache, read
    a shortlist's rows at a time, not in the process's own memory. Others are read into memory.
    """
    p = params_from_entry(params or {})
    return faiss.IO_FLAG_MMAP_IFC if p.get("type") == "IndexRefineFlat" else 0


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


def _build_ivf(x: np.ndarray, metric: str, nlist: int | None, per_list: int, seed: int,
               kind: str = "ivf", pq_m: int = 25) -> tuple[faiss.Index, dict[str, Any]]:
    """A trained, empty IVF index (flat, SQ8 or PQ lists) and its build parameters."""
    n, d = x.shape
    if nlist is None:  # about 4 sqrt(n) lists (FAISS's guideline), a power of two
        nlist = 2 ** round(math.log2(max(1.0, 4 * math.sqrt(n))))
    nlist = max(1, min(int(nlist), n // 39))  # k-means wants at least 39 points per centroid
    quantizer = faiss.IndexFlat(d, _METRICS[metric])
    index: Any
    built: dict[str, Any]
    if kind == "ivf_sq8":
        # FAISS scans 8-bit codes with SIMD only when the dimension is a multiple of 16 (AVX-512;
        # 8 for AVX2): 50-D codes were scanned one by one, 10x slower than the same vectors zero-
        # padded to 64-D (1M parts, 8 queries, nprobe 8, top 256: 9.6 ms against 0.9 ms).
        padded = -(-d // 16) * 16
        quantizer = faiss.IndexFlat(padded, _METRICS[metric])
        ivf = faiss.IndexIVFScalarQuantizer(quantizer, padded, nlist, faiss.ScalarQuantizer.QT_8bit,
                                            _METRICS[metric])
        index = (ivf if padded == d else
                 faiss.IndexPreTransform(_zero_padding(d, padded), ivf))
        built = {"type": "IndexIVFScalarQuantizer", "quantizer": "SQ8", "padded_dim": padded}
    elif kind in ("ivf_pq", "ivf_pqfs"):
        if d % pq_m:
            raise ValueError(f"pq_m must divide the dimension {d}, found {pq_m}")
        if kind == "ivf_pq":
            index = faiss.IndexIVFPQ(quantizer, d, nlist, pq_m, 8, _METRICS[metric])
            built = {"type": "IndexIVFPQ", "quantizer": f"PQ{pq_m}x8"}
        else:  # 4-bit codes scanned in SIMD registers (FAISS's "fast scan")
            index = faiss.IndexIVFPQFastScan(quantizer, d, nlist, pq_m, 4, _METRICS[metric])
            built = {"type": "IndexIVFPQFastScan", "quantizer": f"PQ{pq_m}x4fs"}
    else:
        index = faiss.IndexIVFFlat(quantizer, d, nlist, _METRICS[metric])
        built = {"type": "IndexIVFFlat"}
    ivf_of = faiss.extract_index_ivf(index)
    ivf_of.cp.seed = seed
    ivf_of.cp.max_points_per_centroid = per_list  # FAISS would subsample silently; say so here
    rng = np.random.default_rng(seed)
    m = min(n, max(nlist, per_list * nlist))
    train = x if m == n else x[np.sort(rng.choice(n, size=m, replace=False))]
    index.train(np.ascontiguousarray(train))  # (faiss's wrapper keeps ``quantizer`` alive with ``index``)
    return index, {**built, "nlist": nlist, "train_points": m}


def _zero_padding(d: int, padded: int) -> faiss.VectorTransform:
    """A transform that keeps the ``d`` dimensions and appends ``padded - d`` zeros."""
    source = np.full(padded, -1, dtype=np.int32)
    source[:d] = np.arange(d)
    return faiss.RemapDimensionsTransform(d, padded, faiss.swig_ptr(source))  # (copies the map)


def _build_hnsw(x: np.ndarray, metric: str, m: int, ef_construction: int, kind: str = "hnsw"
                ) -> tuple[faiss.Index, dict[str, Any]]:
    """A trained, empty HNSW index (flat or SQ8 storage) and its build parameters."""
    index: Any
    if kind == "hnsw_sq8":
        index = faiss.index_factory(x.shape[1], f"HNSW{m},SQ8", _METRICS[metric])
        index.train(np.ascontiguousarray(x[:: max(1, len(x) // 100_000)]))
        name = "IndexHNSWSQ"
    else:
        index = faiss.IndexHNSWFlat(x.shape[1], m, _METRICS[metric])
        name = "IndexHNSWFlat"
    index.hnsw.efConstruction = ef_construction
    built: dict[str, Any] = {"type": name, "M": m, "efConstruction": ef_construction}
    if kind == "hnsw_sq8":
        built["quantizer"] = "SQ8"
    return index, built


# Vectors are added in blocks of this many rows: a progress bar can follow, and a memory-mapped
# catalog is read block by block instead of all at once.
_ADD_BLOCK = 500_000


def _add(index: faiss.Index, x: np.ndarray, progress: Progress | None) -> None:
    starts: Iterable[int] = range(0, len(x), _ADD_BLOCK)
    for start in (progress(starts) if progress is not None else starts):
        index.add(np.ascontiguousarray(x[start:start + _ADD_BLOCK]))


def _add_refined(index: faiss.Index, x: np.ndarray, rerank: int | None, progress: Progress | None
                 ) -> faiss.Index:
    """Add ``x`` to the trained, empty ``index``; with ``rerank``, to an IndexRefineFlat around it
    (exact re-rank of ``rerank`` x k candidates), which is returned instead."""
    target = index
    if rerank is not None:
        if rerank < 1:
            raise ValueError(f"rerank must be at least 1, found {rerank}")
        # An exact flat copy of every vector, for the re-rank (faiss's wrapper keeps ``index`` alive).
        target = faiss.IndexRefineFlat(index)
        target.k_factor = float(rerank)
    _add(target, x, progress)
    return target


def _tune(index: faiss.Index, params: dict[str, Any], queries: np.ndarray,
          exact: np.ndarray, k: int, target: float) -> dict[str, Any]:
    """The smallest search breadth (doubling, then refined) whose recall@k reaches ``target``."""
    if "nlist" in params:
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
    if isinstance(index, faiss.IndexRefine):
        index = faiss.downcast_index(index.base_index)
    return index if isinstance(index, faiss.IndexHNSW) else None
