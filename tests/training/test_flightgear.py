"""`complementme data flightgear` (training.data.flightgear): AC3D aircraft to OBJ folders."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from orientation_check import top_behind_and_ahead
from typer.testing import CliRunner

from training.cli import app
from training.data.flightgear import MAX_DEPTH, AC3DError, export_aircraft, read_ac3d
from training.data.ingest import IngestConfig, ingest_folder


def _poly(name: str, centre: tuple[float, float, float], size: tuple[float, float, float],
          kids: str = "", n_kids: int = 0, loc: str = "") -> str:
    """A box as an AC3D poly object: 8 vertices, 6 quads."""
    c, s = np.asarray(centre), np.asarray(size) / 2
    corners = [c + s * np.array([x, y, z]) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    lines = ["OBJECT poly", f'name "{name}"', *([loc] if loc else []), "numvert 8",
             *[f"{x} {y} {z}" for x, y, z in corners], "numsurf 6"]
    for q in quads:
        lines += ["SURF 0x10", "mat 0", "refs 4", *[f"{i} 0 0" for i in q]]
    lines.append(f"kids {n_kids}")
    return "\n".join(lines) + "\n" + kids


# An AC3D plane: y up, nose towards -x. The wings are a kid of the fuselage, placed by its loc.
HEADER = "AC3Db\nMATERIAL \"m\" rgb 1 1 1 amb 0 0 0 emis 0 0 0 spec 0 0 0 shi 0 trans 0\n"
PLANE = HEADER + "OBJECT world\nkids 4\n" + (
    _poly("fuselage", (0, 0, 0), (10, 1, 1), n_kids=1,
          kids=_poly("wings", (0, 0, 0), (2, 0.2, 12), loc="loc 1 0 0"))
    + _poly("tail", (4.5, 1.5, 0), (1, 2, 0.2))
    + _poly("nav-light", (0, 0, 6), (0.1, 0.1, 0.1))
    + _poly("engines", (-1, -0.8, 0), (2, 0.6, 8)))


def test_objects_are_read_with_their_parents_placement(tmp_path: Path) -> None:
    (tmp_path / "plane.ac").write_text(PLANE)
    objects = {o.name: o for o in read_ac3d(tmp_path / "plane.ac")}
    assert set(objects) == {"fuselage", "wings", "tail", "nav-light", "engines"}
    assert len(objects["wings"].triangles) == 12                   # 6 quads fanned
    assert objects["wings"].vertices[:, 0].mean() == pytest.approx(1.0)  # its loc in the fuselage


def test_models_are_written_front_plus_x_without_lights(tmp_path: Path) -> None:
    root = tmp_path / "Aircraft" / "Test" / "Models"
    root.mkdir(parents=True)
    (root / "plane.ac").write_text(PLANE)
    (root / "blob.ac").write_text(HEADER + "OBJECT world\nkids 1\n" + _poly("body", (0, 0, 0), (1, 1, 1)))
    written, skipped = export_aircraft(tmp_path / "Aircraft", tmp_path / "out")
    assert (written, skipped) == (1, [])   # the blob has one part object: not an assembly
    text = (tmp_path / "out" / "airplane" / "fg-test-plane.obj").read_text()
    groups = [line[2:] for line in text.splitlines() if line.startswith("g ")]
    assert groups == ["fuselage", "wings", "tail", "engines"]
    v = np.array([[float(x) for x in line.split()[1:]] for line in text.splitlines()
                  if line.startswith("v ")])
    tail = v[16:24]                          # the third group's vertices
    assert tail[:, 0].mean() < 0 < tail[:, 1].mean()   # the tail behind (front +x) and up
    assert json.loads((tmp_path / "out" / "sources.json").read_text())[0]["objects"] == 4
    report = ingest_folder(tmp_path / "out", tmp_path / "raw", None, IngestConfig())
    assert [w["pieces"] for w in report.written] == [4]


@pytest.mark.parametrize(("text", "message"), [
    ("solid x\n", "not an AC3D file"),
    ("AC3Db\nOBJECT world\nkids 1\nOBJECT poly\nnumvert 5\n0 0 0\n", "numvert 5 is more than"),
    ("AC3Db\nOBJECT world\nkids 1\nOBJECT poly\nnumvert 1\n0 0 x\n", "vertex: not numbers"),
    ("AC3Db\nOBJECT world\nkids 1\nOBJECT poly\nnumvert 1\n0 0 0\nnumsurf 1\nSURF 0\nrefs 3\n"
     "0 0 0\n1 0 0\n2 0 0\nkids 0\n", "refers to a vertex the object does not have"),
    ("AC3Db\nOBJECT world\nkids 1\nOBJECT poly\nnumvert 1\n0 0 0\n", "the file ends inside an object"),
    ("AC3Db\n" + "OBJECT poly\nkids 1\n" * (MAX_DEPTH + 2), "nest deeper than"),
])
def test_broken_files_are_refused_with_their_line(tmp_path: Path, text: str, message: str) -> None:
    (tmp_path / "bad.ac").write_text(text)
    with pytest.raises(AC3DError, match=message):
        read_ac3d(tmp_path / "bad.ac")


def test_a_tree_announcing_more_kids_than_it_holds_keeps_what_it_has(tmp_path: Path) -> None:
    (tmp_path / "short.ac").write_text(HEADER + "OBJECT world\nkids 3\n" + _poly("a", (0, 0, 0), (1, 1, 1)))
    assert [o.name for o in read_ac3d(tmp_path / "short.ac")] == ["a"]


def test_command_skips_unreadable_files_and_names_them(tmp_path: Path) -> None:
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "plane.ac").write_text(PLANE)
    (tmp_path / "m" / "bad.ac").write_text("AC3Db\nOBJECT world\nkids 1\nOBJECT poly\nnumvert 1\n")
    result = CliRunner().invoke(app, ["data", "flightgear", str(tmp_path / "m"),
                                      "--out", str(tmp_path / "o")])
    assert result.exit_code == 0, result.output
    assert "1 airplanes, 1 files unreadable" in result.output and "bad.ac" in result.output
    missing = CliRunner().invoke(app, ["data", "flightgear", str(tmp_path / "nowhere")])
    assert missing.exit_code == 2 and "is not a folder" in missing.output


DEBIAN_AIRCRAFT = Path("/usr/share/games/flightgear/AI/Aircraft")


@pytest.mark.skipif(not DEBIAN_AIRCRAFT.is_dir(),
                    reason="no FlightGear AI aircraft: .ci/run installs Debian's flightgear-data-ai")
def test_debians_aircraft_are_written_as_docs_benchmark_real_says(tmp_path: Path) -> None:
    written, skipped = export_aircraft(DEBIAN_AIRCRAFT, tmp_path)
    assert written == 100 and len(skipped) == 2, skipped  # docs/benchmark-real: the two Dromaders
    # Front +x: a plane's highest points (its fin, the top 20% of its height) lie behind its centre.
    behind, ahead = top_behind_and_ahead(tmp_path / "airplane", 0.2)
    assert behind >= 75 and ahead <= 10, (behind, ahead)
