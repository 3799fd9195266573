"""A minimal triangle mesh and the rigid/affine 4x4 transforms the generator composes.

The generator builds every piece in a local frame and places it with a 4x4 matrix, so that
repeated pieces (legs, slats, wheels) are one geometry under several transforms, exactly as in a
3D Warehouse scene graph.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Mesh:
    """A closed triangle mesh in some local frame.

    Shapes:
        vertices: (V, 3) float64.
        faces: (F, 3) int64, counter-clockwise seen from outside.
    """

    vertices: np.ndarray
    faces: np.ndarray

    def transformed(self, matrix: np.ndarray) -> Mesh:
        """Apply a 4x4 transform; a reflection (negative determinant) also flips the winding."""
        v = self.vertices @ matrix[:3, :3].T + matrix[:3, 3]
        faces = self.faces if np.linalg.det(matrix[:3, :3]) > 0 else self.faces[:, ::-1].copy()
        return Mesh(v, faces)

    def signed_volume(self) -> float:
        """Volume by the divergence theorem: positive when the faces point outward."""
        a, b, c = (self.vertices[self.faces[:, i]] for i in range(3))
        return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)

    def oriented_outward(self) -> Mesh:
        """The same surface with faces flipped if they point inward."""
        if self.signed_volume() < 0:
            return Mesh(self.vertices, self.faces[:, ::-1].copy())
        return self


def concatenate(meshes: list[Mesh]) -> Mesh:
    """Join meshes into one piece (one scene node holding several closed shells)."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return Mesh(
        np.concatenate([m.vertices for m in meshes]),
        np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)]),
    )


# ---- 4x4 transforms ---------------------------------------------------------------------------


def translation(x: float, y: float, z: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def scaling(sx: float, sy: float, sz: float) -> np.ndarray:
    return np.diag([sx, sy, sz, 1.0])


def rotation(axis: str, angle: float) -> np.ndarray:
    """Right-handed rotation by ``angle`` radians about the x, y or z axis."""
    c, s = np.cos(angle), np.sin(angle)
    i, j = {"x": (1, 2), "y": (2, 0), "z": (0, 1)}[axis]
    m = np.eye(4)
    m[i, i] = c
    m[j, j] = c
    m[i, j] = -s
    m[j, i] = s
    return m


def compose(*matrices: np.ndarray) -> np.ndarray:
    """``compose(A, B, C)`` applies C first, then B, then A (like A @ B @ C)."""
    out = np.eye(4)
    for m in matrices:
        out = out @ m
    return out


def align_y_to(direction: np.ndarray) -> np.ndarray:
    """The rotation (4x4) that takes the +y axis to the unit vector along ``direction``."""
    d = np.asarray(direction, dtype=float)
    d = d / np.linalg.norm(d)
    y = np.array([0.0, 1.0, 0.0])
    c = float(np.dot(y, d))
    m = np.eye(4)
    if c > 1 - 1e-12:
        return m
    if c < -1 + 1e-12:
        return rotation("x", np.pi)
    v = np.cross(y, d)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    m[:3, :3] = np.eye(3) + vx + vx @ vx / (1 + c)
    return m
