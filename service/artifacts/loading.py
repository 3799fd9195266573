"""Open an artifact folder once, check every file against the manifest, refuse bad folders.

``load_served_artifacts`` (``load_artifacts`` with the server's settings) is what the server's
lifespan calls: it opens the five ONNX graphs with
explicit session options, the FAISS index and the catalog, checks names, dimensions and counts
against ``manifest.json`` and each other, runs every graph once on catalog data, and raises
``ArtifactError`` naming the offending file at the first problem.
"""

from __future__ import annotations

import logging
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import faiss
import numpy as np
import onnxruntime as ort
from threadpoolctl import threadpool_limits

from service.artifacts.catalog import Catalog, load_catalog
from service.artifacts.indexing import configure_search, params_from_entry, read_flags
from service.artifacts.layout import (
    CATALOG_ARRAYS,
    CATALOG_JSON,
    FAMILIARITY_FILE,
    GRAPH_FILES,
    GRAPH_INPUTS,
    GRAPH_OUTPUTS,
    INDEX_FILE,
    OPTIONAL_OUTPUTS,
    ArtifactError,
    read_manifest,
)
from service.artifacts.models import Networks
from service.settings import Settings

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FamiliarityBank:
    """The familiarity check's bank (``familiarity.npz``) and its calibrated threshold.

    Shapes:
        descriptors: (Q, P) float32, in the principal subspace ``components`` (P, K * D + K)
        about ``mean`` (K * D + K,).
    """

    descriptors: np.ndarray
    threshold: float
    mean: np.ndarray
    components: np.ndarray


def load_familiarity(folder: Path, manifest: dict[str, Any]) -> FamiliarityBank | None:
    """The bank the manifest names (None for an export made before it); ``ArtifactError`` names
    the file when it is missing, unreadable or does not match g's outputs."""
    entry = manifest.get("familiarity")
    if entry is None:
        return None
    path = folder / FAMILIARITY_FILE
    K, D = int(manifest["n_modes"]), int(manifest["embedding_dim"])
    try:
        threshold = float(entry["threshold"])
        with np.load(path, allow_pickle=False) as data:
            descriptors, mean, components = (np.asarray(data[k], dtype=np.float32)
                                             for k in ("descriptors", "mean", "components"))
    except (OSError, KeyError, TypeError, ValueError, zipfile.BadZipFile) as exc:
        raise ArtifactError(f"{path}: cannot read the familiarity bank the manifest names ({exc!r})") from exc
    F = K * D + K
    if (mean.shape != (F,) or components.ndim != 2 or components.shape[1] != F
            or descriptors.ndim != 2 or descriptors.shape[1] != len(components) or len(descriptors) == 0):
        raise ArtifactError(f"{path}: expected mean ({F},), components (P, {F}) and descriptors (Q, P) for "
                            f"{K} modes of {D} dimensions, found shapes {mean.shape}, {components.shape} "
                            f"and {descriptors.shape}")
    if not (all(np.isfinite(a).all() for a in (descriptors, mean, components))
            and np.isfinite(threshold) and threshold > 0):
        raise ArtifactError(f"{path}: non-finite arrays or a threshold that is not positive "
                            f"({threshold!r} in manifest.json)")
    return FamiliarityBank(descriptors, threshold, mean, components)


@dataclass
class Artifacts:
    """Everything loaded from one artifact folder, checked and ready to serve."""

    folder: Path
    manifest: dict[str, Any]
    networks: Networks
    index: faiss.Index
    catalog: Catalog
    familiarity: FamiliarityBank | None = None

    @property
    def model_version(self) -> str:
        return str(self.manifest["model_version"])

    @property
    def n_points(self) -> int:
        """Points per query the networks were trained on (N)."""
        return int(self.manifest["n_points"])

    @property
    def placement_points(self) -> int:
        """Points h takes of a query and of a part (the manifest's ``placement_points``; N when
        absent). h places more precisely on more points than f and g need (docs/training.md)."""
        return int(self.manifest.get("placement_points", self.n_points))

    @property
    def query_points(self) -> int:
        """Points a query should bring for every network: what the service samples a mesh or an
        assembly to before each network takes its own count."""
        return max(self.n_points, self.placement_points)

    @property
    def n_modes(self) -> int:
        return int(self.manifest["n_modes"])

    @property
    def head_categories(self) -> list[str]:
        """The classes of g's ``category_probs`` output, in order (empty without a category head)."""
        return [str(c) for c in self.manifest.get("categories") or []]

    @property
    def embedding_dim(self) -> int:
        return int(self.manifest["embedding_dim"])


def session_options(threads: int) -> ort.SessionOptions:
    """ONNX Runtime options for serving: fixed threads, no spinning, full graph optimisation.

    Idle onnxruntime workers spin by default and starve FAISS's threads in the same process
    (searches 3-4x slower), so spinning is turned off for both thread pools.
    """
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    opts.add_session_config_entry("session.inter_op.allow_spinning", "0")
    opts.log_severity_level = 3  # errors only: warnings about unused initialisers are noise
    return opts


def build_session(path: Path, threads: int) -> ort.InferenceSession:
    """One ONNX graph as a CPU session with ``session_options(threads)``: the one way a session is
    built, by the server, the exporter (``training.export``) and the weight read-back
    (``training.from_onnx``) alike. onnxruntime's own errors pass through untouched."""
    # onnxruntime's telemetry is off (ORT_DISABLE_TELEMETRY, set in service/__init__.py); this
    # also stops the events of a build that honours only the API.
    ort.disable_telemetry_events()
    return ort.InferenceSession(str(path), sess_options=session_options(threads),
                                providers=["CPUExecutionProvider"])


def open_session(path: Path, graph: str, threads: int) -> ort.InferenceSession:
    """Open one graph and check its input and output names against the artifact contract."""
    if not path.is_file():
        raise ArtifactError(f"artifact file missing: {path}")
    try:
        sess = build_session(path, threads)
    except Exception as exc:  # onnxruntime raises its own untyped errors on bad files
        raise ArtifactError(f"{path}: cannot be opened as an ONNX graph ({exc})") from exc
    outputs = [o.name for o in sess.get_outputs()]
    allowed = [GRAPH_OUTPUTS[graph], GRAPH_OUTPUTS[graph] + OPTIONAL_OUTPUTS.get(graph, [])]
    inputs = [i.name for i in sess.get_inputs()]
    if inputs != GRAPH_INPUTS[graph]:
        raise ArtifactError(f"{path}: graph {graph!r} has inputs {inputs}, expected {GRAPH_INPUTS[graph]}")
    if outputs not in allowed:
        raise ArtifactError(f"{path}: graph {graph!r} has outputs {outputs}, expected "
                            + " or ".join(str(a) for a in allowed))
    for inp in sess.get_inputs():
        if inp.type != "tensor(float)":
            raise ArtifactError(f"{path}: input {inp.name!r} has type {inp.type}, expected tensor(float)")
    return sess


def _static_dim(sess: ort.InferenceSession, output: str, axis: int) -> int | None:
    """A fixed dimension of an output, or None when the graph leaves it symbolic."""
    for o in sess.get_outputs():
        if o.name == output:
            dim = o.shape[axis] if len(o.shape) > axis else None
            return dim if isinstance(dim, int) else None
    return None


def load_index(path: Path, dim: int, count: int, threads: int, blas_threshold: int,
               params: dict[str, Any] | None = None) -> faiss.Index:
    """Read the FAISS index, check it holds ``count`` vectors of size ``dim``, and configure it.

    ``params`` is the manifest's ``"index"`` entry: its type must be the file's, and its search
    parameters (``nprobe``, ``efSearch``; ``service.artifacts.indexing``) are applied. Older manifests
    (a flat index, no search parameters) load as before.
    """
    if not path.is_file():
        raise ArtifactError(f"artifact file missing: {path}")
    try:
        index = faiss.read_index(str(path), read_flags(params))
    except RuntimeError as exc:
        raise ArtifactError(f"{path}: cannot read FAISS index ({str(exc).splitlines()[0]})") from exc
    if index.d != dim:
        raise ArtifactError(f"{path}: index dimension {index.d}, but the manifest says embedding_dim={dim}")
    if index.ntotal != count:
        raise ArtifactError(f"{path}: index holds {index.ntotal} vectors, but the manifest says "
                            f"part_count={count}")
    if not index.is_trained:
        raise ArtifactError(f"{path}: index is not trained")
    if params is not None:
        entry = params_from_entry(params)
        if entry.get("type") not in (None, type(index).__name__):
            raise ArtifactError(f"{path}: index is a {type(index).__name__}, but manifest.json says "
                                f"{entry['type']}")
        try:
            configure_search(index, entry)
        except ValueError as exc:
            raise ArtifactError(f"{path}: {exc} (manifest.json index entry)") from exc
    faiss.omp_set_num_threads(threads)
    faiss.cvar.distance_compute_blas_threshold = blas_threshold
    return index


def _check_run(folder: Path, nets: Networks, catalog: Catalog, manifest: dict[str, Any]) -> None:
    """Run every graph once on two catalog parts and check output shapes and values.

    Symbolic output shapes cannot be checked statically; this catches a graph exported with the
    wrong embedding size, mode count or feature size before the first request does.
    """
    n, K, D = int(manifest["n_points"]), int(manifest["n_modes"]), int(manifest["embedding_dim"])
    parts = catalog.points[:2].astype(np.float32)
    B = len(parts)
    rng = np.random.default_rng(0)
    query = rng.uniform(-0.5, 0.5, size=(B, n, 3)).astype(np.float32)
    fp = catalog.part_features.shape[1]
    runs: list[tuple[str, Any, tuple[int, ...]]] = []

    def run(graph: str, fn: Any, *args: Any) -> Any:
        try:
            return fn(*args)
        except Exception as exc:  # onnxruntime reports shape mismatches as generic errors
            raise ArtifactError(f"{folder / GRAPH_FILES[graph]}: test run failed ({exc})") from exc

    emb = run("f", nets.embed, parts)
    runs.append(("f", emb, (B, D)))
    mix = run("g", nets.mixture, query)
    runs += [("g", mix.weights, (B, K)), ("g", mix.means, (B, K, D)), ("g", mix.sigmas, (B, K, D))]
    qf = run("h_query", nets.query_features, query)
    pf = run("h_part", nets.part_features, parts)
    runs += [("h_query", qf, (B, qf.shape[1] if qf.ndim == 2 else -1)), ("h_part", pf, (B, fp))]
    tr = run("h_head", nets.place, qf, catalog.part_features[:B])
    runs.append(("h_head", tr, (B, 3)))
    for graph, out, shape in runs:
        path = folder / GRAPH_FILES[graph]
        if tuple(out.shape) != shape:
            raise ArtifactError(f"{path}: output of shape {tuple(out.shape)}, expected {shape} "
                                "(from manifest.json and catalog.npz)")
        if not np.all(np.isfinite(out)):
            raise ArtifactError(f"{path}: test run gave NaN or infinite values")
    if np.any(mix.sigmas <= 0):
        raise ArtifactError(f"{folder / GRAPH_FILES['g']}: sigmas must be positive")
    # The catalog must come from these graphs: f and h_part of its own points should reproduce
    # its stored embeddings and features, loosely: the stored points are a 256-point float16
    # preview of the samples the catalog was embedded from, which moves the outputs by about 5-7%
    # (measured on the shipped model); graphs of another training differ by far more.
    for graph, got, stored in (("f", emb, catalog.embeddings[:B]), ("h_part", pf, catalog.part_features[:B])):
        rel = float(np.abs(got - stored).max() / (np.abs(stored).max() + 1e-6))
        if rel > 0.25:
            log.warning("%s: recomputed %s outputs differ from %s by %.3f (relative); "
                        "is the catalog exported with these graphs?", folder / GRAPH_FILES[graph],
                        graph, folder / CATALOG_ARRAYS, rel)


def load_served_artifacts(settings: Settings) -> Artifacts:
    """The artifacts as the server loads them: its thread counts, checks and run sizes."""
    s = settings
    return load_artifacts(s.artifacts, onnx_threads=s.onnx_threads, faiss_threads=s.faiss_threads,
                          faiss_blas_threshold=s.faiss_blas_threshold, blas_threads=s.blas_threads,
                          verify_checksums=s.verify_checksums, max_points_per_run=s.max_points_per_run)


def load_artifacts(folder: Path, *, onnx_threads: int = 1, faiss_threads: int = 1,
                   faiss_blas_threshold: int = 20, blas_threads: int | None = None,
                   verify_checksums: bool = True, max_points_per_run: int = 1024) -> Artifacts:
    """Load and check an artifact folder; ``ArtifactError`` names the first bad file.

    ``blas_threads`` limits numpy's BLAS for the whole process, as FAISS's settings are (None:
    leave it as it is).
    """
    folder = Path(folder)
    if blas_threads is not None:
        threadpool_limits(limits=blas_threads, user_api="blas")
    if not folder.is_dir():
        raise ArtifactError(f"artifact folder not found: {folder}")
    manifest = read_manifest(folder, verify_checksums=verify_checksums)
    optional = [key for key in ("placement_points",) if key in manifest]  # absent: N
    for key in ("n_points", "embedding_dim", "n_modes", "part_count", *optional):
        value = manifest[key]
        if not (isinstance(value, int) and value > 0):
            raise ArtifactError(f"{folder / 'manifest.json'}: {key} must be a positive integer, "
                                f"found {value!r}")
    D, K, P = int(manifest["embedding_dim"]), int(manifest["n_modes"]), int(manifest["part_count"])
    sessions = {g: open_session(folder / name, g, onnx_threads) for g, name in GRAPH_FILES.items()}
    for graph, output, axis, expected in (("f", "embedding", 1, D), ("g", "weights", 1, K),
                                          ("g", "means", 2, D)):
        dim = _static_dim(sessions[graph], output, axis)
        if dim is not None and dim != expected:
            raise ArtifactError(f"{folder / GRAPH_FILES[graph]}: output {output!r} has size {dim} on axis "
                                f"{axis}, but manifest.json says {expected}")
    entry = manifest.get("index")
    index = load_index(folder / INDEX_FILE, D, P, faiss_threads, faiss_blas_threshold,
                       entry if isinstance(entry, dict) else None)
    catalog = load_catalog(folder / CATALOG_JSON, folder / CATALOG_ARRAYS, P, D)
    nets = Networks(**sessions, max_points_per_run=max_points_per_run)
    _check_run(folder, nets, catalog, manifest)
    log.info("loaded artifacts %s: model %s, %d parts in %d categories", folder,
             manifest["model_version"], P, len(catalog.categories))
    familiarity = load_familiarity(folder, manifest)
    return Artifacts(folder=folder, manifest=manifest, networks=nets, index=index, catalog=catalog,
                     familiarity=familiarity)
