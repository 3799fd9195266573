"""Airplanes nobody here made: FlightGear's AI aircraft (AC3D files) as a folder for ``data ingest``.

Debian packages the simulator's AI traffic models (``apt-get install flightgear-data-ai``:
``/usr/share/games/flightgear/AI/Aircraft/<type>/Models/*.ac``, GPL): airliners, business jets,
fighters and propeller planes in the AC3D format, each a tree of named objects (fuselage, wings,
gear, ...), many of them a body and its gear only. ``export_aircraft`` writes every model with at
least ``min_objects`` named objects that carry faces (lights, glass, windows, shadows and
propeller discs left out: they are not parts) as an OBJ file under ``<out>/airplane/`` with one
group per object, in the canonical frame's orientation: AC3D is y up with the nose towards -x,
so a half turn about y gives front +x. ``data ingest`` and ``data preprocess`` then make a
processed folder of them like any user collection, for ``complementme evaluate-real``.

The files are read as untrusted input: every count (vertices, surfaces, references, kids) is
checked against the lines that are left, objects nest at most ``MAX_DEPTH`` deep, and a file that
breaks either is refused with its name and line.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from training.data.shape_io import write_sources

MAX_DEPTH = 32
# Objects by these names are not parts of the plane.
_SKIPPED = re.compile(r"light|shadow|glass|window|strobe|beacon|prop.*disc", re.IGNORECASE)
# AC3D (y up, nose at -x) to the canonical frame (y up, front +x): a half turn about y.
_TO_CANONICAL = np.diag([-1.0, 1.0, -1.0])


class AC3DError(ValueError):
    """An AC3D file that cannot be read (names the file, the line and what is wrong)."""


@dataclass
class AcObject:
    """One object of an AC3D tree with its geometry in the file's world frame."""

    name: str
    vertices: np.ndarray      # (V, 3) float64, world frame (parents' loc and rot applied)
    triangles: np.ndarray     # (F, 3) int64, polygons fanned into triangles


class _Lines:
    def __init__(self, path: Path, text: str):
        self.path, self.lines, self.i = path, text.splitlines(), 0

    def error(self, what: str) -> AC3DError:
        return AC3DError(f"{self.path}:{self.i}: {what}")

    def next(self) -> str:
        if self.i >= len(self.lines):
            raise self.error("the file ends inside an object")
        self.i += 1
        return self.lines[self.i - 1].strip()

    def seek_object(self) -> bool:
        """Move past the next OBJECT line; False at the end of the file."""
        while self.i < len(self.lines):
            self.i += 1
            if self.lines[self.i - 1].startswith("OBJECT"):
                return True
        return False

    def count(self, token: str, what: str, bounded: bool = True) -> int:
        """A count of the file; ``bounded``: each item takes a line, so no more than are left."""
        try:
            n = int(token)
        except ValueError as exc:
            raise self.error(f"{what} must be a whole number, found {token!r}") from exc
        if n < 0:
            raise self.error(f"{what} must not be negative, found {n}")
        if bounded and n > len(self.lines) - self.i:
            raise self.error(f"{what} {n} is more than the file's remaining lines")
        return n

    def numbers(self, line: str, n: int, what: str) -> list[float]:
        try:
            values = [float(v) for v in line.split()[:n]]
        except ValueError as exc:
            raise self.error(f"{what}: not numbers: {line!r}") from exc
        if len(values) != n or not np.all(np.isfinite(values)):
            raise self.error(f"{what}: expected {n} finite numbers, found {line!r}")
        return values


def _read_object(src: _Lines, origin: np.ndarray, turn: np.ndarray, depth: int, out: list[AcObject]) -> None:
    """Read one OBJECT block (its header line already read) and its kids into ``out``."""
    if depth > MAX_DEPTH:
        raise src.error(f"objects nest deeper than {MAX_DEPTH}")
    name, loc, rot = "", np.zeros(3), np.eye(3)
    verts: np.ndarray | None = None
    tris: list[tuple[int, int, int]] = []
    while True:
        line = src.next()
        key, _, rest = line.partition(" ")
        if key == "name":
            name = rest.strip().strip('"')
        elif key == "loc":
            loc = np.asarray(src.numbers(rest, 3, "loc"))
        elif key == "rot":
            rot = np.asarray(src.numbers(rest, 9, "rot")).reshape(3, 3)
        elif key == "numvert":
            n = src.count(rest.strip(), "numvert")
            verts = np.asarray([src.numbers(src.next(), 3, "vertex") for _ in range(n)]).reshape(-1, 3)
        elif key == "numsurf":
            for _ in range(src.count(rest.strip(), "numsurf")):
                while not (line := src.next()).startswith("refs"):
                    pass  # SURF and mat lines: flags and materials, nothing we use
                n_refs = src.count(line.partition(" ")[2].strip(), "refs")
                refs = [(src.next().split() or [""])[0] for _ in range(n_refs)]
                idx = [src.count(r, "vertex reference", bounded=False) for r in refs]
                if verts is None or any(j >= len(verts) for j in idx):
                    raise src.error("a surface refers to a vertex the object does not have")
                tris += [(idx[0], idx[k], idx[k + 1]) for k in range(1, len(idx) - 1)]
        elif key == "kids":
            # AC3D's loc and rot place an object in its parent: compose them down the tree.
            here_turn, here_origin = turn @ rot, origin + turn @ loc
            if verts is not None and tris:
                out.append(AcObject(name or "object", verts @ here_turn.T + here_origin,
                                    np.asarray(tris, dtype=np.int64)))
            # Exporters sometimes announce more kids than they write: the file's end ends the list.
            for _ in range(src.count(rest.strip(), "kids", bounded=False)):
                if not src.seek_object():
                    break
                _read_object(src, here_origin, here_turn, depth + 1, out)
            return


def read_ac3d(path: Path, max_bytes: int = 64 * 1024 * 1024) -> list[AcObject]:
    """Every object of an AC3D file that has faces, in the file's world frame."""
    size = path.stat().st_size
    if size > max_bytes:
        raise AC3DError(f"{path}: {size} bytes (limit {max_bytes})")
    src = _Lines(path, path.read_text(encoding="latin-1"))
    if not src.lines or not src.lines[0].startswith("AC3D"):
        raise AC3DError(f"{path}: not an AC3D file (no AC3D header)")
    if not src.seek_object():
        raise AC3DError(f"{path}: no OBJECT in it")
    out: list[AcObject] = []
    _read_object(src, np.zeros(3), np.eye(3), 0, out)
    return out


def canonical_obj(objects: list[AcObject]) -> str:
    """OBJ text with a group per object, turned into the canonical orientation."""
    lines, base = [], 1
    for obj in objects:
        lines.append("g " + re.sub(r"\s+", "_", obj.name))
        lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in obj.vertices @ _TO_CANONICAL.T]
        lines += [f"f {a + base} {b + base} {c + base}" for a, b, c in obj.triangles]
        base += len(obj.vertices)
    return "\n".join(lines) + "\n"


def export_aircraft(root: Path, out: Path, min_objects: int = 3) -> tuple[int, list[str]]:
    """Write every model under ``root`` with ``min_objects`` or more part objects as
    ``<out>/airplane/fg-<type>-<file>.obj``, and ``<out>/sources.json``.

    Returns the number written and, for each file that could not be read, why (it is skipped).
    """
    sources, skipped = [], []
    folder = out / "airplane"
    folder.mkdir(parents=True, exist_ok=True)
    for path in sorted(root.rglob("*.ac")):
        try:
            objects = read_ac3d(path)
        except AC3DError as exc:
            skipped.append(str(exc))
            continue
        parts = [o for o in objects if not _SKIPPED.search(o.name)]
        if len(parts) < min_objects:
            continue
        kind = path.parent.parent.name if path.parent.name.lower() == "models" else path.parent.name
        slug = re.sub(r"[^a-z0-9]+", "-", f"{kind}-{path.stem}".lower()).strip("-")
        (folder / f"fg-{slug}.obj").write_text(canonical_obj(parts))
        sources.append({"file": f"airplane/fg-{slug}.obj", "source": str(path.relative_to(root)),
                        "objects": len(parts)})
    write_sources(out, sources)
    return len(sources), skipped
