"""Raw shapes: a shape as the list of pieces its file holds, before preprocessing.

This is the in-memory contract between everything that *produces* shapes (the procedural
generator, the ingest of user meshes) and the preprocessing of Section 4 of the paper.

On disk the built-in dataset is one binary glTF scene per shape (``<shape_id>.glb``: one
scene-graph node per piece; pieces that are instances of one geometry share one glTF mesh) plus a
small sidecar ``<shape_id>.json`` holding the metadata a user's own collection may also supply::

    {"shape_id": "chair-0001", "category": "chair", "style": "armchair",
     "labels": {"<node name>": "leg", ...},
     "geometry_keys": {"<node name>": "<key shared by instances of one geometry>", ...}}

(glTF readers such as trimesh split shared meshes apart on load, so the sidecar keeps which nodes
are instances of one geometry; without it, identical-up-to-translation detection groups them.)

``style`` and ``labels`` are for evaluation only: training never reads them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class RawPiece:
    """One scene-graph leaf (or connected component) of a shape, in the shape's frame.

    Shapes:
        vertices: (V, 3) float64, already transformed into the shape frame.
        faces: (F, 3) int64.
    """

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    # Pieces sharing a key are instances of one geometry in the scene graph (e.g. four legs).
    geometry_key: str
    # Semantic label, for evaluation only (None when the source has none).
    label: str | None = None


@dataclass
class RawShape:
    """A shape as read from a file or made by the generator, before any merge."""

    shape_id: str
    category: str
    pieces: list[RawPiece] = field(default_factory=list)
    # Fine-grained style (e.g. "armchair"), for evaluation only.
    style: str | None = None
    # Where the shape came from (a path, or "generated:<seed>").
    source: str = ""


SIDECAR_SUFFIX = ".json"
