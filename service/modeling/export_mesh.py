"""An assembly of catalog parts as one mesh file (GLB or OBJ), for download.

Each item is a catalog part, the translation of its bounding-box centre and a uniform scale
about that centre. Placed in the caller's frame like every answer of the API:

    placed vertex = radius * R^T (scale * v) + translation

with ``v`` the part's centred catalog vertex (canonical units) and ``radius``, ``R`` those of the
request's frame (identity and 1 in the canonical frame). Each part becomes its own node (GLB) or
object (OBJ), named ``<index>_<part id>``, so the file keeps the assembly's structure.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import trimesh

from service.artifacts.catalog import Catalog
from service.errors import InputError
from service.geometry.frames import Frame

ExportFormat = Literal["glb", "obj"]
MEDIA_TYPES: dict[str, str] = {"glb": "model/gltf-binary", "obj": "model/obj"}


@dataclass(frozen=True)
class ExportItem:
    """One placed part. Shapes: translation (3,) in the caller's frame."""

    part_id: str
    translation: tuple[float, float, float]
    scale: float | tuple[float, float, float] = 1.0   # uniform, or per axis of the caller's frame


def placed_meshes(catalog: Catalog, items: list[ExportItem], frame: Frame
                  ) -> list[tuple[str, trimesh.Trimesh]]:
    """Every item's mesh placed in the caller's frame, with its node name.

    Raises ``NotFoundError`` for an unknown part id (before any geometry is built).
    """
    rows = [catalog.lookup(it.part_id) for it in items]
    out = []
    for n, (it, i) in enumerate(zip(items, rows, strict=True)):
        v, f = catalog.mesh(i)
        # A per-axis scale is given along the caller's axes; the catalog mesh is in the model's.
        scale = np.broadcast_to(np.asarray(it.scale, dtype=np.float64), (3,)) @ np.abs(frame.rotation).T
        placed = frame.radius * ((scale * v.astype(np.float64)) @ frame.part_rotation.T) + np.asarray(
            it.translation, dtype=np.float64)
        # Mesh files store float32: coordinates must stay finite there too.
        if not np.all(np.abs(placed) < np.finfo(np.float32).max):
            raise InputError("non_finite_geometry", f"item {n} ({it.part_id}): translation, scale and "
                             "frame give vertices that are not finite in float32")
        name = f"{n}_{it.part_id.replace('/', '_')}"
        out.append((name, trimesh.Trimesh(vertices=placed, faces=f.astype(np.int64), process=False)))
    return out


def export_assembly(catalog: Catalog, items: list[ExportItem], fmt: ExportFormat, frame: Frame | None = None,
                    max_parts: int | None = None) -> bytes:
    """The placed parts as one GLB or OBJ file.

    Args:
        catalog: where the parts' meshes come from.
        items: the parts, translations and scales.
        fmt: "glb" (binary glTF 2.0, one node per part) or "obj" (one object per part).
        frame: the caller's frame of the translations (default: canonical).
        max_parts: refuse more items than this (``InputError`` too_many_parts).
    """
    if not items:
        raise InputError("no_parts", "give at least one part to export")
    if max_parts is not None and len(items) > max_parts:
        raise InputError("too_many_parts", f"{len(items)} parts given, at most {max_parts} can be exported "
                         "at once")
    if fmt not in MEDIA_TYPES:
        raise InputError("unsupported_format", f"format {fmt!r} is not one of {', '.join(MEDIA_TYPES)}")
    scene = trimesh.Scene()
    for name, mesh in placed_meshes(catalog, items, frame or Frame()):
        scene.add_geometry(mesh, node_name=name, geom_name=name)
    data = scene.export(file_type=fmt, **({"include_normals": False} if fmt == "obj" else {}))
    return data.encode("utf-8") if isinstance(data, str) else bytes(data)
