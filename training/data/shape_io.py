"""Write a RawShape to disk: ``<shape_id>.glb`` (one scene node per piece) plus its sidecar.

The GLB is an ordinary glTF 2.0 binary any 3D tool opens; pieces that share a geometry key and
are rigid copies of one another (four legs, five spokes, wheels) are written as one glTF mesh
referenced by several nodes, the way 3D Warehouse scene graphs instance repeated parts. The
sidecar JSON (see ``training/data/shapes.py``) keeps category, style, labels and geometry keys.
Output is byte-identical for identical input, so seeded datasets reproduce exactly.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import trimesh

from training.data.shapes import SIDECAR_SUFFIX, RawPiece, RawShape

# An outside collection's attribution list (``data sweethome3d``, ``data flightgear``): one entry
# per file written, naming where it came from.
SOURCES_FILE = "sources.json"

# Max vertex error (shape units, radius 1) for a piece to be written as an instance of another.
INSTANCE_TOLERANCE = 1e-6


def _rigid_fit(local: np.ndarray, target: np.ndarray) -> np.ndarray | None:
    """The proper rigid 4x4 transform taking ``local`` onto ``target`` (same vertex order), or None.

    Kabsch/Procrustes on corresponding vertices; reflections are refused because a mirrored
    instance would flip the winding of the faces for glTF readers that do not correct it.

    Shapes:
        local, target: (V, 3) float64.
    """
    if local.shape != target.shape:
        return None
    cl, ct = local.mean(axis=0), target.mean(axis=0)
    u, _, vt = np.linalg.svd((local - cl).T @ (target - ct))
    rot = (u @ vt).T
    if np.linalg.det(rot) < 0:
        return None
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = ct - rot @ cl
    if np.abs(local @ rot.T + m[:3, 3] - target).max() > INSTANCE_TOLERANCE:
        return None
    return m


def _scene(pieces: list[RawPiece]) -> trimesh.Scene:
    scene = trimesh.Scene()
    # First piece of each key (in piece order) defines the shared geometry, centred locally.
    shared: dict[str, tuple[np.ndarray, np.ndarray, str]] = {}
    extra = 0
    for piece in pieces:
        if not piece.name or piece.name in scene.graph.nodes:
            raise ValueError(f"piece names must be unique and non-empty, got {piece.name!r}")
        ref = shared.get(piece.geometry_key)
        transform = None
        if ref is not None and np.array_equal(ref[1], piece.faces):
            transform = _rigid_fit(ref[0], piece.vertices)
        if transform is not None and ref is not None:
            scene.graph.update(
                frame_to=piece.name, frame_from=scene.graph.base_frame, matrix=transform, geometry=ref[2]
            )
            continue
        lo, hi = piece.vertices.min(axis=0), piece.vertices.max(axis=0)
        centre = 0.5 * (lo + hi)
        local = piece.vertices - centre
        geom_name = piece.geometry_key
        if ref is not None or geom_name in scene.geometry:
            # Same key but not a rigid copy: its own glTF mesh; the sidecar still groups it.
            extra += 1
            geom_name = f"{piece.geometry_key}.{extra}"
        else:
            shared[piece.geometry_key] = (local, piece.faces, geom_name)
        mesh = trimesh.Trimesh(local, piece.faces, process=False)
        scene.add_geometry(
            mesh,
            node_name=piece.name,
            geom_name=geom_name,
            transform=trimesh.transformations.translation_matrix(centre),
        )
    return scene


def sidecar(shape: RawShape) -> dict:
    """The sidecar metadata of a shape (labels only for labelled pieces)."""
    return {
        "shape_id": shape.shape_id,
        "category": shape.category,
        "style": shape.style,
        "labels": {p.name: p.label for p in shape.pieces if p.label is not None},
        "geometry_keys": {p.name: p.geometry_key for p in shape.pieces},
    }


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def save_shape(shape: RawShape, folder: Path) -> Path:
    """Write ``<folder>/<shape_id>.glb`` and ``<folder>/<shape_id>.json``; returns the GLB path.

    Raises:
        ValueError: the shape has no pieces, or piece names are not unique.
    """
    if not shape.pieces:
        raise ValueError(f"shape {shape.shape_id!r} has no pieces to write")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    glb = folder / f"{shape.shape_id}.glb"
    data = _scene(shape.pieces).export(file_type="glb", include_normals=False)
    _write_atomic(glb, data)
    meta = json.dumps(sidecar(shape), sort_keys=True, indent=1) + "\n"
    _write_atomic(folder / f"{shape.shape_id}{SIDECAR_SUFFIX}", meta.encode())
    return glb


def write_sources(out: Path, sources: list[dict]) -> Path:
    """Write an outside collection's ``SOURCES_FILE`` into ``out``; returns its path."""
    path = out / SOURCES_FILE
    path.write_text(json.dumps(sources, indent=1) + "\n")
    return path
