"""Import a folder of shapes into a running catalog: each shape's components become parts.

Every file is read as the trainer reads user shapes (``training.data.ingest.load_shape_file``:
scene-graph leaves, or connected components of a single mesh, never following references to
other files) and merged into components exactly as the training data was (Section 4:
``training.data.preprocess.preprocess_shape``, in the shape's unit-radius frame). Each component
is then added as one part of the shape, placed where it sits in the shape (the service takes its
bounding-box centre as its translation), labelled with its majority label.

Parts go to the catalog through a ``PartSink``: the HTTP API of a running service (``HttpSink``,
needs the API key) or the data folder directly (``LocalSink``: loads the artifacts in this
process and writes as a server would; a server on the same folder picks the parts up).

Re-running an import continues where it stopped: a shape whose parts are all in the catalog is
skipped, one that is partly there gets its remaining components (components come out in the
same order every time, and part ids number them).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import trimesh
from tqdm import tqdm

from service.geometry.frames import Frame
from training.data.ingest import IngestConfig, ShapeFileError, find_shape_files, load_shape_file
from training.data.preprocess import PreprocessConfig, Rejected, preprocess_shape

log = logging.getLogger(__name__)


@dataclass
class Component:
    """One component of an imported shape, in the shape's canonical (unit-radius) frame.

    Shapes:
        vertices: (V, 3) float32, where the component sits in the shape; faces: (F, 3) int32.
    """

    vertices: np.ndarray
    faces: np.ndarray
    label: str | None


@dataclass
class ImportReport:
    """What an import added, what it found already there, and what it skipped (and why)."""

    added: list[dict[str, Any]] = field(default_factory=list)      # {"file", "part_id"}
    present: list[dict[str, Any]] = field(default_factory=list)    # {"file", "shape_id", "parts"}
    skipped: list[dict[str, Any]] = field(default_factory=list)    # {"file", "reason"}

    def table(self) -> str:
        lines = [f"{len(self.added)} part(s) added from {len({a['file'] for a in self.added})} file(s); "
                 f"{len(self.present)} shape(s) already in the catalog; {len(self.skipped)} file(s) skipped"]
        if self.skipped:
            lines.append("skipped:")
            lines.extend(f"  {s['file']}: {s['reason']}" for s in self.skipped)
        return "\n".join(lines)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


class PartSink(Protocol):
    """Where imported parts go."""

    def present(self, shape_id: str) -> int:
        """Parts of ``shape_id`` already in the catalog."""

    def add(self, mesh: bytes, filename: str, category: str, **fields: Any) -> str:
        """Add one part (a PLY mesh); returns its part id. Raises ``PartRefusedError`` if refused."""


class PartRefusedError(RuntimeError):
    """The catalog refused a part (bad mesh, bad name, not allowed); the message says why."""


def shape_components(path: Path, category: str | None, up_axis: str = "y",
                     ingest: IngestConfig | None = None, preprocess: PreprocessConfig | None = None
                     ) -> tuple[str, str, str | None, list[Component]]:
    """Read one file and merge its pieces into components (Section 4).

    Returns:
        (shape id, category, style, components in the unit-radius frame of the shape).

    Raises:
        ShapeFileError: unreadable, refused or unusable file (the message says why).
    """
    shape = load_shape_file(path, category, ingest or IngestConfig(ignore_obj_materials=True))
    rotation = Frame(up_axis=up_axis).rotation  # type: ignore[arg-type]
    for piece in shape.pieces:
        piece.vertices = np.asarray(piece.vertices, dtype=np.float64) @ rotation.T
        if len(piece.faces) == 0:
            raise ShapeFileError(path, "holds points without triangles; catalog parts need a surface",
                                 "no_surface")
    config = preprocess or PreprocessConfig(min_components=1, max_components=64)
    result = preprocess_shape(shape, config)
    if isinstance(result, Rejected):
        raise ShapeFileError(path, result.reason, result.code)
    parts = zip(result.meshes, result.translation, result.labels, strict=True)
    comps = [Component((v + t).astype(np.float32), f.astype(np.int32), label) for (v, f), t, label in parts]
    return shape.shape_id, shape.category, shape.style, comps


def ply_bytes(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    """A binary PLY of a triangle mesh (what the sinks upload)."""
    data = trimesh.Trimesh(vertices=vertices, faces=faces, process=False).export(file_type="ply")
    return data.encode() if isinstance(data, str) else bytes(data)


def import_folder(folder: Path, sink: PartSink, category: str | None = None, up_axis: str = "y",
                  progress: bool = True) -> ImportReport:
    """Add every shape file under ``folder`` to the catalog through ``sink`` (see the module doc)."""
    files = find_shape_files(folder)
    if not files:
        raise FileNotFoundError(f"no shape files (.obj .glb .gltf .ply .off .stl) under {folder}")
    report = ImportReport()
    for path in tqdm(files, desc="catalog add", unit="file", disable=not progress):
        rel = path.relative_to(folder)
        folder_cat = rel.parts[0] if len(rel.parts) > 1 else None
        try:
            shape_id, cat, style, comps = shape_components(path, category or folder_cat, up_axis)
        except ShapeFileError as exc:
            report.skipped.append({"file": str(path), "reason": exc.reason})
            log.warning("skipped %s", exc)
            continue
        done = sink.present(shape_id)
        if done >= len(comps):
            report.present.append({"file": str(path), "shape_id": shape_id, "parts": done})
            continue
        for k in range(done, len(comps)):
            c = comps[k]
            try:
                part_id = sink.add(ply_bytes(c.vertices, c.faces), f"{path.stem}-{k}.ply", cat,
                                   shape_id=shape_id, name=f"{path.name} component {k}", style=style,
                                   label=c.label)
            except PartRefusedError as exc:
                report.skipped.append({"file": str(path), "reason": f"component {k}: {exc}"})
                log.warning("%s: component %d refused: %s", path, k, exc)
                break  # later components would get the wrong numbers; re-run after fixing
            report.added.append({"file": str(path), "part_id": part_id})
    return report


class HttpSink:
    """Parts go to a running service through its API (``POST /parts``)."""

    def __init__(self, client: Any):
        self.client = client

    def present(self, shape_id: str) -> int:
        from service.serve.client import ClientError

        try:
            return int(self.client.parts(shape_id=shape_id, limit=1)["total"])
        except ClientError as exc:
            if exc.code == "unknown_shape":
                return 0
            raise

    def add(self, mesh: bytes, filename: str, category: str, **fields: Any) -> str:
        from service.serve.client import ClientError

        try:
            return str(self.client.add_part(mesh, filename, category, **fields)["part_id"])
        except ClientError as exc:
            if exc.status is not None and 400 <= exc.status < 500 and exc.status not in (401, 403):
                raise PartRefusedError(f"{exc.code}: {exc.message}") from None
            raise  # no key, read-only server, unreachable: stop the whole import


class LocalSink:
    """Parts go straight into a data folder, computed with the artifacts loaded in this process."""

    def __init__(self, artifacts: Path, data_dir: Path):
        from service.artifacts.loading import load_artifacts
        from service.catalog_store.writer import CatalogWriter
        from service.settings import Settings
        from service.suggest.engine import SuggestionEngine

        self.settings = Settings(artifacts=artifacts, data_dir=data_dir, catalog_poll_seconds=0)
        loaded = load_artifacts(artifacts, verify_checksums=self.settings.verify_checksums)
        self.writer = CatalogWriter.open(self.settings, SuggestionEngine(loaded, self.settings),
                                         publish=lambda snapshot: None)

    def close(self) -> None:
        self.writer.close()

    def present(self, shape_id: str) -> int:
        return sum(p.record["shape_id"] == shape_id for p in self.writer.parts.values())

    def add(self, mesh: bytes, filename: str, category: str, **fields: Any) -> str:
        from service.catalog_store.part_prep import prepare_part
        from service.errors import ServiceError

        s, engine = self.settings, self.writer.engine
        try:
            part = prepare_part(
                mesh, "ply", name=filename, frame=Frame(), networks=engine.networks,
                n_points=engine.artifacts.n_points, placement_points=engine.artifacts.placement_points,
                preview_points=self.writer.builder.n_points, seed=s.seed,
                max_vertices=s.max_mesh_vertices, max_faces=s.max_mesh_faces, max_nodes=s.max_mesh_nodes,
                max_nesting=s.max_mesh_nesting, max_extent=s.max_part_extent,
                category=category, part_name=fields.get("name"), style=fields.get("style"),
                label=fields.get("label"), model_version=engine.model_version)
            return self.writer.add(part, fields.get("shape_id")).part_id
        except ServiceError as exc:
            raise PartRefusedError(f"{exc.code}: {exc.message}") from None
