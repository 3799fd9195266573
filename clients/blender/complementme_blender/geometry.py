"""Pure geometry of the add-on: the query as GLB, the request frame, OBJ parts and their placement.

No ``bpy`` here, so these functions run (and are tested) outside Blender. Coordinates are
Blender's world coordinates in scene units, z up; the service is told so with the request
``frame`` (``up_axis: "z"``) and answers in the same frame, so nothing is converted by hand.
"""

from __future__ import annotations

import json
import math
import struct
import sys
from array import array
from collections.abc import Sequence

Vec3 = tuple[float, float, float]

# How the request frame (the complete object's centre and radius) is found from the selection.
FRAME_MODES = (
    ("GROUND", "On the ground",
     "The complete object stands on the ground (z = 0) under the selection: its box is the "
     "selection's box extended down to z = 0"),
    ("SELECTION", "Whole selection",
     "The selection already spans the complete object (its box is the object's box)"),
    ("MANUAL", "Manual", "Give the complete object's centre and radius"),
    ("FIT", "Fitted by the service",
     "The service estimates the complete object's centre and radius from the selection (z up): "
     "for an object that does not stand on the ground"),
)


def glb_bytes(positions: Sequence[float], indices: Sequence[int]) -> bytes:
    """A binary glTF 2.0 file with one triangle mesh and one node, coordinates as given.

    Args:
        positions: x, y, z of every vertex, flattened (3V floats).
        indices: three vertex indices per triangle, flattened (3F ints).

    Shapes:
        positions (3V,) float -> float32 in the file; indices (3F,) int -> uint32.
    """
    assert len(positions) % 3 == 0 and len(positions) > 0, (
        f"positions must be 3V > 0 floats, found {len(positions)}")
    assert len(indices) % 3 == 0 and len(indices) > 0, f"indices must be 3F > 0 ints, found {len(indices)}"
    pos = array("f", positions)
    idx = array("I", indices)
    if sys.byteorder == "big":  # glTF is little-endian
        pos.byteswap()
        idx.byteswap()
    lo = [min(positions[i::3]) for i in range(3)]
    hi = [max(positions[i::3]) for i in range(3)]
    pos_bytes, idx_bytes = pos.tobytes(), idx.tobytes()
    doc = {
        "asset": {"version": "2.0", "generator": "complementme-blender"},
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": "selection"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1, "mode": 4}]}],
        "buffers": [{"byteLength": len(pos_bytes) + len(idx_bytes)}],
        "bufferViews": [
            {"buffer": 0, "byteOffset": 0, "byteLength": len(pos_bytes), "target": 34962},
            {"buffer": 0, "byteOffset": len(pos_bytes), "byteLength": len(idx_bytes), "target": 34963},
        ],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": len(pos) // 3, "type": "VEC3",
             "min": lo, "max": hi},
            {"bufferView": 1, "componentType": 5125, "count": len(idx), "type": "SCALAR"},
        ],
    }
    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    binary = pos_bytes + idx_bytes  # both multiples of 4 bytes
    total = 12 + 8 + len(js) + 8 + len(binary)
    return (struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(js), b"JSON") + js
            + struct.pack("<I4s", len(binary), b"BIN\x00") + binary)


def request_frame(mode: str, lo: Vec3, hi: Vec3, center: Vec3 = (0.0, 0.0, 0.0),
                  radius: float = 1.0) -> dict[str, object]:
    """The request's ``frame`` (z up) for the selection's world box ``lo``-``hi``.

    The service expects the centre and radius of the *complete* object. Taking them from a
    partial selection misleads it: the example chair without its legs, fitted to its own box,
    was answered with five seats; on the ground (its box extended to z = 0) with five legs.

    Args:
        mode: one of ``FRAME_MODES``: ``GROUND`` (default in the panel), ``SELECTION``, ``MANUAL``,
            ``FIT`` (only the up axis: the request then asks ``fit_frame``, see ``frame_request``).
        lo, hi: the selection's box; center, radius: used by ``MANUAL`` only.
    """
    if mode == "FIT":
        return {"up_axis": "z"}
    if mode == "MANUAL":
        c, r = tuple(center), float(radius)
    else:
        box_lo = list(lo)
        if mode == "GROUND":
            box_lo[2] = min(0.0, lo[2])
        elif mode != "SELECTION":
            raise ValueError(f"frame mode must be GROUND, SELECTION or MANUAL, found {mode!r}")
        c = tuple((a + b) / 2 for a, b in zip(box_lo, hi, strict=True))
        r = math.dist(hi, c)  # half the box's diagonal: every point of the box lies within it
    if not (r > 0 and math.isfinite(r)):
        raise ValueError("the frame's radius must be > 0: the selection has no extent" if mode != "MANUAL"
                         else "the frame's radius must be > 0")
    return {"center": [float(x) for x in c], "radius": r, "up_axis": "z"}


def frame_request(mode: str, lo: Vec3, hi: Vec3, center: Vec3 = (0.0, 0.0, 0.0),
                  radius: float = 1.0) -> dict[str, object]:
    """The request options that say where the complete object is: its ``frame``
    (``request_frame``) and, in ``FIT`` mode, ``fit_frame`` (the service fits centre and radius)."""
    options: dict[str, object] = {"frame": request_frame(mode, lo, hi, center, radius)}
    if mode == "FIT":
        options["fit_frame"] = True
    return options


def parse_obj(text: str) -> tuple[list[Vec3], list[tuple[int, ...]]]:
    """Vertices and faces (0-based, polygons kept) of an OBJ text; other statements are skipped.

    Shapes:
        -> vertices (V,) of (x, y, z) floats, faces (F,) of index tuples.
    """
    vertices: list[Vec3] = []
    faces: list[tuple[int, ...]] = []
    for line in text.splitlines():
        fields = line.split()
        if not fields:
            continue
        if fields[0] == "v" and len(fields) >= 4:
            vertices.append((float(fields[1]), float(fields[2]), float(fields[3])))
        elif fields[0] == "f" and len(fields) >= 4:
            # "f 1/2/3 ..." keeps the vertex index; negative indices count from the end.
            idx = [int(f.split("/")[0]) for f in fields[1:]]
            faces.append(tuple(i - 1 if i > 0 else len(vertices) + i for i in idx))
    n = len(vertices)
    if not vertices or not faces or any(not 0 <= i < n for face in faces for i in face):
        raise ValueError(f"the part's OBJ mesh is empty or has a face index out of range ({n} vertices)")
    return vertices, faces


def part_scale(entry: dict[str, object]) -> Vec3:
    """The per-axis ``scale`` of a suggestion or step (caller axes), (1, 1, 1) when absent."""
    s = entry.get("scale")
    if s is None:
        return (1.0, 1.0, 1.0)
    if isinstance(s, (int, float)):
        return (float(s),) * 3
    assert isinstance(s, (list, tuple)) and len(s) == 3, f"scale must be a number or 3 numbers, found {s!r}"
    return (float(s[0]), float(s[1]), float(s[2]))


def placement_matrix(frame: dict[str, object], translation: Sequence[float],
                     scale: Sequence[float] = (1.0, 1.0, 1.0)) -> list[list[float]]:
    """The 4x4 world matrix of a catalog part: ``scale * (frame.scale * rotation @ v) + translation``.

    The part's mesh is centred and in canonical units (``GET /parts/{id}/mesh``); the answer's
    ``frame`` gives ``scale`` and ``rotation`` into the caller's axes, its ``translation`` where
    the part's box centre goes. ``scale`` (the part's per-axis fitting scale, when the service
    gives one) is along the caller's axes, about the part's centre, as ``POST /export`` applies it.

    Shapes:
        frame["rotation"]: (3, 3); translation, scale: (3,) -> (4, 4) row-major.
    """
    s = float(frame["scale"])  # type: ignore[arg-type]
    rot = frame["rotation"]
    assert isinstance(rot, list) and len(rot) == 3, f"frame rotation must be 3x3, found {rot!r}"
    rows = [[s * float(scale[i]) * float(rot[i][j]) for j in range(3)] + [float(translation[i])]
            for i in range(3)]
    return [*rows, [0.0, 0.0, 0.0, 1.0]]


def transform_box(matrix: list[list[float]], vertices: Sequence[Vec3]) -> tuple[Vec3, Vec3]:
    """World box of ``vertices`` under a 4x4 ``matrix`` (lo, hi)."""
    pts = [[sum(matrix[i][j] * v[j] for j in range(3)) + matrix[i][3] for i in range(3)] for v in vertices]
    lo = (min(p[0] for p in pts), min(p[1] for p in pts), min(p[2] for p in pts))
    hi = (max(p[0] for p in pts), max(p[1] for p in pts), max(p[2] for p in pts))
    return lo, hi
