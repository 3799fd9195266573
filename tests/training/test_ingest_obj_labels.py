"""OBJ group and object names become part labels on ingest (unless a sidecar gives labels)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import trimesh

from training.data.ingest import ingest_folder, load_shape_file, obj_label


def _obj(groups: list[tuple[str, str, tuple[float, float, float]]]) -> str:
    """An OBJ with one box per (keyword, name, offset); keyword ``g``, ``o`` or "" (no name)."""
    lines, offset = [], 1
    for keyword, name, at in groups:
        box = trimesh.creation.box((0.2, 0.2, 0.2))
        box.apply_translation(at)
        if keyword:
            lines.append(f"{keyword} {name}")
        lines += [f"v {x} {y} {z}" for x, y, z in box.vertices.tolist()]
        lines += [f"f {a + offset} {b + offset} {c + offset}" for a, b, c in box.faces.tolist()]
        offset += len(box.vertices)
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize("keyword", ["g", "o"])
def test_obj_names_are_labels(tmp_path: Path, keyword: str) -> None:
    path = tmp_path / "chair" / "a.obj"
    path.parent.mkdir()
    path.write_text(_obj([(keyword, "seat", (0, 0, 0)), (keyword, "leg.001", (1, 0, 0)),
                          (keyword, "leg_2", (2, 0, 0)), (keyword, "back_rest", (3, 0, 0))]))
    shape = load_shape_file(path)
    assert sorted(p.label for p in shape.pieces) == ["back_rest", "leg", "leg", "seat"]


def test_obj_without_names_stays_unlabelled(tmp_path: Path) -> None:
    path = tmp_path / "chair" / "b.obj"
    path.parent.mkdir()
    path.write_text(_obj([("", "", (0, 0, 0)), ("", "", (2, 0, 0))]))
    shape = load_shape_file(path)
    assert len(shape.pieces) == 2 and all(p.label is None for p in shape.pieces)


def test_sidecar_labels_win_and_labels_reach_the_written_sidecar(tmp_path: Path) -> None:
    src = tmp_path / "src" / "chair"
    src.mkdir(parents=True)
    (src / "c.obj").write_text(_obj([("g", "seat", (0, 0, 0)), ("g", "leg", (1, 0, 0))]))
    (src / "c.json").write_text(json.dumps({"labels": {"seat": "cushion"}}))
    assert sorted(p.label for p in load_shape_file(src / "c.obj").pieces) == ["cushion", "leg"]
    ingest_folder(tmp_path / "src", tmp_path / "raw")
    written = json.loads(next((tmp_path / "raw").rglob("c.json")).read_text())
    assert sorted(written["labels"].values()) == ["cushion", "leg"]


def test_obj_label_of_names() -> None:
    assert [obj_label(n) for n in ("seat", "leg.001", "leg_2", "leg/1", "geometry/0", "geometry")] == [
        "seat", "leg", "leg", "leg", None, None]
