"""Shapes nobody here made: Sweet Home 3D furniture libraries as a folder for ``data ingest``.

Debian packages the free furniture libraries of Sweet Home 3D (``apt-get install
sweethome3d-furniture``: ``/usr/share/sweethome3d/furniture/*.sh3f``, CC0 and CC-BY models by
BlendSwap's contributors, Scopia, Reallusion, Andrew Kator and Jennifer Legaz). A ``.sh3f`` file is
a zip: ``PluginFurnitureCatalog.properties`` lists each model (``name#N``, ``model#N``, optional
``modelRotation#N``, ``creator#N``) and the OBJ files hold their geometry, split into groups by
their makers (often one group per material, not per functional part).

``export_library`` writes the models whose names say chair, table, sofa or lamp as OBJ files under
``<out>/<category>/`` in the canonical frame's orientation (y up, front +x; Sweet Home 3D's models
face +z once their ``modelRotation`` is applied), keeping only vertices, faces and groups. The
category comes from the library's own names (``category_of``): it files each model into a
category folder, which is how users organise a collection, and it is read to *measure* only
(``complementme evaluate-real``); part labels do not exist here. ``data ingest`` and ``data
preprocess`` then make a processed folder of them like any user collection.

The zip is read as untrusted input: only entries the catalog names are read, each at most
``max_entry_bytes``; nothing is extracted to disk but the OBJ text written here.
"""

from __future__ import annotations

import re
import zipfile
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from training.data.shape_io import write_sources

CATALOG_ENTRY = "PluginFurnitureCatalog.properties"

# Our categories by the words of a model's name, checked in this order. Names that hold one of the
# EXCLUDED words are other objects that share a word (a table fan, a street lamp, a wheelchair).
_CATEGORY_WORDS = (
    ("lamp", ("lamp",)),
    ("sofa", ("sofa", "couch", "settee", "loveseat")),
    ("chair", ("chair", "stool")),
    ("table", ("table", "desk")),
)
_EXCLUDED = ("wheelchair", "table fan", "tennis", "pool table", "football", "changing table", "bedside",
             "tablet", "ottoman")

# Sweet Home 3D's models face +z with y up; the canonical frame faces +x: a quarter turn about y.
_TO_CANONICAL = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])


class LibraryError(ValueError):
    """A furniture library that cannot be read (names the file and what is wrong)."""


@dataclass(frozen=True)
class Model:
    """One furniture model of a library: its catalog entry and where its OBJ lies in the zip."""

    library: str
    number: int
    name: str
    category: str
    entry: str                 # the OBJ's name inside the zip
    rotation: np.ndarray       # (3, 3) Sweet Home 3D's modelRotation (identity when absent)
    creator: str | None

    @property
    def slug(self) -> str:
        """A file name unique within the exported folder: library, catalog number, name."""
        words = re.sub(r"[^a-z0-9]+", "-", self.name.lower()).strip("-")
        return f"{self.library.lower()}-{self.number:03d}-{words}"


def category_of(name: str) -> str | None:
    """Our category for a model's name (chair, table, sofa, lamp), or None for anything else."""
    n = name.lower()
    if any(word in n for word in _EXCLUDED):
        return None
    for category, words in _CATEGORY_WORDS:
        if any(word in n for word in words):
            return category
    return None


def _properties(text: str) -> dict[int, dict[str, str]]:
    """``key#N=value`` lines grouped by N (Java properties as Sweet Home 3D writes them)."""
    items: dict[int, dict[str, str]] = {}
    for line in text.splitlines():
        m = re.match(r"^\s*(\w+)#(\d+)\s*=\s*(.*?)\s*$", line)
        if m:
            items.setdefault(int(m.group(2)), {})[m.group(1)] = m.group(3)
    return items


def _rotation(text: str | None, where: str) -> np.ndarray:
    if text is None:
        return np.eye(3)
    try:
        values = [float(v) for v in text.split()]
    except ValueError:
        values = []
    if len(values) != 9 or not np.all(np.isfinite(values)):
        raise LibraryError(f"{where}: modelRotation must be 9 numbers, found {text!r}")
    return np.asarray(values).reshape(3, 3)


def _entry(z: zipfile.ZipFile, path: Path, name: str, max_bytes: int) -> str:
    """One entry of a library as text, refused past ``max_bytes`` (checked before reading)."""
    info = z.getinfo(name)  # KeyError when missing: the callers say what named it
    if info.file_size > max_bytes:
        raise LibraryError(f"{path}: {name} is {info.file_size} bytes (limit {max_bytes})")
    return z.read(info).decode("latin-1")


def read_catalog(z: zipfile.ZipFile, path: Path, max_entry_bytes: int) -> Iterator[Model]:
    """The models of one open ``.sh3f`` library whose names map to a category, in catalog order."""
    try:
        text = _entry(z, path, CATALOG_ENTRY, max_entry_bytes)
    except KeyError as exc:
        raise LibraryError(f"{path}: not a Sweet Home 3D furniture library ({exc})") from exc
    for number, item in sorted(_properties(text).items()):
        name = item.get("name", "")
        category = category_of(name)
        entry = item.get("model", "").lstrip("/")
        if category is None or not entry.lower().endswith(".obj"):
            continue
        yield Model(library=path.stem, number=number, name=name, category=category, entry=entry,
                    rotation=_rotation(item.get("modelRotation"), f"{path} #{number}"),
                    creator=item.get("creator"))


def canonical_obj(text: str, rotation: np.ndarray) -> str:
    """An OBJ's vertices turned into the canonical orientation, with its faces and groups only.

    Normals, texture coordinates and materials are dropped (geometry is all ingest reads, and a
    material library would be a second file); face corners keep their vertex index.
    """
    turn = _TO_CANONICAL @ rotation
    out = []
    for line in text.splitlines():
        if line.startswith("v "):
            p = turn @ np.asarray([float(v) for v in line.split()[1:4]])
            out.append(f"v {p[0]:.6f} {p[1]:.6f} {p[2]:.6f}")
        elif line.startswith("f "):
            out.append("f " + " ".join(corner.split("/")[0] for corner in line.split()[1:]))
        elif line.startswith(("g ", "o ")):
            out.append(line.rstrip())
    return "\n".join(out) + "\n"


def export_library(paths: list[Path], out: Path, max_entry_bytes: int = 64 * 1024 * 1024) -> Counter[str]:
    """Write every chair, table, sofa and lamp of the libraries as ``<out>/<category>/<slug>.obj``.

    Also writes ``<out>/sources.json``: each file's library, catalog name and creator (the
    libraries' licences ask for attribution). Returns the count per category.
    """
    sources = []
    counts: Counter[str] = Counter()
    for path in paths:
        try:
            z = zipfile.ZipFile(path)
        except (zipfile.BadZipFile, OSError) as exc:
            raise LibraryError(f"{path}: not a Sweet Home 3D furniture library ({exc})") from exc
        with z:
            for model in list(read_catalog(z, path, max_entry_bytes)):
                try:
                    text = _entry(z, path, model.entry, max_entry_bytes)
                except KeyError as exc:
                    raise LibraryError(
                        f"{path}: #{model.number} names {model.entry}, which is not in it") from exc
                try:
                    obj = canonical_obj(text, model.rotation)
                except ValueError as exc:
                    raise LibraryError(f"{path}: {model.entry}: unreadable vertex ({exc})") from exc
                folder = out / model.category
                folder.mkdir(parents=True, exist_ok=True)
                (folder / f"{model.slug}.obj").write_text(obj)
                counts[model.category] += 1
                sources.append({"file": f"{model.category}/{model.slug}.obj", "library": model.library,
                                "name": model.name, "creator": model.creator})
    out.mkdir(parents=True, exist_ok=True)
    write_sources(out, sources)
    return counts
