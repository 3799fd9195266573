"""The exported artifact format: the one contract between the trainer and the server.

Layout of an artifact folder (``exported/`` ships with the repository)::

    manifest.json       format version, model config, dataset seed/hash, metrics, checksums
    f.onnx              embedding f:      points (B, N, 3)            -> embedding (B, D)
    g.onnx              retrieval g:      points (B, N, 3)            -> weights (B, K),
                                                                         means (B, K, D),
                                                                         sigmas (B, K, D)
    h_query.onnx        placement, query branch:  points (B, N, 3)    -> query_feature (B, Fq)
    h_part.onnx         placement, part branch:   points (B, N, 3)    -> part_feature (B, Fp)
    h_head.onnx         placement head:  query_feature (B, Fq),
                                         part_feature (B, Fp)         -> translation (B, 3)
                        (exports since 2026-12-05 fold the head's first layer into the branches,
                        so Fq = Fp = its width and h_head starts with their sum: the service
                        runs the graphs the same way either way)
    index.faiss         FAISS index over the catalog embeddings (row i = catalog part i)
    catalog.json        one record per catalog part (see ``CatalogPart`` fields below)
    catalog.npz         embeddings (P, D) float32, part_features (P, Fp) float32,
                        points (P, S, 3) float16 centred samples,
                        mesh_vertices (Vt, 3) float32 centred, mesh_faces (Ft, 3) int32 local,
                        vertex_first (P + 1,) int64, face_first (P + 1,) int64
    familiarity.npz     optional: descriptors (Q, P) float32, g's answers for training partial
                        assemblies (``service.suggest.familiarity``) in their principal subspace:
                        components (P, K * D + K) about mean (K * D + K,); the manifest's
                        "familiarity" entry holds the distance threshold calibrated on them

manifest.json's ``n_points`` (N) is the point count of f and g, of h too unless the manifest
gives h its own, ``placement_points`` (format 2: a reader of format 1 would give h N points).

Query points are in the canonical frame: y up, front +x, the complete object centred at its
bounding-box centre and scaled to unit radius. Part points are centred at the part's
bounding-box centre (same scale). A translation is the part's bounding-box centre.

A change of layout bumps ``FORMAT_VERSION``; readers refuse versions they do not know.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from service.artifacts.files import write_file_atomic

FORMAT_VERSION = 1
# Format 2 is format 1 with the manifest's optional ``placement_points``; a folder without it
# is still written as format 1, so every reader of format 1 keeps reading it.
PLACEMENT_POINTS_FORMAT = 2
SUPPORTED_FORMATS = (FORMAT_VERSION, PLACEMENT_POINTS_FORMAT)

MANIFEST = "manifest.json"
GRAPH_FILES = {
    "f": "f.onnx",
    "g": "g.onnx",
    "h_query": "h_query.onnx",
    "h_part": "h_part.onnx",
    "h_head": "h_head.onnx",
}
INDEX_FILE = "index.faiss"
CATALOG_JSON = "catalog.json"
CATALOG_ARRAYS = "catalog.npz"
# Optional (exports before it lack it): the bank of the familiarity check; see the docstring.
FAMILIARITY_FILE = "familiarity.npz"

# Input and output names of each graph, checked at load time against the ONNX files.
GRAPH_INPUTS = {
    "f": ["points"],
    "g": ["points"],
    "h_query": ["points"],
    "h_part": ["points"],
    "h_head": ["query_feature", "part_feature"],
}
GRAPH_OUTPUTS = {
    "f": ["embedding"],
    "g": ["weights", "means", "sigmas"],
    "h_query": ["query_feature"],
    "h_part": ["part_feature"],
    "h_head": ["translation"],
}
# Outputs a graph may add after its required ones (model v3): g's category probabilities over
# the manifest's "categories", h_head's per-axis log scale that fits a part to the query.
OPTIONAL_OUTPUTS = {"g": ["category_probs"], "h_head": ["log_scale"]}


def graph_outputs(graph: str, category_head: bool = False, scale_head: bool = False) -> list[str]:
    """The output names of one graph, with the optional heads it was exported with."""
    names = list(GRAPH_OUTPUTS[graph])
    if (graph == "g" and category_head) or (graph == "h_head" and scale_head):
        names += OPTIONAL_OUTPUTS[graph]
    return names

# The arrays of catalog.npz (shapes and dtypes in the docstring above); ``catalog_arrays`` names
# them for a writer, readers look for exactly these.
CATALOG_ARRAY_NAMES = ("embeddings", "part_features", "points", "mesh_vertices", "mesh_faces",
                       "vertex_first", "face_first")


def catalog_arrays(*, embeddings: np.ndarray, part_features: np.ndarray, points: np.ndarray,
                   mesh_vertices: np.ndarray, mesh_faces: np.ndarray, vertex_first: np.ndarray,
                   face_first: np.ndarray) -> dict[str, np.ndarray]:
    """The arrays of catalog.npz by their names (``CATALOG_ARRAY_NAMES``), as written and loaded."""
    return dict(zip(CATALOG_ARRAY_NAMES, (embeddings, part_features, points, mesh_vertices, mesh_faces,
                                          vertex_first, face_first), strict=True))


def format_part_id(shape_id: str, n: int) -> str:
    """A part's id: its source shape's id and the part's number in that shape ("chair-0007/2")."""
    return f"{shape_id}/{n}"


# Fields of one record in catalog.json.
CATALOG_FIELDS = (
    "part_id",        # str, stable id, e.g. "chair-0007/2"
    "shape_id",       # str, source shape
    "category",       # str
    "style",          # str | None, fine-grained style of the source shape (may be unknown)
    "label",          # str | None, majority semantic label (may be unknown)
    "translation",    # [x, y, z], bounding-box centre in the source shape's frame
    "bbox_min",       # [x, y, z], centred bounding box
    "bbox_max",       # [x, y, z]
    "area",           # float, surface area
    "split",          # "train" | "test", the split of the source shape
    "duplicate_of",   # int | None, index of the part this one is a near-duplicate of
)


class ArtifactError(RuntimeError):
    """An artifact folder is missing a file, has a bad checksum or an unknown format."""


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def write_json_atomic(path: Path, obj: Any) -> None:
    """Write JSON so that readers never see half a file (``files.write_file_atomic``)."""
    write_file_atomic(Path(path), (json.dumps(obj, indent=1, sort_keys=True) + "\n").encode())


def write_manifest(folder: Path, manifest: dict[str, Any]) -> dict[str, Any]:
    """Complete ``manifest`` with the format version and the checksum of every file, then write it."""
    folder = Path(folder)
    files = [*GRAPH_FILES.values(), INDEX_FILE, CATALOG_JSON, CATALOG_ARRAYS]
    if (folder / FAMILIARITY_FILE).is_file():
        files.append(FAMILIARITY_FILE)
    checksums = {}
    for name in files:
        p = folder / name
        if not p.is_file():
            raise ArtifactError(f"cannot write manifest: {p} is missing")
        checksums[name] = sha256_file(p)
    # Dynamo exports may write weights beside the graph; they must ship and be checked too.
    for extra in sorted(folder.glob("*.onnx.data")):
        checksums[extra.name] = sha256_file(extra)
    full = dict(manifest)
    full["format_version"] = PLACEMENT_POINTS_FORMAT if "placement_points" in manifest else FORMAT_VERSION
    full["files"] = checksums
    write_json_atomic(folder / MANIFEST, full)
    return full


def read_manifest(folder: Path, verify_checksums: bool = True) -> dict[str, Any]:
    """Read and check ``manifest.json``; raise ``ArtifactError`` naming the bad file."""
    folder = Path(folder)
    path = folder / MANIFEST
    if not path.is_file():
        raise ArtifactError(f"artifact manifest not found: {path}")
    try:
        manifest = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ArtifactError(f"{path}: not valid JSON ({exc})") from exc
    version = manifest.get("format_version")
    if version not in SUPPORTED_FORMATS:
        raise ArtifactError(f"{path}: format_version {version!r} is not supported "
                            f"(expected one of {', '.join(map(str, SUPPORTED_FORMATS))})")
    if "placement_points" in manifest and version != PLACEMENT_POINTS_FORMAT:
        raise ArtifactError(f"{path}: placement_points needs format_version {PLACEMENT_POINTS_FORMAT}, "
                            f"found {version!r}")
    for key in ("model_version", "n_points", "embedding_dim", "n_modes", "part_count", "files"):
        if key not in manifest:
            raise ArtifactError(f"{path}: required key {key!r} missing")
    if verify_checksums:
        for name, digest in manifest["files"].items():
            p = folder / name
            if not p.is_file():
                raise ArtifactError(f"artifact file missing: {p}")
            if sha256_file(p) != digest:
                raise ArtifactError(f"artifact file {p} does not match its checksum in {path}")
    return manifest
