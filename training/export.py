"""Export a trained run as the artifact folder the service loads (layout: ``service.artifacts.layout``).

Writes the five ONNX graphs (f, g, h_query, h_part, h_head; one file each, dynamic batch and
point axes), then computes the catalog with the *exported* graphs run in onnxruntime (so the
shipped embeddings and placement features are exactly what the shipped graphs produce), the
FAISS index over the embeddings, ``catalog.json`` / ``catalog.npz`` and finally the manifest.

Files are written into a temporary folder beside the destination and moved in one by one, the
manifest last, so a reader never pairs a new graph with an old manifest's checksums (it refuses
the folder instead until the manifest lands).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import warnings
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import faiss
import numpy as np
import onnx
import onnxruntime as ort
import torch
from torch import nn

from service.artifacts.catalog import load_catalog, partial_assemblies, partial_assembly_bank
from service.artifacts.files import write_file_atomic
from service.artifacts.indexing import IndexKind, build_index, index_entry
from service.artifacts.layout import (
    CATALOG_ARRAYS,
    CATALOG_JSON,
    FAMILIARITY_FILE,
    GRAPH_FILES,
    GRAPH_INPUTS,
    INDEX_FILE,
    MANIFEST,
    catalog_arrays,
    graph_outputs,
    read_manifest,
    write_manifest,
)
from service.artifacts.loading import build_session
from service.suggest.familiarity import Projection, calibrate_threshold, mixture_descriptor
from training.catalog import concat_meshes, find_duplicates, part_records, sample_parts
from training.checkpoint import Trained, load_trained, load_trained_config, summary_of
from training.config import config_to_dict
from training.data.processed import ProcessedDataset, save_npz_deterministic
from training.models import PlacementNet, RetrievalPair
from training.split import load_split

log = logging.getLogger(__name__)


@dataclass
class ExportOptions:
    """Settings of an export (every limit is a setting)."""

    # Points the service samples per query or part (manifest n_points); None = the training N.
    n_points: int | None = None
    # Points h takes of a query and of a part (manifest placement_points); None = n_points. h
    # places more precisely on more points than f and g need (docs/training.md, "h on 512 points").
    placement_points: int | None = None
    # Points stored per catalog part (float16) for the service's previews and checks.
    catalog_points: int = 256
    # Seed of the catalog's point samples.
    seed: int = 0
    # Near-duplicates: embedding distance below this radius AND Chamfer distance of the cached
    # samples below factor * sqrt(area / samples) (the noise is about 0.5).
    duplicate_embedding_radius: float = 0.05
    duplicate_chamfer_factor: float = 0.65
    # ... AND area and bounding-box extents equal within this relative tolerance.
    duplicate_size_tolerance: float = 0.02
    # The whole folder must stay under this size (the repository ships it).
    max_megabytes: float = 35.0
    # Storage of the catalog arrays (the service reads any float kind and casts to float32):
    # float16 placement features and mesh vertices cut about 3 MB from a 7000-part catalog; the
    # error (about 5e-4 relative) is far below what placement or display can show.
    feature_dtype: str = "float16"
    vertex_dtype: str = "float16"
    # The FAISS index: exact (flat) for catalogs of at most index_flat_max parts; above, "auto"
    # builds IVF-Flat ("ivf" or "hnsw" force a kind) whose search breadth is raised until
    # recall@index_recall_k against exact search reaches index_target_recall (docs/performance.md).
    index_flat_max: int = 50_000
    index_kind: IndexKind = "auto"
    index_target_recall: float = 0.95
    index_recall_k: int = 64
    # The approximate index is tuned on g's mixture means of this many training shapes with one
    # part left out (the queries it will serve), not on jittered embeddings (service.artifacts.indexing).
    index_tuning_shapes: int = 128
    # The familiarity check's bank (service.suggest.familiarity): g's answers for this many partial
    # assemblies of every training shape, and the quantile of their nearest-other-shape distances
    # that becomes the threshold (0.99: 1 in 100 new shapes of a known kind is called unfamiliar).
    familiarity_per_shape: int = 3
    familiarity_quantile: float = 0.99
    # Principal components the bank is kept in (64 of 408 hold 99% of its variance; at full width
    # it cost 0.8 ms per request streaming from memory).
    familiarity_components: int = 64
    opset: int = 17
    # Parts per onnxruntime call when encoding the catalog.
    chunk: int = 256


def options_of(manifest: dict[str, Any]) -> ExportOptions:
    """The settings an export's manifest records, so that exporting its networks again (with a new
    catalog or a refitted head) serves them the same way."""
    n_points = int(manifest["n_points"])
    dups = manifest.get("duplicates", {})
    fam = manifest.get("familiarity") or {}
    defaults = ExportOptions()
    return ExportOptions(
        n_points=n_points, placement_points=int(manifest.get("placement_points", n_points)),
        catalog_points=int(manifest.get("catalog_points", defaults.catalog_points)),
        seed=int(fam.get("seed", defaults.seed)),
        duplicate_embedding_radius=float(dups.get("embedding_radius", defaults.duplicate_embedding_radius)),
        duplicate_chamfer_factor=float(dups.get("chamfer_factor", defaults.duplicate_chamfer_factor)),
        duplicate_size_tolerance=float(dups.get("size_tolerance", defaults.duplicate_size_tolerance)),
        familiarity_per_shape=int(fam.get("per_shape", defaults.familiarity_per_shape)),
        familiarity_quantile=float(fam.get("quantile", defaults.familiarity_quantile)),
        familiarity_components=int(fam.get("components", defaults.familiarity_components)))


def output_names(graph: str, module: nn.Module) -> list[str]:
    """The graph's output names, with the optional heads its module has (service.artifacts.layout)."""
    return graph_outputs(graph, category_head=getattr(module, "category_head", None) is not None,
                         scale_head=bool(getattr(module, "predict_scale", False)))


def _dynamic_axes(graph: str, outputs: list[str]) -> dict[str, dict[int, str]]:
    axes: dict[str, dict[int, str]] = {}
    for name in GRAPH_INPUTS[graph]:
        axes[name] = {0: "batch", 1: "n_points"} if name == "points" else {0: "batch"}
    for name in outputs:
        axes[name] = {0: "batch"}
    return axes


def graph_modules(pair: RetrievalPair, placement: PlacementNet) -> dict[str, nn.Module]:
    """The torch module behind each exported graph (in the order of ``GRAPH_FILES``)."""
    return {"f": pair.f, "g": pair.g, **placement.exported_modules()}


def example_inputs(graph: str, placement: PlacementNet, batch: int = 2, n: int = 64,
                   seed: int = 0) -> tuple[torch.Tensor, ...]:
    """Random inputs of the right shapes for one graph (used for tracing and parity tests)."""
    gen = torch.Generator().manual_seed(seed)
    if graph == "h_head":
        return (torch.randn(batch, placement.query_dim, generator=gen),
                torch.randn(batch, placement.part_dim, generator=gen))
    return (torch.rand(batch, n, 3, generator=gen) - 0.5,)


def export_graph(module: nn.Module, graph: str, inputs: tuple[torch.Tensor, ...], path: Path,
                 opset: int = 17) -> None:
    """Write one graph as a single ONNX file (legacy exporter) and check it with onnx.checker."""
    module.eval()
    outputs = output_names(graph, module)
    with warnings.catch_warnings():
        # The legacy exporter is deprecated, but it is the one that writes a single file per graph.
        warnings.simplefilter("ignore", DeprecationWarning)
        torch.onnx.export(module, inputs, str(path), dynamo=False, opset_version=opset,
                          input_names=GRAPH_INPUTS[graph], output_names=outputs,
                          dynamic_axes=_dynamic_axes(graph, outputs))
    onnx.checker.check_model(onnx.load(str(path)))


def export_graphs(pair: RetrievalPair, placement: PlacementNet, folder: Path, opset: int = 17) -> None:
    """Write f.onnx, g.onnx, h_query.onnx, h_part.onnx and h_head.onnx into ``folder``."""
    pair.eval()
    placement.eval()
    with torch.no_grad():
        for graph, module in graph_modules(pair, placement).items():
            export_graph(module, graph, example_inputs(graph, placement), Path(folder) / GRAPH_FILES[graph],
                         opset)


def run_chunked(session: ort.InferenceSession, points: np.ndarray, chunk: int) -> np.ndarray:
    """Run a single-input graph over ``points`` in chunks; returns the first output, concatenated.

    Shapes:
        points (P, N, 3) -> (P, ...).
    """
    name = session.get_inputs()[0].name
    outs = [session.run(None, {name: np.ascontiguousarray(points[s:s + chunk], np.float32)})[0]
            for s in range(0, len(points), chunk)]
    return np.concatenate(outs)


def tuning_means(folder: Path, part_count: int, dim: int, n_points: int, opts: ExportOptions
                 ) -> np.ndarray | None:
    """g's mixture means of training shapes with one part left out, from the folder just written.

    None when the catalog has no multi-part shape (the index then tunes on jittered embeddings).

    Shapes:
        returns (shapes * K, D) float32.
    """
    catalog = load_catalog(folder / CATALOG_JSON, folder / CATALOG_ARRAYS, part_count, dim)
    clouds = partial_assemblies(catalog, opts.index_tuning_shapes, n_points, opts.seed, split="train")
    if not clouds:
        return None
    session = build_session(folder / GRAPH_FILES["g"], torch.get_num_threads())
    means = session.run(["means"], {GRAPH_INPUTS["g"][0]: np.stack(clouds)})[0]
    return np.ascontiguousarray(means.reshape(-1, means.shape[-1]), dtype=np.float32)


def write_familiarity(folder: Path, n_points: int, part_count: int, dim: int, opts: ExportOptions
                      ) -> dict[str, Any]:
    """The familiarity bank of the folder just written (``FAMILIARITY_FILE``); its manifest entry.

    g's descriptors (``mixture_descriptor``) of ``familiarity_per_shape`` partial assemblies of
    every training shape of the folder's catalog, run through the folder's own g.onnx, kept in
    their first ``familiarity_components`` principal components (``Projection``); the threshold
    is calibrated on the stored (projected) values, as the service reads them.
    """
    catalog = load_catalog(folder / CATALOG_JSON, folder / CATALOG_ARRAYS, part_count, dim)
    clouds, groups = partial_assembly_bank(catalog, opts.familiarity_per_shape, n_points, opts.seed,
                                           split="train")
    session = build_session(folder / GRAPH_FILES["g"], torch.get_num_threads())
    descriptors = []
    for start in range(0, len(clouds), opts.chunk):
        weights, means = session.run(["weights", "means"],
                                     {GRAPH_INPUTS["g"][0]: np.stack(clouds[start:start + opts.chunk])})
        descriptors.append(mixture_descriptor(weights, means))
    full = np.concatenate(descriptors)
    if not np.isfinite(full).all():
        raise ValueError(f"{folder / GRAPH_FILES['g']}: g's answers are not finite; cannot store the "
                         "familiarity bank")
    projection = Projection.fit(full, opts.familiarity_components)
    stored = projection(full).astype(np.float32)
    threshold = calibrate_threshold(stored, groups, opts.familiarity_quantile)
    save_npz_deterministic(folder / FAMILIARITY_FILE, {
        "descriptors": stored, "mean": projection.mean, "components": projection.components})
    log.info("familiarity bank: %d descriptors of %d training shapes, threshold %.3f (quantile %g)",
             len(stored), len(np.unique(groups)), threshold, opts.familiarity_quantile)
    return {"threshold": round(threshold, 6), "quantile": opts.familiarity_quantile, "queries": len(stored),
            "per_shape": opts.familiarity_per_shape, "components": int(stored.shape[1]), "seed": opts.seed}


def add_familiarity(folder: Path, opts: ExportOptions) -> dict[str, Any]:
    """Write the familiarity bank into an exported folder and its manifest (nothing else changes)."""
    folder = Path(folder)
    manifest = read_manifest(folder)
    part_count, dim = int(manifest["part_count"]), int(manifest["embedding_dim"])
    manifest["familiarity"] = write_familiarity(folder, int(manifest["n_points"]), part_count, dim, opts)
    manifest.pop("files", None)
    manifest.pop("format_version", None)
    return write_manifest(folder, manifest)


def _round_floats(obj: Any, digits: int = 6) -> Any:
    if isinstance(obj, float):
        return float(f"{obj:.{digits}g}")
    if isinstance(obj, list):
        return [_round_floats(v, digits) for v in obj]
    if isinstance(obj, dict):
        return {k: _round_floats(v, digits) for k, v in obj.items()}
    return obj


def write_catalog_json(path: Path, records: list[dict[str, Any]]) -> None:
    """catalog.json, compact: one record per line, floats to 6 significant digits (about half the size)."""
    lines = [json.dumps(_round_floats(rec), separators=(",", ":"), sort_keys=True) for rec in records]
    write_file_atomic(Path(path), ("[\n" + ",\n".join(lines) + ("\n" if lines else "") + "]\n").encode())


def folder_megabytes(folder: Path) -> dict[str, float]:
    return {p.name: p.stat().st_size / 1e6 for p in sorted(Path(folder).iterdir()) if p.is_file()}


def _models_hash(folder: Path) -> str:
    h = hashlib.sha256()
    for name in GRAPH_FILES.values():
        h.update((Path(folder) / name).read_bytes())
    return h.hexdigest()[:10]


def export_run(run_dir: Path, out_dir: Path, data: Path | None = None,
               options: ExportOptions | None = None, networks: tuple[Trained, str] | None = None
               ) -> dict[str, Any]:
    """Export the run in ``run_dir`` to ``out_dir``; returns the manifest written.

    ``data`` overrides the processed dataset folder stored in the run's config (the catalog is
    every component of that dataset; the run's ``split.json`` must match it). ``networks``
    (trained networks and their name, e.g. ``training.from_onnx.trained_from_artifacts``) are
    exported instead of the run's checkpoint: the run then gives only the split and dataset (only
    its ``split.json`` when ``data`` is given).
    """
    opts = options or ExportOptions()
    run_dir, out_dir = Path(run_dir), Path(out_dir)
    if networks is None:
        trained = load_trained(run_dir)
        name = f"{run_dir.name}-s{int(trained.state['step'])}"
    else:
        trained, name = networks
    cfg = trained.config
    if data is not None:
        data_dir = Path(data)
    else:  # networks from elsewhere: the run's own config names its dataset
        data_dir = Path((load_trained_config(run_dir) if networks is not None else cfg).data)
    ds = ProcessedDataset.load(data_dir)
    split = load_split(run_dir, ds)
    n_points = opts.n_points or cfg.n_points

    out_dir.mkdir(parents=True, exist_ok=True)
    tmp = out_dir.parent / f".{out_dir.name}.export-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        manifest = _write_artifacts(trained, ds, split.split_of_shape(ds.n_shapes), tmp, n_points, opts,
                                    data_dir, run_dir, name)
        sizes = folder_megabytes(tmp)
        total = sum(sizes.values())
        if total > opts.max_megabytes:
            detail = ", ".join(f"{k} {v:.2f} MB" for k, v in sizes.items())
            raise ValueError(f"export of {run_dir} would take {total:.1f} MB, over the limit of "
                             f"{opts.max_megabytes} MB ({detail})")
        for stale in out_dir.glob("*.onnx.data"):
            stale.unlink()
        for p in sorted(tmp.iterdir()):
            if p.name != MANIFEST:
                os.replace(p, out_dir / p.name)
        os.replace(tmp / MANIFEST, out_dir / MANIFEST)
        log.info("exported %s to %s: %d parts, %.2f MB (%s)", run_dir, out_dir, manifest["part_count"], total,
                 ", ".join(f"{k} {v:.2f}" for k, v in sizes.items()))
        return manifest
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _write_artifacts(trained: Trained, ds: ProcessedDataset, split_of_shape: list[str], folder: Path,
                     n_points: int, opts: ExportOptions, data_dir: Path, run_dir: Path, name: str
                     ) -> dict[str, Any]:
    cfg = trained.config
    export_graphs(trained.pair, trained.placement, folder, opts.opset)
    f_sess = build_session(folder / GRAPH_FILES["f"], torch.get_num_threads())
    part_sess = build_session(folder / GRAPH_FILES["h_part"], torch.get_num_threads())

    # Embeddings and placement features from the shipped graphs, on n_points samples per part.
    parts = sample_parts(ds, n_points, opts.seed)
    embeddings = run_chunked(f_sess, parts, opts.chunk).astype(np.float32)
    placement_points = opts.placement_points or n_points
    if placement_points != n_points:
        parts = sample_parts(ds, placement_points, opts.seed)
    part_features = run_chunked(part_sess, parts, opts.chunk).astype(np.float32)
    preview = sample_parts(ds, opts.catalog_points, opts.seed + 1).astype(np.float16)

    records = part_records(ds, split_of_shape)
    extents = np.array([np.subtract(r["bbox_max"], r["bbox_min"]) for r in records]).reshape(-1, 3)
    duplicates = find_duplicates(embeddings, ds.points, ds.area, extents, opts.duplicate_embedding_radius,
                                 opts.duplicate_chamfer_factor, opts.duplicate_size_tolerance)
    for rec, dup in zip(records, duplicates, strict=True):
        rec["duplicate_of"] = dup
    write_catalog_json(folder / CATALOG_JSON, records)
    meshes = concat_meshes(ds)
    meshes["mesh_vertices"] = meshes["mesh_vertices"].astype(opts.vertex_dtype)
    # Faces index their own part's vertices: 16 bits suffice unless a part has 65536 vertices.
    block_sizes = np.diff(meshes["vertex_first"])
    if len(block_sizes) and block_sizes.max() <= np.iinfo(np.uint16).max + 1:
        meshes["mesh_faces"] = meshes["mesh_faces"].astype(np.uint16)
    # The meshes compress far better with LZMA (faces 2.57 -> 0.19 MB, vertices 3.78 -> 2.29 MB
    # for the shipped catalog) for about 0.1 s more at load; the other arrays gain little from it
    # and the points would cost 0.5 s (h's projected part features, dense since the head was
    # split, take 3.9 MB where the raw ones took 2.2).
    save_npz_deterministic(folder / CATALOG_ARRAYS, catalog_arrays(
        embeddings=embeddings, part_features=part_features.astype(opts.feature_dtype), points=preview,
        **meshes), lzma=("mesh_faces", "mesh_vertices"))

    # Exact (flat) up to index_flat_max parts; above, IVF tuned to the recall target on g's means
    # of training queries, its parameters recorded in the manifest (service.artifacts.indexing).
    approximate = opts.index_kind in ("ivf", "hnsw") or (opts.index_kind == "auto"
                                                         and len(records) > opts.index_flat_max)
    tuning = (tuning_means(folder, len(records), cfg.model.embedding_dim, n_points, opts) if approximate
              else None)
    index, index_params = build_index(embeddings, flat_max=opts.index_flat_max, kind=opts.index_kind,
                                      target_recall=opts.index_target_recall, recall_k=opts.index_recall_k,
                                      queries=tuning, seed=opts.seed)
    faiss.write_index(index, str(folder / INDEX_FILE))
    familiarity = write_familiarity(folder, n_points, len(records), cfg.model.embedding_dim, opts)

    state = trained.state
    summary = summary_of(run_dir)
    n_dups = sum(d is not None for d in duplicates)
    manifest = {
        "model_version": f"{name}-{_models_hash(folder)}",
        "n_points": int(n_points),
        # Written only when h takes its own count (the loader reads N without it).
        **({"placement_points": int(placement_points)} if placement_points != n_points else {}),
        "embedding_dim": cfg.model.embedding_dim,
        "n_modes": cfg.model.n_modes,
        "part_count": len(records),
        "query_feature_dim": trained.placement.query_dim,
        "part_feature_dim": trained.placement.part_dim,
        "catalog_points": opts.catalog_points,
        "index": index_entry(index_params),
        "familiarity": familiarity,
        "model_config": config_to_dict(cfg.model),
        # The classes of g's category_probs output, in order (ProcessedDataset.categories).
        **({"categories": ds.categories()} if cfg.model.n_categories else {}),
        "dataset": {"seed": ds.info.get("seed"), "hash": ds.info.get("hash") or ds.content_hash(),
                    "path": str(data_dir), "shapes": ds.n_shapes},
        "split": {"train_shapes": split_of_shape.count("train"), "test_shapes": split_of_shape.count("test")},
        "duplicates": {"count": n_dups, "embedding_radius": opts.duplicate_embedding_radius,
                       "chamfer_factor": opts.duplicate_chamfer_factor,
                       "size_tolerance": opts.duplicate_size_tolerance},
        "training": {
            "steps": int(state["step"]),
            "wall_minutes": float(state.get("elapsed_seconds", 0.0)) / 60,
            # Networks read back from an export keep their own record (the run gives only the split).
            "final_losses": state.get("final_losses", summary.get("final_losses", {})),
            "validation": dict(state.get("validation", {})),
            "n_points": cfg.n_points,
            "batch_size": cfg.batch_size,
            "seed": cfg.seed,
            # A fine-tuned run (train --init-from) names the model it started from.
            **({"started_from": state["started_from"]} if state.get("started_from") else {}),
            # g's category head refitted on outside collections (training.category_head).
            **({"category_head": state["category_head"]} if state.get("category_head") else {}),
        },
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    return write_manifest(folder, manifest)
