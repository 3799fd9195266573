"""An uploaded part mesh -> a part ready to store: checked, centred, sampled, embedded.

The upload is untrusted: it goes through ``service.geometry.mesh.load_mesh_bytes`` with the size
limits, and external references are refused (not dropped, as ``/suggest/mesh`` does: catalog
content must be self-contained). The mesh is mapped from the caller's frame to the canonical
one (parts keep the scale of their complete object, which has unit radius), centred at its
bounding-box centre (that centre becomes the part's ``translation``), sampled area-weighted to
the model's point count and embedded with f; h's part branch gives its placement feature.
"""

from __future__ import annotations

import numpy as np

from service.artifacts.models import Networks
from service.catalog_store.store import NewPart, PartGeometry
from service.errors import InputError
from service.geometry.frames import Frame
from service.geometry.inputs import upload_error
from service.geometry.mesh import MeshError, load_mesh_bytes, mesh_area, sample_surface


def embed_geometry(networks: Networks, vertices: np.ndarray, faces: np.ndarray, n_points: int,
                   seed: int, placement_points: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """f's embedding and h's part feature of a centred mesh, from ``n_points`` seeded samples
    (h's from ``placement_points`` when the artifacts give h its own count; as the export does).

    Shapes:
        vertices (V, 3), faces (F, 3) -> embedding (D,) float32, part_feature (Fp,) float32.
    """
    pts = sample_surface(vertices, faces, n_points, seed)[None]  # (1, N, 3)
    embedding = networks.embed(pts)[0]
    if placement_points is not None and placement_points != n_points:
        pts = sample_surface(vertices, faces, placement_points, seed)[None]
    feature = networks.part_features(pts)[0]
    if not (np.isfinite(embedding).all() and np.isfinite(feature).all()):
        raise InputError("non_finite", "the networks gave non-finite outputs for this part")
    return embedding.astype(np.float32), feature.astype(np.float32)


def prepare_part(data: bytes, file_type: str, *, name: str, frame: Frame, networks: Networks,
                 n_points: int, preview_points: int, seed: int, max_vertices: int, max_faces: int,
                 max_nodes: int, max_nesting: int, max_extent: float, category: str,
                 part_name: str | None, style: str | None, label: str | None, model_version: str,
                 placement_points: int | None = None) -> NewPart:
    """Load, check, centre, sample and embed one uploaded part.

    Args:
        data, file_type, name: the upload's bytes, format (``MESH_FORMATS``) and how errors name it.
        frame: the caller's frame (centre and radius of the complete object, up axis).
        n_points: points the networks take (N); placement_points: h's, when its own (None: N);
            preview_points: samples kept for display (S).
        max_extent: largest bounding-box diagonal in the canonical frame.

    Raises:
        ServiceError: 415 for an unknown format, 413 over the limits, 422 for a bad mesh.
    """
    try:
        mesh = load_mesh_bytes(data, file_type, name=name, max_vertices=max_vertices, max_faces=max_faces,
                               max_nodes=max_nodes, max_nesting=max_nesting)
    except MeshError as exc:
        raise upload_error(exc) from None
    vertices = frame.to_canonical(np.asarray(mesh.vertices, dtype=np.float64)).astype(np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if not np.isfinite(vertices).all():
        raise InputError("non_finite", f"{name}: vertices are not finite in the canonical frame; check "
                         "the frame's center and radius")
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    extent = float(np.linalg.norm(hi - lo))
    if extent > max_extent:
        raise InputError("part_too_large", f"{name}: the part is {extent:.4g} across in the canonical frame "
                         f"(at most {max_extent:g}); parts keep the scale of their complete object, which "
                         "has unit radius: give the frame (center, radius) of the object it belongs to")
    centre = (lo + hi) / 2
    v = vertices - centre
    area = mesh_area(v, faces)
    if not area > 0:
        raise InputError("zero_area", f"{name}: the part's surface area is zero in the canonical frame")
    embedding, feature = embed_geometry(networks, v, faces, n_points, seed, placement_points)
    preview = sample_surface(v, faces, preview_points, seed + 1).astype(np.float16)
    geometry = PartGeometry(vertices=v.astype(np.float32), faces=faces.astype(np.int32), points=preview)
    return NewPart(category=category, name=part_name, style=style, label=label, translation=centre,
                   bbox_min=lo - centre, bbox_max=hi - centre, area=area, embedding=embedding,
                   part_feature=feature, model_version=model_version, geometry=geometry)
