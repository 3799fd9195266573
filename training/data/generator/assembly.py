"""ShapeBuilder: collects the pieces of one generated shape and turns them into a RawShape.

Category modules describe a shape part by part (``add(mesh, label, transforms)``); the builder
keeps which pieces are instances of one geometry, adds the small mess real 3D Warehouse models
carry (bolts, duplicated overlapping pieces), and at the end normalises the shape to the
canonical frame (bounding-box centre at the origin, max vertex distance 1) and names the nodes
neutrally, in a shuffled order, so nothing but the sidecar tells which piece is which part.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from training.data.generator.mesh import Mesh, align_y_to, compose, translation
from training.data.generator.primitives import frustum
from training.data.shapes import RawPiece, RawShape


@dataclass
class _Piece:
    key: int
    label: str
    mesh: Mesh  # in the build frame (y up, front +x, arbitrary scale)


class ShapeBuilder:
    """Accumulates placed pieces; one ``add`` call is one geometry with one or more instances."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self._pieces: list[_Piece] = []
        self._geometry: list[tuple[Mesh, str]] = []  # key -> (local mesh, label)

    def add(self, mesh: Mesh, label: str, transforms: list[np.ndarray] | None = None) -> int:
        """Add one geometry placed once per transform (default: as is); returns its key."""
        key = len(self._geometry)
        self._geometry.append((mesh, label))
        self.place(key, transforms if transforms is not None else [np.eye(4)])
        return key

    def place(self, key: int, transforms: list[np.ndarray]) -> None:
        """Place more instances of a geometry added before (e.g. a spare wheel)."""
        mesh, label = self._geometry[key]
        for m in transforms:
            self._pieces.append(_Piece(key, label, mesh.transformed(m)))

    def bolts(
        self,
        points: np.ndarray,
        label: str,
        radius: float,
        length: float,
        direction: tuple[float, float, float] = (0.0, 1.0, 0.0),
        frame: np.ndarray | None = None,
        segments: int = 8,
    ) -> None:
        """Tiny identical screw heads / rivets centred on ``points``, axis along ``direction``.

        ``points`` and ``direction`` are given in ``frame`` (a 4x4 placed part's frame, default the
        build frame). They sit half inside the surface they fasten, so preprocessing merges them
        into it.
        """
        head = frustum(radius, 0.8 * radius, length, segments).transformed(translation(0, -length / 2, 0))
        rot = align_y_to(np.asarray(direction, float))
        f = np.eye(4) if frame is None else frame
        self.add(head, label, [compose(f, translation(*p), rot) for p in np.atleast_2d(points)])

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Bounding box (min, max) of everything added so far, in build units."""
        v = np.concatenate([p.mesh.vertices for p in self._pieces])
        return v.min(axis=0), v.max(axis=0)

    def duplicate_some(self, probability: float, offset: float) -> None:
        """With ``probability``, repeat one random geometry as overlapping near-copies.

        Real models often hold the same geometry twice, a hair apart. Every instance of the
        chosen geometry is copied with the same shift of ``offset`` (build units) in a random
        direction, so the instances stay alike (all four legs doubled, not one).
        """
        if not self._pieces or self.rng.random() >= probability:
            return
        key = self._pieces[int(self.rng.integers(len(self._pieces)))].key
        d = self.rng.normal(size=3)
        shift = d / np.linalg.norm(d) * offset
        for src in [p for p in self._pieces if p.key == key]:
            self._pieces.append(_Piece(key, src.label, Mesh(src.mesh.vertices + shift, src.mesh.faces)))

    def build(self, shape_id: str, category: str, style: str, source: str) -> RawShape:
        """Normalise to the canonical frame and name nodes neutrally in a shuffled order."""
        if not self._pieces:
            raise ValueError(f"shape {shape_id} has no pieces")
        allv = np.concatenate([p.mesh.vertices for p in self._pieces])
        centre = 0.5 * (allv.min(axis=0) + allv.max(axis=0))
        radius = float(np.linalg.norm(allv - centre, axis=1).max())
        order = self.rng.permutation(len(self._pieces))
        key_names: dict[int, str] = {}
        pieces = []
        for node_index, i in enumerate(order):
            p = self._pieces[int(i)]
            key_names.setdefault(p.key, f"mesh_{len(key_names):03d}")
            pieces.append(
                RawPiece(
                    name=f"node_{node_index:03d}",
                    vertices=(p.mesh.vertices - centre) / radius,
                    faces=p.mesh.faces.astype(np.int64),
                    geometry_key=key_names[p.key],
                    label=p.label,
                )
            )
        return RawShape(shape_id=shape_id, category=category, pieces=pieces, style=style, source=source)
