"""The preprocessed dataset: components, contact graphs and cached point samples.

Written once by ``complementme data preprocess`` and read by training and evaluation, so that
training never re-samples meshes (normalise once and cache; sample per epoch).

Layout of a processed folder::

    processed/
      dataset.json     # seed, hash, thresholds, merge counts, per-shape metadata
      arrays.npz       # the concatenated arrays below (written deterministically)

Arrays (C = total components over all shapes, S = shapes, P = points cached per component):
    points        (C, P, 3) float16  area-weighted surface samples, centred at the component's
                                     bounding-box centre
    translation   (C, 3)    float32  bounding-box centre of the component in the shape frame
    area          (C,)      float32  surface area of the component
    shape_of      (C,)      int32    index of the owning shape
    first_comp    (S + 1,)  int64    components of shape s are first_comp[s]:first_comp[s + 1]
    edges         (E, 2)    int32    contact-graph edges as global component indices (i < j)
    mesh_vertices (Vt, 3)   float32  centred component meshes, concatenated
    mesh_faces    (Ft, 3)   int32    faces, indices local to their component's vertex block
    vertex_first  (C + 1,)  int64    vertex block of component c
    face_first    (C + 1,)  int64    face block of component c

Per-shape metadata in ``dataset.json`` (``shapes`` list, index = shape index): shape_id,
category, style (may be null), source, and ``labels``: one majority label per component (null
when unknown). Styles and labels are for evaluation only.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import zipfile
from collections.abc import Collection
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ARRAY_NAMES = (
    "points", "translation", "area", "shape_of", "first_comp", "edges",
    "mesh_vertices", "mesh_faces", "vertex_first", "face_first",
)
_FIXED_ZIP_TIME = (1980, 1, 1, 0, 0, 0)
GROUPED_KEY = "grouped_by_label"  # dataset.json key of a dataset grouped by label (evaluation only)


def save_npz_deterministic(path: Path, arrays: dict[str, np.ndarray], lzma: Collection[str] = ()) -> None:
    """Write arrays like ``np.savez_compressed`` but byte-identical for identical input.

    ``np.savez`` stamps the current time into the zip entries; re-running a seeded pipeline must
    reproduce its files exactly, so entries get a fixed timestamp and a sorted order. Arrays named
    in ``lzma`` are compressed with LZMA instead of deflate (``np.load`` reads either: zipfile
    decompresses both), for arrays where it pays for its slower decompression.
    """
    tmp = Path(str(path) + ".tmp")
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(arrays):
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(name + ".npy", date_time=_FIXED_ZIP_TIME)
            info.compress_type = zipfile.ZIP_LZMA if name in lzma else zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, buf.getvalue())
    os.replace(tmp, path)


def load_npz(path: Path) -> dict[str, np.ndarray]:
    """Load every array of an ``.npz`` file eagerly (no pickles)."""
    with np.load(path, allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


@dataclass
class ProcessedDataset:
    """Components and contact graphs of every kept shape (see module docstring for shapes)."""

    points: np.ndarray
    translation: np.ndarray
    area: np.ndarray
    shape_of: np.ndarray
    first_comp: np.ndarray
    edges: np.ndarray
    mesh_vertices: np.ndarray
    mesh_faces: np.ndarray
    vertex_first: np.ndarray
    face_first: np.ndarray
    shapes: list[dict[str, Any]] = field(default_factory=list)
    info: dict[str, Any] = field(default_factory=dict)

    @property
    def n_shapes(self) -> int:
        return len(self.first_comp) - 1

    @property
    def n_components(self) -> int:
        return len(self.translation)

    @property
    def grouped_by_label(self) -> bool:
        """Whether the components were grouped by their labels (``training.evaluate.grouped``):
        data made from labels, for the paper-protocol benchmark only, never for training."""
        return bool(self.info.get(GROUPED_KEY))

    def categories(self) -> list[str]:
        """The collection's category folders, sorted: the classes of g's category head.

        Folders are how users organise a collection, so naming them is fair supervision (part
        labels and styles stay unread). Training and export both take the list from here.
        """
        return sorted({str(meta.get("category", "")) for meta in self.shapes})

    def components_of(self, shape: int) -> np.ndarray:
        """Global component indices of one shape."""
        return np.arange(self.first_comp[shape], self.first_comp[shape + 1])

    def component_mesh(self, comp: int) -> tuple[np.ndarray, np.ndarray]:
        """Centred mesh of one component: ``(V, 3) float32`` vertices and ``(F, 3) int32`` faces."""
        v = self.mesh_vertices[self.vertex_first[comp]:self.vertex_first[comp + 1]]
        f = self.mesh_faces[self.face_first[comp]:self.face_first[comp + 1]]
        return v, f

    def component_label(self, comp: int) -> str | None:
        s = int(self.shape_of[comp])
        return self.shapes[s]["labels"][comp - int(self.first_comp[s])]

    def adjacency(self) -> list[set[int]]:
        """Neighbour sets over global component indices, from the contact-graph edges."""
        adj: list[set[int]] = [set() for _ in range(self.n_components)]
        for i, j in self.edges.tolist():
            adj[i].add(j)
            adj[j].add(i)
        return adj

    def save(self, folder: Path) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        save_npz_deterministic(folder / "arrays.npz", {n: getattr(self, n) for n in ARRAY_NAMES})
        meta = dict(self.info)
        meta["shapes"] = self.shapes
        meta["hash"] = self.content_hash()
        (folder / "dataset.json").write_text(json.dumps(meta, indent=1, sort_keys=True) + "\n")

    def content_hash(self) -> str:
        """SHA-256 over the arrays and shape metadata: identifies the data a model was trained on."""
        h = hashlib.sha256()
        for n in ARRAY_NAMES:
            a = np.ascontiguousarray(getattr(self, n))
            h.update(n.encode())
            h.update(str(a.dtype).encode() + str(a.shape).encode())
            h.update(a.tobytes())
        h.update(json.dumps(self.shapes, sort_keys=True).encode())
        return h.hexdigest()

    @classmethod
    def load(cls, folder: Path) -> ProcessedDataset:
        folder = Path(folder)
        arrays_path, meta_path = folder / "arrays.npz", folder / "dataset.json"
        for p in (arrays_path, meta_path):
            if not p.is_file():
                raise FileNotFoundError(
                    f"processed dataset file missing: {p} (run `complementme data preprocess`)")
        meta = json.loads(meta_path.read_text())
        shapes = meta.pop("shapes")
        arrays = load_npz(arrays_path)
        missing = [n for n in ARRAY_NAMES if n not in arrays]
        if missing:
            raise ValueError(f"{arrays_path}: missing arrays {missing}")
        return cls(**{n: arrays[n] for n in ARRAY_NAMES}, shapes=shapes, info=meta)

    def subset(self, shape_indices: np.ndarray | list[int]) -> ProcessedDataset:
        """A new dataset holding only the given shapes (e.g. a train or test split)."""
        shape_indices = [int(s) for s in shape_indices]
        comps = np.concatenate([self.components_of(s) for s in shape_indices]) if shape_indices \
            else np.zeros(0, dtype=np.int64)
        remap = -np.ones(self.n_components, dtype=np.int64)
        remap[comps] = np.arange(len(comps))
        first = np.zeros(len(shape_indices) + 1, dtype=np.int64)
        first[1:] = np.cumsum([self.first_comp[s + 1] - self.first_comp[s] for s in shape_indices])
        shape_of = np.repeat(np.arange(len(shape_indices), dtype=np.int32), np.diff(first))
        keep = (remap[self.edges[:, 0]] >= 0) & (remap[self.edges[:, 1]] >= 0) if len(self.edges) \
            else np.zeros(0, dtype=bool)
        edges = remap[self.edges[keep]].astype(np.int32).reshape(-1, 2)
        vblocks = [self.mesh_vertices[self.vertex_first[c]:self.vertex_first[c + 1]] for c in comps]
        fblocks = [self.mesh_faces[self.face_first[c]:self.face_first[c + 1]] for c in comps]
        vfirst = np.zeros(len(comps) + 1, dtype=np.int64)
        vfirst[1:] = np.cumsum([len(b) for b in vblocks])
        ffirst = np.zeros(len(comps) + 1, dtype=np.int64)
        ffirst[1:] = np.cumsum([len(b) for b in fblocks])
        return ProcessedDataset(
            points=self.points[comps], translation=self.translation[comps], area=self.area[comps],
            shape_of=shape_of, first_comp=first, edges=edges,
            mesh_vertices=np.concatenate(vblocks) if vblocks else np.zeros((0, 3), np.float32),
            mesh_faces=np.concatenate(fblocks) if fblocks else np.zeros((0, 3), np.int32),
            vertex_first=vfirst, face_first=ffirst,
            shapes=[self.shapes[s] for s in shape_indices], info=dict(self.info),
        )
