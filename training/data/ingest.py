"""Read a user's shape collection into the built-in raw format (one GLB + sidecar per shape).

Accepted inputs, one shape per file:
- OBJ: each group (``g``) or object (``o``) is a piece, labelled by its name (``leg``,
  ``leg.001`` and ``leg_2`` all label a ``leg``) unless a sidecar gives labels; a file without
  groups is split into its connected components (unlabelled).
- GLB / glTF: each scene-graph leaf is a piece. A sidecar ``<stem>.json`` (see
  ``training.data.shapes``) supplies shape id, category, style, labels and geometry keys; the
  built-in generator writes exactly that, so this is also how preprocessing reads it.
- PLY / OFF / STL: connected components are the pieces.
- Segmented point clouds of the ShapeNet part benchmark: ``<id>.pts`` (``x y z`` per line) with
  ``<id>.seg`` (one segment id per line) beside it, or in the benchmark's ``../points_label/``.
  Each segment is a piece with points but no triangles (``faces`` has shape (0, 3)), labelled by
  its segment id.

Files are untrusted: they are read through ``service.geometry.mesh``, which refuses any reference to
another file or URL, so a shape file can never make the loader read anything but itself (and
the sidecar that *we* look for by name).
"""

from __future__ import annotations

import json
import logging
import re
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from service.geometry.mesh import MeshError, load_scene_leaves, valid_point_set
from training.data.shapes import SIDECAR_SUFFIX, RawPiece, RawShape

log = logging.getLogger(__name__)

MESH_SUFFIXES = (".obj", ".glb", ".gltf", ".ply", ".off", ".stl")
POINT_SUFFIX = ".pts"
SEGMENT_SUFFIX = ".seg"
SHAPE_SUFFIXES = (*MESH_SUFFIXES, POINT_SUFFIX)
REPORT_NAME = "ingest_report.json"


@dataclass
class IngestConfig:
    """Limits and options for reading untrusted shape files (every limit is a setting)."""

    # Refuse files larger than this before reading them.
    max_file_bytes: int = 256 * 1024 * 1024
    # Refuse meshes with more vertices / triangles (checked on headers before allocating).
    max_vertices: int = 2_000_000
    max_faces: int = 4_000_000
    # Refuse point clouds with more points.
    max_points: int = 2_000_000
    # OBJ files usually name a material library; refusing it keeps the loader from reading other
    # files. With this set, material lines are dropped instead (geometry is all we use).
    ignore_obj_materials: bool = False
    # A shape needs at least this many pieces to yield a (partial assembly, complement) pair.
    min_pieces: int = 2


class ShapeFileError(ValueError):
    """A shape file that cannot be used; the message names the file and says why."""

    def __init__(self, path: Path | str, reason: str, code: str = "invalid"):
        super().__init__(f"{path}: {reason}")
        self.path = str(path)
        self.reason = reason
        self.code = code


def _read_bytes(path: Path, config: IngestConfig) -> bytes:
    try:
        size = path.stat().st_size
    except OSError as err:
        raise ShapeFileError(path, f"cannot be read ({err.strerror})", "unreadable") from err
    if size > config.max_file_bytes:
        raise ShapeFileError(path, f"is {size} bytes, more than the limit of {config.max_file_bytes}",
                             "too_large")
    return path.read_bytes()


def read_sidecar(path: Path) -> dict[str, Any] | None:
    """The sidecar ``<stem>.json`` of a shape file, validated, or None when there is none."""
    side = path.with_suffix(SIDECAR_SUFFIX)
    if not side.is_file():
        return None
    try:
        meta = json.loads(side.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ShapeFileError(side, f"sidecar is not valid JSON ({err})", "bad_sidecar") from err
    if not isinstance(meta, dict):
        raise ShapeFileError(side, "sidecar must be a JSON object", "bad_sidecar")
    for key in ("shape_id", "category", "style"):
        if meta.get(key) is not None and not isinstance(meta[key], str):
            raise ShapeFileError(side, f"sidecar field {key!r} must be a string", "bad_sidecar")
    for key in ("labels", "geometry_keys"):
        value = meta.get(key, {})
        if not isinstance(value, dict) or not all(isinstance(v, str) or v is None for v in value.values()):
            raise ShapeFileError(side, f"sidecar field {key!r} must map node names to strings", "bad_sidecar")
    return meta


def _mesh_pieces(path: Path, config: IngestConfig, meta: dict[str, Any] | None) -> list[RawPiece]:
    data = _read_bytes(path, config)
    try:
        leaves = load_scene_leaves(data, path.suffix, name=str(path), max_vertices=config.max_vertices,
                                   max_faces=config.max_faces,
                                   ignore_obj_materials=config.ignore_obj_materials)
    except MeshError as err:
        raise ShapeFileError(path, err.message.removeprefix(f"{path}: "), err.code) from err
    labels = (meta or {}).get("labels", {})
    keys = (meta or {}).get("geometry_keys", {})
    named = path.suffix.lower() == ".obj"
    return [RawPiece(name=leaf.name, vertices=leaf.vertices, faces=leaf.faces,
                     geometry_key=keys.get(leaf.name) or leaf.geometry,
                     label=labels.get(leaf.name) or (obj_label(leaf.name) if named else None))
            for leaf in leaves]


# trimesh names the geometry of an OBJ without groups "geometry"; components get "/<i>".
_UNNAMED_OBJ = "geometry"


def obj_label(leaf_name: str) -> str | None:
    """The part label an OBJ group or object name gives, or None for an unnamed piece.

    ``seat`` -> ``seat``; ``leg.001`` (Blender's copies), ``leg_2`` and ``leg/1`` (one group
    split into connected components) -> ``leg``.
    """
    base = leaf_name.split("/", 1)[0]
    if base == _UNNAMED_OBJ:
        return None
    return re.sub(r"[._]\d+$", "", base) or None


def _segment_file(path: Path) -> Path | None:
    """``<stem>.seg`` beside the points, or the part benchmark's ``../points_label/<stem>.seg``."""
    benchmark = path.parent.parent / "points_label" / (path.stem + SEGMENT_SUFFIX)
    for cand in (path.with_suffix(SEGMENT_SUFFIX), benchmark):
        if cand.is_file():
            return cand
    return None


def _parse_numbers(path: Path, data: bytes, columns: int, dtype: type, limit: int) -> np.ndarray:
    lines = [ln for ln in data.decode("ascii", errors="replace").splitlines() if ln.strip()]
    if len(lines) > limit:
        raise ShapeFileError(path, f"has {len(lines)} points, more than the limit of {limit}", "too_large")
    if not lines:
        raise ShapeFileError(path, "has no points", "empty_mesh")
    try:
        arr: np.ndarray = np.array([ln.split() for ln in lines], dtype=dtype)
    except ValueError as err:
        raise ShapeFileError(path, f"expected {columns} number(s) per line ({err})", "corrupt_mesh") from err
    if arr.ndim != 2 or arr.shape[1] != columns:
        raise ShapeFileError(path, f"expected {columns} number(s) per line", "corrupt_mesh")
    return arr


def _point_pieces(path: Path, config: IngestConfig) -> list[RawPiece]:
    points = _parse_numbers(path, _read_bytes(path, config), 3, float, config.max_points)
    try:
        valid_point_set(points, str(path))
    except MeshError as err:
        raise ShapeFileError(path, err.message.removeprefix(f"{path}: "), err.code) from err
    seg_path = _segment_file(path)
    if seg_path is None:
        raise ShapeFileError(path, f"no segment file {path.stem}{SEGMENT_SUFFIX} beside it (a point "
                             "cloud needs per-point segment ids to have components)", "no_segments")
    seg = _parse_numbers(seg_path, _read_bytes(seg_path, config), 1, np.int64, config.max_points)[:, 0]
    if len(seg) != len(points):
        raise ShapeFileError(seg_path, f"has {len(seg)} segment ids for {len(points)} points", "corrupt_mesh")
    pieces = []
    for sid in np.unique(seg).tolist():
        name = f"segment_{sid}"
        pieces.append(RawPiece(name=name, vertices=points[seg == sid], faces=np.zeros((0, 3), np.int64),
                               geometry_key=name, label=str(sid)))
    return pieces


def _category_from_path(path: Path) -> str:
    # The part benchmark keeps points in <category>/points/<id>.pts.
    parent = path.parent
    return parent.parent.name if parent.name == "points" else parent.name


def load_shape_file(path: Path, category: str | None = None, config: IngestConfig | None = None) -> RawShape:
    """Read one shape file into its pieces (see the module docstring for the formats).

    Category: ``category`` when given, else the sidecar's, else the folder's name.
    Shape id: the sidecar's, else the file's stem.

    Raises:
        ShapeFileError: naming the file, for anything unreadable, unsupported or refused.
    """
    path = Path(path)
    config = config or IngestConfig()
    suffix = path.suffix.lower()
    if suffix not in SHAPE_SUFFIXES:
        raise ShapeFileError(path, f"unsupported file type {path.suffix!r}; expected one of "
                             f"{', '.join(SHAPE_SUFFIXES)}", "unsupported_format")
    meta = read_sidecar(path) if suffix != POINT_SUFFIX else None
    pieces = _point_pieces(path, config) if suffix == POINT_SUFFIX else _mesh_pieces(path, config, meta)
    meta = meta or {}
    return RawShape(shape_id=meta.get("shape_id") or path.stem,
                    category=category or meta.get("category") or _category_from_path(path),
                    pieces=pieces, style=meta.get("style"), source=str(path))


def find_shape_files(folder: Path) -> list[Path]:
    """Every shape file under ``folder`` (recursively), in sorted order."""
    return sorted(p for p in Path(folder).rglob("*") if p.is_file() and p.suffix.lower() in SHAPE_SUFFIXES)


# --------------------------------------------------------------------------------------------
# Folder ingest.


@dataclass
class IngestReport:
    """What an ingest wrote and what it skipped (and why), one entry per file."""

    src: str
    out: str
    written: list[dict[str, Any]] = field(default_factory=list)
    skipped: list[dict[str, Any]] = field(default_factory=list)

    def table(self) -> str:
        """A plain-text summary: counts per category, then every skipped file with its reason."""
        per_cat = Counter(w["category"] for w in self.written)
        lines = [f"ingest {self.src} -> {self.out}: {len(self.written)} written, {len(self.skipped)} skipped",
                 f"{'category':<24}{'shapes':>8}{'pieces (mean)':>16}"]
        for cat in sorted(per_cat):
            pieces = [w["pieces"] for w in self.written if w["category"] == cat]
            lines.append(f"{cat:<24}{per_cat[cat]:>8}{np.mean(pieces):>16.1f}")
        if self.skipped:
            lines.append("skipped:")
            lines.extend(f"  {s['file']}: {s['reason']}" for s in self.skipped)
        return "\n".join(lines)

    def save(self, path: Path) -> None:
        Path(path).write_text(json.dumps(asdict(self), indent=1, sort_keys=True) + "\n")


_ID_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")


def _shape_ids(files: list[Path], src: Path) -> dict[Path, str]:
    """File stems as ids; where stems repeat (``model_normalized.obj``), the relative path."""
    stems = Counter(p.stem for p in files)
    ids = {}
    for p in files:
        raw = p.stem if stems[p.stem] == 1 else "-".join(p.relative_to(src).with_suffix("").parts)
        ids[p] = _ID_UNSAFE.sub("_", raw).strip("._") or "shape"
    return ids


def check_shape(shape: RawShape, config: IngestConfig) -> None:
    """Refuse shapes preprocessing cannot use (too few pieces), naming the source file."""
    if len(shape.pieces) < config.min_pieces:
        raise ShapeFileError(shape.source, f"has {len(shape.pieces)} component(s); a shape needs at "
                             f"least {config.min_pieces} to yield (assembly, complement) pairs",
                             "too_few_components")


def save_point_shape(shape: RawShape, folder: Path) -> Path:
    """Write a point-only shape as ``<id>.pts`` + ``<id>.seg`` (a GLB cannot hold it usefully)."""
    folder.mkdir(parents=True, exist_ok=True)
    pts_path = folder / f"{shape.shape_id}{POINT_SUFFIX}"
    seg_ids = [int(p.name.removeprefix("segment_")) if p.name.startswith("segment_") else i
               for i, p in enumerate(shape.pieces)]
    points = np.concatenate([p.vertices for p in shape.pieces])
    seg = np.concatenate([np.full(len(p.vertices), s) for p, s in zip(shape.pieces, seg_ids, strict=True)])
    pts_path.write_text("".join(f"{x!r} {y!r} {z!r}\n" for x, y, z in points.tolist()))
    (folder / f"{shape.shape_id}{SEGMENT_SUFFIX}").write_text("".join(f"{s}\n" for s in seg.tolist()))
    return pts_path


def ingest_folder(src: Path, out: Path, category: str | None = None,
                  config: IngestConfig | None = None) -> IngestReport:
    """Convert every shape file under ``src`` into the built-in format under ``out/<category>/``.

    Category: ``category`` when given, else the sidecar's, else the first sub-folder of ``src``
    holding the file (or ``src``'s own name for files directly inside it). Bad files are skipped
    with a reason each; the report is also written to ``out/ingest_report.json``.
    """
    from training.data.shape_io import save_shape  # written alongside; imported late on purpose

    src, out = Path(src), Path(out)
    config = config or IngestConfig()
    if not src.is_dir():
        raise FileNotFoundError(f"ingest source folder not found: {src}")
    report = IngestReport(src=str(src), out=str(out))
    files = find_shape_files(src)
    ids = _shape_ids(files, src)
    seen: dict[tuple[str, str], str] = {}
    for path in files:
        rel = path.relative_to(src)
        folder_cat = rel.parts[0] if len(rel.parts) > 1 else src.resolve().name
        try:
            meta = read_sidecar(path) if path.suffix.lower() != POINT_SUFFIX else None
            shape = load_shape_file(path, category or (meta or {}).get("category") or folder_cat, config)
            if shape.shape_id == path.stem:
                shape.shape_id = ids[path]
            check_shape(shape, config)
            key = (shape.category, shape.shape_id)
            if key in seen:
                raise ShapeFileError(path, f"shape id {shape.shape_id!r} already used by {seen[key]}",
                                     "duplicate")
            seen[key] = str(path)
            point_only = all(len(p.faces) == 0 for p in shape.pieces)
            written = save_point_shape(shape, out / shape.category) if point_only \
                else save_shape(shape, out / shape.category)
        except ShapeFileError as err:
            log.warning("skipped %s", err)
            report.skipped.append({"file": str(path), "reason": err.reason, "code": err.code})
            continue
        report.written.append({"file": str(path), "shape_id": shape.shape_id, "category": shape.category,
                               "pieces": len(shape.pieces), "path": str(written)})
    out.mkdir(parents=True, exist_ok=True)
    report.save(out / REPORT_NAME)
    return report
