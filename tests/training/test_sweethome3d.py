"""`complementme data sweethome3d` (training.data.sweethome3d): furniture libraries to OBJ folders."""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh
from orientation_check import top_behind_and_ahead
from typer.testing import CliRunner

from training.cli import app
from training.data.ingest import IngestConfig, ingest_folder
from training.data.sweethome3d import LibraryError, category_of, export_library


def _obj(groups: dict[str, trimesh.Trimesh]) -> str:
    """An OBJ with one group per mesh, with normals and texture corners as exporters write them."""
    lines, base = ["mtllib model.mtl"], 1
    for name, mesh in groups.items():
        lines.append(f"g {name}")
        lines.append("usemtl wood")
        lines += [f"v {x} {y} {z}" for x, y, z in mesh.vertices]
        lines.append("vn 0 1 0")
        lines += [f"f {a + base}/1/1 {b + base}/1/1 {c + base}/1/1" for a, b, c in mesh.faces]
        base += len(mesh.vertices)
    return "\n".join(lines) + "\n"


def _box(extents: tuple[float, float, float], centre: tuple[float, float, float]) -> trimesh.Trimesh:
    m = trimesh.creation.box(extents=extents)
    m.apply_translation(centre)
    return m


# A chair as Sweet Home 3D models it: y up, facing +z, so its back lies at negative z.
CHAIR = {"seat": _box((40, 5, 40), (0, 45, 0)), "back": _box((40, 45, 5), (0, 70, -18)),
         "legs": _box((5, 42, 5), (0, 21, 0))}
# A lamp modelled z up (its shade high in z): its catalog entry turns it y up.
LAMP = {"base": _box((20, 20, 3), (0, 0, 1.5)), "pole": _box((2, 2, 50), (0, 0, 28)),
        "shade": _box((25, 25, 15), (0, 0, 60))}


def _library(path: Path, extra: str = "", models: dict[str, str] | None = None) -> Path:
    props = "\n".join([
        "id=test", "name#1=Oak chair", "category#1=Living room", "model#1=/chair/chair.obj",
        "creator#1=Someone",
        "name#2=Table fan", "model#2=/fan/fan.obj",
        "name#3=Bookcase", "model#3=/bookcase/bookcase.obj",
        "name#4=Desk lamp", "model#4=/lamp/lamp.obj", "modelRotation#4=1 0 0 0 0 1 0 -1 0",
        extra])
    files = {"chair/chair.obj": _obj(CHAIR), "lamp/lamp.obj": _obj(LAMP), "fan/fan.obj": _obj(CHAIR),
             "bookcase/bookcase.obj": _obj(CHAIR), **(models or {})}
    with zipfile.ZipFile(path, "w") as z:
        z.writestr("PluginFurnitureCatalog.properties", props)
        for name, text in files.items():
            z.writestr(name, text)
    return path


def _groups(obj: Path) -> dict[str, np.ndarray]:
    """Vertices of each group of an OBJ written by the exporter."""
    verts, groups, current = [], {}, None
    for line in obj.read_text().splitlines():
        if line.startswith("v "):
            verts.append([float(v) for v in line.split()[1:]])
        elif line.startswith("g "):
            current = line[2:]
        elif line.startswith("f "):
            idx = [int(t) - 1 for t in line.split()[1:]]
            groups.setdefault(current, set()).update(idx)
    v = np.asarray(verts)
    return {g: v[sorted(i)] for g, i in groups.items()}


@pytest.mark.parametrize(("name", "category"), [
    ("Oak chair", "chair"), ("Armchair", "chair"), ("Bar stool", "chair"), ("Corner sofa", "sofa"),
    ("Futon couch", "sofa"), ("Coffee table", "table"), ("Wooden desk", "table"), ("Desk lamp", "lamp"),
    ("Table fan", None), ("Wheelchair", None), ("Bedside table", None), ("Bookcase", None)])
def test_names_map_to_categories(name: str, category: str | None) -> None:
    assert category_of(name) == category


def test_models_are_written_in_the_canonical_orientation(tmp_path: Path) -> None:
    counts = export_library([_library(tmp_path / "lib.sh3f")], tmp_path / "out")
    assert dict(counts) == {"chair": 1, "lamp": 1}
    chair = _groups(tmp_path / "out" / "chair" / "lib-001-oak-chair.obj")
    assert set(chair) == {"seat", "back", "legs"}
    # Front +x: the back, behind the seat in Sweet Home 3D's -z, is behind it in -x now.
    assert chair["back"][:, 0].mean() < chair["seat"][:, 0].mean() - 10
    assert np.ptp(chair["back"][:, 1]) == pytest.approx(45)   # heights stay on y
    lamp = _groups(tmp_path / "out" / "lamp" / "lib-004-desk-lamp.obj")
    # modelRotation turned the z-up lamp y up: the shade on top.
    assert lamp["shade"][:, 1].min() > lamp["pole"][:, 1].mean() > lamp["base"][:, 1].max()
    sources = json.loads((tmp_path / "out" / "sources.json").read_text())
    assert [s["name"] for s in sources] == ["Oak chair", "Desk lamp"]
    assert sources[0]["creator"] == "Someone" and sources[0]["library"] == "lib"


def test_exported_folder_ingests_with_its_groups_as_pieces(tmp_path: Path) -> None:
    export_library([_library(tmp_path / "lib.sh3f")], tmp_path / "src")
    report = ingest_folder(tmp_path / "src", tmp_path / "raw", None, IngestConfig())
    written = {w["category"]: w["pieces"] for w in report.written}
    assert written == {"chair": 3, "lamp": 3}, report.table()


def test_broken_libraries_are_refused_by_name(tmp_path: Path) -> None:
    (tmp_path / "plain.sh3f").write_text("not a zip")
    with pytest.raises(LibraryError, match=r"plain\.sh3f: not a Sweet Home 3D furniture library"):
        export_library([tmp_path / "plain.sh3f"], tmp_path / "out")
    missing = _library(tmp_path / "missing.sh3f", "name#5=Sofa\nmodel#5=/sofa/sofa.obj")
    with pytest.raises(LibraryError, match=r"#5 names sofa/sofa\.obj, which is not in it"):
        export_library([missing], tmp_path / "out2")
    rotated = _library(tmp_path / "rot.sh3f", "name#6=Sofa\nmodel#6=/chair/chair.obj\nmodelRotation#6=1 0 x")
    with pytest.raises(LibraryError, match="modelRotation must be 9 numbers"):
        export_library([rotated], tmp_path / "out3")
    with pytest.raises(LibraryError, match="limit 100"):
        export_library([_library(tmp_path / "big.sh3f")], tmp_path / "out4", max_entry_bytes=100)


def test_command_reads_a_folder_of_libraries(tmp_path: Path) -> None:
    (tmp_path / "libs").mkdir()
    _library(tmp_path / "libs" / "a.sh3f")
    result = CliRunner().invoke(app, ["data", "sweethome3d", str(tmp_path / "libs"),
                                      "--out", str(tmp_path / "out")])
    assert result.exit_code == 0, result.output
    assert "1 chair, 1 lamp from 1 libraries" in result.output
    empty = CliRunner().invoke(app, ["data", "sweethome3d", str(tmp_path / "out"),
                                     "--out", str(tmp_path / "o2")])
    assert empty.exit_code == 2 and "no .sh3f library" in empty.output


DEBIAN_LIBRARIES = Path("/usr/share/sweethome3d/furniture")


@pytest.mark.skipif(not DEBIAN_LIBRARIES.is_dir(),
                    reason="no furniture libraries: .ci/run installs Debian's sweethome3d-furniture")
def test_debians_libraries_are_filed_as_docs_benchmark_real_says(tmp_path: Path) -> None:
    counts = export_library(sorted(DEBIAN_LIBRARIES.glob("*.sh3f")), tmp_path)
    assert dict(counts) == {"chair": 63, "lamp": 20, "sofa": 23, "table": 45}  # docs/benchmark-real
    # Front +x: a chair's back (the top 30% of its height) lies behind its centre.
    behind, ahead = top_behind_and_ahead(tmp_path / "chair", 0.3)
    assert behind >= 50 and ahead <= 3, (behind, ahead)
