"""The paper's database protocol: each shape's components of one label grouped into one part.

Section 6.2 of the paper "group[s] all components with the same label into a single part" and
uses the grouped parts both to make the query shapes and as the component database of that
experiment. ``complementme evaluate`` by default removes a label's components from a query but
ranks the catalog's single components (the service's catalog); ``--database grouped`` measures
the shipped networks under the paper's protocol instead: the same shapes with their components
grouped by label (``group_by_label``), a catalog of those parts exported with the shipped
networks (``grouped_catalog``), and the same tables over it.

Labels are read here to measure only: a grouped dataset is marked (``ProcessedDataset.
grouped_by_label``) and training refuses it.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import numpy as np

from service.artifacts.layout import MANIFEST, write_json_atomic
from training.data.processed import GROUPED_KEY, ProcessedDataset

log = logging.getLogger(__name__)



def _groups(labels: list[str | None]) -> list[list[int]]:
    """Local component indices per group, in order of each group's first component; a component
    without a label is a group of its own."""
    first: dict[str, int] = {}
    groups: list[list[int]] = []
    for i, label in enumerate(labels):
        if label is None:
            groups.append([i])
        elif label in first:
            groups[first[label]].append(i)
        else:
            first[label] = len(groups)
            groups.append([i])
    return groups


def _take_by_area(areas: np.ndarray, total: int) -> np.ndarray:
    """How many of ``total`` samples each member gets: proportional to its area, largest
    remainders first (the members' cached samples are area-weighted, so the union's are too).

    Shapes:
        areas (M,) -> (M,) int64 summing to ``total``.
    """
    share = areas / areas.sum() * total if areas.sum() > 0 else np.full(len(areas), total / len(areas))
    counts = np.floor(share).astype(np.int64)
    order = np.argsort(-(share - counts), kind="stable")
    counts[order[: total - int(counts.sum())]] += 1
    return counts


def group_by_label(ds: ProcessedDataset, seed: int = 0) -> ProcessedDataset:
    """``ds`` with each shape's components of one label merged into one component.

    A group's mesh is its members' meshes placed in the shape and centred at their joint
    bounding-box centre (the group's translation), its area the members' sum, its cached samples
    ``P`` drawn from the members' samples in proportion to their areas (seeded), and it touches
    another group when any of their members touched. Shapes keep their order, ids, categories
    and styles; ``labels`` hold one label per group.

    Shapes:
        ds.points (C, P, 3) float16 -> points (G, P, 3) float16, G <= C groups.
    """
    rng = np.random.default_rng(seed)
    P = ds.points.shape[1]
    points: list[np.ndarray] = []
    translation: list[np.ndarray] = []
    area: list[np.floating[Any]] = []
    shape_of: list[int] = []
    vblocks: list[np.ndarray] = []
    fblocks: list[np.ndarray] = []
    shapes: list[dict[str, Any]] = []
    group_of = np.empty(ds.n_components, np.int64)
    first = [0]
    for s, meta in enumerate(ds.shapes):
        base = int(ds.first_comp[s])
        groups = _groups(list(meta["labels"]))
        for members in groups:
            comps = [base + i for i in members]
            group_of[comps] = len(translation)
            shape_of.append(s)
            if len(comps) == 1:  # a label of one component: that component, as it was
                c = comps[0]
                points.append(ds.points[c])
                translation.append(ds.translation[c])
                area.append(ds.area[c])
                vertices, faces = ds.component_mesh(c)
                vblocks.append(vertices)
                fblocks.append(faces)
                continue
            placed = [ds.component_mesh(c)[0].astype(np.float64) + ds.translation[c] for c in comps]
            every = np.concatenate(placed)
            centre = (every.min(axis=0) + every.max(axis=0)) / 2
            counts = _take_by_area(ds.area[comps].astype(np.float64), P)
            samples = [ds.points[c][np.sort(rng.choice(P, int(k), replace=False))].astype(np.float64)
                       + ds.translation[c] for c, k in zip(comps, counts, strict=True) if k > 0]
            points.append((np.concatenate(samples) - centre).astype(np.float16))
            translation.append(centre.astype(np.float32))
            area.append(np.float32(ds.area[comps].sum()))
            vblocks.append(np.concatenate([v - centre for v in placed]).astype(np.float32))
            offsets = np.cumsum([0] + [len(v) for v in placed[:-1]])
            fblocks.append(np.concatenate([ds.component_mesh(c)[1] + o for c, o in zip(comps, offsets,
                                                                                       strict=True)]))
        first.append(first[-1] + len(groups))
        shapes.append({**meta, "labels": [meta["labels"][g[0]] for g in groups]})
    pairs = np.sort(group_of[ds.edges.astype(np.int64)].reshape(-1, 2), axis=1)
    edges = np.unique(pairs[pairs[:, 0] != pairs[:, 1]], axis=0).astype(np.int32).reshape(-1, 2)
    vfirst = np.concatenate([[0], np.cumsum([len(v) for v in vblocks])]).astype(np.int64)
    ffirst = np.concatenate([[0], np.cumsum([len(f) for f in fblocks])]).astype(np.int64)
    info: dict[str, Any] = {k: v for k, v in ds.info.items() if k != "hash"}
    info.update({GROUPED_KEY: True, "grouped_from": ds.content_hash(), "grouped_seed": seed})
    return ProcessedDataset(
        points=np.stack(points), translation=np.stack(translation), area=np.asarray(area, np.float32),
        shape_of=np.asarray(shape_of, np.int32), first_comp=np.asarray(first, np.int64), edges=edges,
        mesh_vertices=np.concatenate(vblocks), mesh_faces=np.concatenate(fblocks).astype(np.int32),
        vertex_first=vfirst, face_first=ffirst, shapes=shapes, info=info)


def grouped_catalog(artifacts: Path, data: Path, cache: Path, seed: int = 0) -> tuple[Path, Path, Path]:
    """The grouped dataset of ``data``, a run folder holding the artifacts' split, and the
    artifacts' networks exported over the grouped parts, made under ``cache`` (``<run>/grouped``
    of ``complementme evaluate``; reused while the artifacts' model and the grouped dataset are
    the same); returns (artifact folder, dataset, run: the fixed-embedding baseline caches there).

    The split is the artifacts' own (their catalog's ``split`` per shape), so the held-out
    shapes are those of the components benchmark.
    """
    from training.checkpoint import CONFIG_FILE
    from training.config import config_to_dict
    from training.export import ExportOptions, export_run
    from training.from_onnx import trained_from_artifacts
    from training.split import Split, save_split

    manifest = json.loads((Path(artifacts) / MANIFEST).read_text())
    ds = ProcessedDataset.load(data)
    if ds.grouped_by_label:
        raise ValueError(f"--database grouped: {data} is grouped already; give the dataset it was "
                         "grouped from")
    log.info("grouped catalog: grouping %d components of %d shapes by label", ds.n_components, ds.n_shapes)
    grouped = group_by_label(ds, seed)
    # Keyed by the grouped data itself (about a second to make), not by its source: a catalog that
    # other grouping code made from the same source is never reused. (docs/benchmark-grouped was
    # once rendered from such a cache, made before the grouping was committed in its final form.)
    key = f"{manifest['model_version']}-{grouped.content_hash()[:10]}"
    folder = Path(cache) / key
    out_data, out_run, out_artifacts = folder / "data", folder / "run", folder / "exported"
    if (out_artifacts / MANIFEST).is_file():
        log.info("grouped catalog: reusing %s", folder)
        return out_artifacts, out_data, out_run
    grouped.save(out_data)
    split_of = _artifact_splits(artifacts)
    missing = [m["shape_id"] for m in grouped.shapes if m["shape_id"] not in split_of]
    if missing:
        raise ValueError(f"{data}: {len(missing)} shapes (e.g. {missing[0]!r}) are not in the catalog of "
                         f"{artifacts}: the dataset is not the one the artifacts were exported from")
    ids = [m["shape_id"] for m in grouped.shapes]
    train = np.array([i for i, sid in enumerate(ids) if split_of[sid] == "train"], np.int64)
    test = np.array([i for i, sid in enumerate(ids) if split_of[sid] == "test"], np.int64)
    networks = trained_from_artifacts(artifacts)
    out_run.mkdir(parents=True, exist_ok=True)
    save_split(Split(train=train, test=test, seed=networks[0].config.seed,
                     test_fraction=len(test) / max(len(ids), 1), dataset_hash=grouped.content_hash()),
               grouped, out_run)
    write_json_atomic(out_run / CONFIG_FILE, config_to_dict(networks[0].config))
    placement = manifest.get("placement_points", manifest["n_points"])
    export_run(out_run, out_artifacts, data=out_data, networks=networks,
               options=ExportOptions(n_points=int(manifest["n_points"]), placement_points=int(placement),
                                     seed=seed, max_megabytes=1e9))
    return out_artifacts, out_data, out_run


def _artifact_splits(artifacts: Path) -> dict[str, str]:
    """``split`` of each source shape in the artifacts' catalog."""
    from service.artifacts.loading import load_artifacts

    catalog = load_artifacts(Path(artifacts)).catalog
    return {str(r["shape_id"]): str(r.get("split", "")) for r in catalog.records}
