"""The part catalog: records from ``catalog.json`` and arrays from ``catalog.npz``, checked together.

Everything the request path needs per part is held as arrays indexed by catalog row (= FAISS
row), so filters, duplicate collapse and placement are numpy indexing, not Python loops.
"""

from __future__ import annotations

import json
import logging
import zipfile
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np

from service.artifacts.layout import CATALOG_ARRAY_NAMES, CATALOG_FIELDS, ArtifactError
from service.errors import InputError, NotFoundError
from service.geometry.mesh import resample_points

log = logging.getLogger(__name__)


@dataclass
class Catalog:
    """The catalog parts, with lookups by id and the arrays of catalog.npz.

    Shapes (P parts, D embedding size, Fp part-feature size, S points per part):
        translations, bbox_min, bbox_max: (P, 3) float32, canonical frame of the source shape.
        embeddings: (P, D) float32.   part_features: (P, Fp) float32.
        points: (P, S, 3) float16, centred at the part's bounding-box centre.
        category_of, shape_of: (P,) int32 codes into ``categories`` and ``shape_ids``.
        group: (P,) int64, the root part of each part's near-duplicate group (itself if none).
        group_size: (P,) int64, parts in that group.
    """

    records: list[dict[str, Any]]
    embeddings: np.ndarray
    part_features: np.ndarray
    points: np.ndarray
    mesh_vertices: np.ndarray
    mesh_faces: np.ndarray
    vertex_first: np.ndarray
    face_first: np.ndarray
    part_ids: list[str] = field(init=False)
    index_of: dict[str, int] = field(init=False)
    categories: list[str] = field(init=False)
    category_of: np.ndarray = field(init=False)
    shape_ids: list[str] = field(init=False)
    shape_of: np.ndarray = field(init=False)
    translations: np.ndarray = field(init=False)
    bbox_min: np.ndarray = field(init=False)
    bbox_max: np.ndarray = field(init=False)
    group: np.ndarray = field(init=False)
    group_size: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        recs = self.records
        self.part_ids = [r["part_id"] for r in recs]
        self.index_of = {pid: i for i, pid in enumerate(self.part_ids)}
        self.categories = sorted({r["category"] for r in recs})
        cat_code = {c: i for i, c in enumerate(self.categories)}
        self.category_of = np.array([cat_code[r["category"]] for r in recs], dtype=np.int32)
        self.shape_ids = sorted({r["shape_id"] for r in recs})
        shape_code = {s: i for i, s in enumerate(self.shape_ids)}
        self.shape_of = np.array([shape_code[r["shape_id"]] for r in recs], dtype=np.int32)
        self.translations = np.array([r["translation"] for r in recs], dtype=np.float32).reshape(-1, 3)
        self.bbox_min = np.array([r["bbox_min"] for r in recs], dtype=np.float32).reshape(-1, 3)
        self.bbox_max = np.array([r["bbox_max"] for r in recs], dtype=np.float32).reshape(-1, 3)
        self.group = _duplicate_roots([r["duplicate_of"] for r in recs])
        self.group_size = np.bincount(self.group, minlength=len(recs))[self.group]

    def __len__(self) -> int:
        return len(self.records)

    @property
    def n_points(self) -> int:
        """Points stored per part (S)."""
        return int(self.points.shape[1])

    def lookup(self, part_id: str) -> int:
        """Catalog row of a part id; ``NotFoundError`` naming the id if unknown."""
        try:
            return self.index_of[part_id]
        except KeyError:
            raise NotFoundError("unknown_part", f"part {part_id!r} is not in the catalog") from None

    def category_codes(self, names: list[str]) -> np.ndarray:
        """Codes of category names; ``InputError`` listing the known ones if a name is unknown."""
        codes = []
        for name in names:
            try:
                codes.append(self.categories.index(name))
            except ValueError:
                raise InputError("unknown_category", f"unknown category {name!r}; known categories: "
                                 f"{', '.join(self.categories)}") from None
        return np.array(codes, dtype=np.int32)

    def shape_code(self, shape_id: str) -> int:
        """Code of a source shape id; ``NotFoundError`` if no catalog part comes from it."""
        i = int(np.searchsorted(self.shape_ids, shape_id))
        if i >= len(self.shape_ids) or self.shape_ids[i] != shape_id:
            raise NotFoundError("unknown_shape", f"shape {shape_id!r} has no parts in the catalog")
        return i

    def mesh(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Centred mesh of part ``i``: ``(V, 3) float32`` vertices and ``(F, 3) int32`` faces."""
        v = self.mesh_vertices[self.vertex_first[i]:self.vertex_first[i + 1]]
        f = self.mesh_faces[self.face_first[i]:self.face_first[i + 1]]
        return v, f

    def part_points(self, i: int) -> np.ndarray:
        """Centred point samples of part ``i`` as ``(S, 3) float32``."""
        return self.points[i].astype(np.float32)

    def part_samples(self, rows: np.ndarray, n: int) -> np.ndarray:
        """The first ``n`` centred samples (a random subset: they are drawn at random) of many parts.

        Shapes:
            rows: (M,) -> (M, min(n, S), 3) float32.
        """
        return self.points[np.asarray(rows, dtype=np.int64), :n].astype(np.float32)


def _duplicate_roots(duplicate_of: list[int | None]) -> np.ndarray:
    """Follow ``duplicate_of`` links to each part's root, so chains collapse into one group."""
    n = len(duplicate_of)
    parent = np.array([i if d is None else d for i, d in enumerate(duplicate_of)], dtype=np.int64)
    root = parent.copy()
    for _ in range(max(1, n.bit_length() + 1)):  # pointer jumping: log2(chain length) steps
        root = root[root]
    if np.any(parent[root] != root):
        raise ArtifactError("duplicate_of links form a cycle")
    return root


def _read_records(path: Path) -> list[dict[str, Any]]:
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ArtifactError(f"{path}: not valid JSON ({exc})") from exc
    # A bare list of records, or an object holding them under "parts".
    records = data.get("parts") if isinstance(data, dict) else data
    if not isinstance(records, list):
        raise ArtifactError(f"{path}: expected a list of part records (or {{'parts': [...]}})")
    for i, rec in enumerate(records):
        if not isinstance(rec, dict):
            raise ArtifactError(f"{path}: record {i} is not an object")
        missing = [f for f in CATALOG_FIELDS if f not in rec]
        if missing:
            raise ArtifactError(f"{path}: record {i} lacks field(s) {', '.join(missing)}")
        for key in ("translation", "bbox_min", "bbox_max"):
            vec = rec[key]
            if not (isinstance(vec, list) and len(vec) == 3
                    and all(isinstance(x, (int, float)) for x in vec)):
                raise ArtifactError(f"{path}: record {i} field {key!r} must be [x, y, z], found {vec!r}")
        dup = rec["duplicate_of"]
        if dup is not None and not (isinstance(dup, int) and 0 <= dup < len(records) and dup != i):
            raise ArtifactError(f"{path}: record {i} has duplicate_of {dup!r}, not another part's index")
    ids = [r["part_id"] for r in records]
    if len(set(ids)) != len(ids):
        raise ArtifactError(f"{path}: part_id values are not unique")
    return records


def _read_arrays(path: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [n for n in CATALOG_ARRAY_NAMES if n not in data.files]
            if missing:
                raise ArtifactError(f"{path}: missing array(s) {', '.join(missing)}")
            return {n: data[n] for n in CATALOG_ARRAY_NAMES}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise ArtifactError(f"{path}: cannot read arrays ({exc})") from exc


def _expect(path: Path, name: str, arr: np.ndarray, shape: tuple[int | None, ...], kinds: str) -> None:
    """Check one array's shape (None = any) and dtype kind; raise naming file and array."""
    ok = arr.ndim == len(shape) and all(s is None or s == a for s, a in zip(shape, arr.shape, strict=False))
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ArtifactError(f"{path}: array {name!r} has shape {arr.shape}, expected {want}")
    if arr.dtype.kind not in kinds:
        raise ArtifactError(f"{path}: array {name!r} has dtype {arr.dtype}, expected kind {kinds!r}")


def load_catalog(json_path: Path, npz_path: Path, part_count: int, embedding_dim: int) -> Catalog:
    """Read the catalog files and check them against each other and the manifest's counts."""
    records = _read_records(json_path)
    if len(records) != part_count:
        raise ArtifactError(f"{json_path}: {len(records)} parts, but the manifest says "
                            f"part_count={part_count}")
    a = _read_arrays(npz_path)
    P = part_count
    _expect(npz_path, "embeddings", a["embeddings"], (P, embedding_dim), "f")
    _expect(npz_path, "part_features", a["part_features"], (P, None), "f")
    _expect(npz_path, "points", a["points"], (P, None, 3), "f")
    _expect(npz_path, "mesh_vertices", a["mesh_vertices"], (None, 3), "f")
    _expect(npz_path, "mesh_faces", a["mesh_faces"], (None, 3), "iu")
    _expect(npz_path, "vertex_first", a["vertex_first"], (P + 1,), "iu")
    _expect(npz_path, "face_first", a["face_first"], (P + 1,), "iu")
    for name, total in (("vertex_first", len(a["mesh_vertices"])), ("face_first", len(a["mesh_faces"]))):
        first = a[name]
        if first[0] != 0 or first[-1] != total or np.any(np.diff(first) < 0):
            raise ArtifactError(f"{npz_path}: {name!r} must rise from 0 to {total}")
    for name in ("embeddings", "part_features", "points", "mesh_vertices"):
        if not np.all(np.isfinite(a[name])):
            raise ArtifactError(f"{npz_path}: array {name!r} holds NaN or infinite values")
    # Faces index their own part's vertex block: check all of them at once.
    faces = a["mesh_faces"].astype(np.int64)
    owner = np.repeat(np.arange(P), np.diff(a["face_first"]))
    n_verts = np.diff(a["vertex_first"])[owner]
    if faces.size and (faces.min() < 0 or np.any(faces.max(axis=1) >= n_verts)):
        raise ArtifactError(f"{npz_path}: mesh_faces index vertices outside their part's block")
    try:
        return _build_catalog(records, a)
    except ArtifactError as exc:
        raise ArtifactError(f"{json_path}: {exc}") from exc


def _build_catalog(records: list[dict[str, Any]], a: dict[str, np.ndarray]) -> Catalog:
    return Catalog(
        records=records,
        embeddings=np.ascontiguousarray(a["embeddings"], dtype=np.float32),
        part_features=np.ascontiguousarray(a["part_features"], dtype=np.float32),
        points=a["points"],
        mesh_vertices=a["mesh_vertices"].astype(np.float32, copy=False),
        mesh_faces=a["mesh_faces"].astype(np.int32, copy=False),
        vertex_first=a["vertex_first"].astype(np.int64, copy=False),
        face_first=a["face_first"].astype(np.int64, copy=False),
    )


def split_shapes(catalog: Catalog, split: str, fallback: bool = True) -> dict[str, list[int]]:
    """Rows of each multi-part shape of one split (records carry ``split``; added parts have
    ``"added"``); a catalog without that split gives every multi-part shape (nothing when
    ``fallback`` is off)."""

    def shapes_with(keep: Any) -> dict[str, list[int]]:
        rows_of: dict[str, list[int]] = {}
        for i, rec in enumerate(catalog.records):
            if keep(rec):
                rows_of.setdefault(rec["shape_id"], []).append(i)
        return {s: rows for s, rows in rows_of.items() if len(rows) >= 2}

    own = shapes_with(lambda rec: rec.get("split", split) == split)
    return own or (shapes_with(lambda rec: True) if fallback else {})


def drawn_training_shapes(catalog: Catalog, category: str | None, max_shapes: int, seed: int = 0,
                          rows_of: dict[str, list[int]] | None = None) -> list[tuple[str, list[int]]]:
    """The catalog's training shapes of ``category`` (every category: None) as (shape id, rows),
    sorted by id, at most ``max_shapes`` of them (a seeded draw, kept in id order): what the
    assembly reads of the data, bounded so that a catalog grown by writes costs no more than the
    shipped one. ``rows_of``: ``split_shapes(catalog, "train")`` when the caller has it already
    (a walk over every record: the warm-up reads eighteen categories' worth from one)."""
    code = None if category is None else catalog.category_codes([category])[0]
    if rows_of is None:
        rows_of = split_shapes(catalog, "train")
    shapes = [(sid, rows) for sid, rows in sorted(rows_of.items())
              if code is None or catalog.category_of[rows[0]] == code]
    if len(shapes) > max_shapes:
        pick = np.random.default_rng(seed).choice(len(shapes), size=max_shapes, replace=False)
        shapes = [shapes[j] for j in np.sort(pick)]
    return shapes


def _assembly_cloud(catalog: Catalog, rows: list[int], n_points: int, rng: np.random.Generator) -> np.ndarray:
    """The stored samples of ``rows`` placed with their translations, resampled to ``n_points``."""
    pts = np.concatenate([catalog.part_points(i) + catalog.translations[i] for i in rows])
    return resample_points(pts, n_points, int(rng.integers(2**31))).astype(np.float32)


def partial_assemblies(catalog: Catalog, count: int, n_points: int, seed: int = 0,
                       split: str = "test") -> list[np.ndarray]:
    """Queries like the service's: shapes of one split, each with one random part left out.

    Points come from the catalog's stored part samples (placed with their translations),
    resampled to ``n_points``; shapes are drawn without replacement (seeded). A catalog without
    that split gives any multi-part shapes.

    Shapes:
        returns ``count`` arrays of (n_points, 3) float32 (fewer if the catalog has fewer shapes).
    """
    rng = np.random.default_rng(seed)
    rows_of = split_shapes(catalog, split)
    shapes = sorted(rows_of)
    out = []
    for j in rng.permutation(len(shapes))[:count]:
        rows = rows_of[shapes[j]]
        drop = rows[int(rng.integers(len(rows)))]
        out.append(_assembly_cloud(catalog, [i for i in rows if i != drop], n_points, rng))
    return out


def partial_assembly_bank(catalog: Catalog, per_shape: int, n_points: int, seed: int = 0,
                          split: str = "train") -> tuple[list[np.ndarray], np.ndarray]:
    """``per_shape`` partial assemblies of every multi-part shape of one split, and their shapes.

    The first of each shape leaves one random part out, the second is one random part alone (the
    page's usual start), the others keep a random number (1 to all but one) of random parts: lone
    parts and near-complete shapes are both there, as in requests. Labels are never read.

    Shapes:
        returns (shapes * per_shape) arrays of (n_points, 3) float32, and (shapes * per_shape,)
        int64 shape numbers (sorted shape ids' positions).
    """
    rng = np.random.default_rng(seed)
    rows_of = split_shapes(catalog, split)
    clouds, groups = [], []
    for j, shape in enumerate(sorted(rows_of)):
        rows = rows_of[shape]
        for t in range(per_shape):
            keep = len(rows) - 1 if t == 0 else 1 if t == 1 else int(rng.integers(1, len(rows)))
            chosen = sorted(int(i) for i in rng.choice(rows, size=keep, replace=False))
            clouds.append(_assembly_cloud(catalog, chosen, n_points, rng))
            groups.append(j)
    return clouds, np.asarray(groups, dtype=np.int64)


@lru_cache(maxsize=1 << 16)
def _part_path(part_id: str) -> str:
    return "/parts/" + quote(part_id, safe="/")


def part_links(part_id: str) -> dict[str, str]:
    """Links to a part's record, mesh and points (ids keep their slash; other characters quoted).

    The API's link format, owned here so that the catalog writer (service.catalog_store.writer) and the
    HTTP layer share it without the core importing the HTTP layer.
    """
    base = _part_path(part_id)
    return {"part": base, "mesh": base + "/mesh", "points": base + "/points"}
