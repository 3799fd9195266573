"""The assembly evaluation (training/evaluate/assembly_eval.py): measures on hand-made runs, the
report block, and one small seeded run of `complementme evaluate-assembly` on the shipped model."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

from service.geometry.frames import Frame
from service.modeling.assembly import AssembleResult, Node, Start
from service.suggest.engine import Suggestion
from training.evaluate.assembly_eval import (
    AssemblyEvalSettings,
    data_good,
    data_stacked,
    good_interval,
    measure_run,
    misplaced,
    report_markers,
    start_parts,
    summarize,
    too_many,
    write_report,
)

SHIPPED = Path(__file__).resolve().parents[2] / "exported"


class _Index:
    """The parts of ShapeIndex that measure_run reads: a catalog of unit boxes and their labels,
    the first ``own`` parts (the start's) forming one shape, the rest another."""

    def __init__(self, labels: list[str], own: int = 1) -> None:
        n = len(labels)
        shapes = [{"shape_id": "start" if i < own else "other"} for i in range(n)]
        self.catalog = SimpleNamespace(part_ids=[f"s/{i}" for i in range(n)], bbox_min=np.full((n, 3), -0.1),
                                       bbox_max=np.full((n, 3), 0.1), records=shapes)
        self.labels = np.array(labels, dtype=object)
        self.rows = {"start": np.arange(own), "other": np.arange(own, n)}


def _node(i: int, row: int, at: list[float]) -> Node:
    t = np.array(at, dtype=np.float64)
    sug = Suggestion(rank=1, part_index=row, part_id=f"s/{row}", shape_id="s", category="c", label=None,
                     score=0.0, rank_score=0.0, mode=0, mode_weight=1.0, duplicates=1, translation=t,
                     bbox_min=t - 0.1, bbox_max=t + 0.1)
    return Node(node=i, parent=i - 1 if i else None, depth=i + 1, suggestion=sug, translation=t,
                contact_offset=np.zeros(3), distance=1.0)


def _result(nodes: list[Node]) -> AssembleResult:
    return AssembleResult(start=Start(kind="part", part_index=0), start_translation=np.zeros(3), category="c",
                          steps=nodes, nodes=nodes, stop_reason="complete", frame=Frame())


def test_measure_run_complete_stacked_and_empty() -> None:
    index = _Index(["seat", "back", "leg", "seat"])
    settings = AssemblyEvalSettings(contact=False)
    # Start seat at 0; back and leg elsewhere: complete, nothing stacked.
    chain = _result([_node(0, 1, [0, 1, 0]), _node(1, 2, [0, -1, 0])])
    good = measure_run(index, {"seat", "back", "leg"}, 0, chain, settings)  # type: ignore[arg-type]
    assert good["complete"] and not good["stacked"] and good["good"] and not good["empty"]
    # A second seat 0.05 beside the first: their boxes overlap with IoU 0.6 > 0.25.
    chain = _result([_node(0, 1, [0, 1, 0]), _node(1, 3, [0.05, 0, 0])])
    stacked = measure_run(index, {"seat", "back"}, 0, chain, settings)  # type: ignore[arg-type]
    assert stacked["complete"] and stacked["stacked"] == [[2, 0, 0.6]] and not stacked["good"]
    empty = measure_run(index, {"seat", "back"}, 0, _result([]), settings)  # type: ignore[arg-type]
    assert empty["empty"] and not empty["complete"] and empty["missing"] == ["back"]
    assert "complete_as_data" not in empty


def test_measure_run_counts_an_object_the_data_has() -> None:
    """A seat with a leg lacks the majority's back but is a stool, a label set of the data; stacked
    parts still spoil it, and a seat alone is no shape of the data."""
    index = _Index(["seat", "back", "leg", "seat"])
    settings = AssemblyEvalSettings(contact=False)
    kinds = [frozenset({"seat", "leg"}), frozenset({"seat", "back", "leg"})]
    stool = measure_run(index, {"seat", "back", "leg"}, 0, _result([_node(0, 2, [0, -1, 0])]),  # type: ignore[arg-type]
                        settings, kinds)
    assert stool["complete_as_data"] and stool["good_as_data"] and not stool["complete"]
    stacked = measure_run(index, {"seat", "leg"}, 0, _result([_node(0, 2, [0, -1, 0]),  # type: ignore[arg-type]
                                                              _node(1, 3, [0.05, 0, 0])]), settings, kinds)
    assert stacked["complete_as_data"] and not stacked["good_as_data"]
    alone = measure_run(index, {"seat", "leg"}, 0, _result([]), settings, kinds)  # type: ignore[arg-type]
    assert not alone["complete_as_data"] and not alone["good_as_data"]


def test_measure_run_knows_whether_the_start_came_from_a_complete_shape() -> None:
    """A run from a stool's seat (its shape has no back) is marked so; the summary's "from a
    complete shape's part" counts only the runs from complete shapes."""
    settings = AssemblyEvalSettings(contact=False)
    essentials = {"seat", "back", "leg"}
    chain = _result([_node(0, 3, [0, 1, 0]), _node(1, 4, [0, -1, 0])])
    chair = measure_run(_Index(["seat", "back", "leg", "back", "leg"], own=3), essentials, 0, chain,  # type: ignore[arg-type]
                        settings)
    stool = measure_run(_Index(["seat", "leg", "seat", "back", "leg"], own=2), essentials, 0, chain,  # type: ignore[arg-type]
                        settings)
    assert chair["start_shape_complete"] and not stool["start_shape_complete"]
    assert chair["good"] and stool["good"]
    runs = [{**chair, "category": "chair"}, {**stool, "category": "chair", "good": False},
            {**stool, "category": "chair"}]
    summary = summarize(runs, [], ["chair"])["chair"]
    assert summary["complete_starts"] == 1 and summary["good_from_complete"] == 1.0
    assert summary["data_complete"] == pytest.approx(1 / 3)
    assert summary["good"] == pytest.approx(2 / 3)
    lone = summarize([{**stool, "category": "chair"}], [], ["chair"])["chair"]
    assert lone["complete_starts"] == 0 and lone["good_from_complete"] is None
    assert lone["data_complete"] == 0.0


def test_a_part_far_from_every_training_part_of_its_label_is_misplaced() -> None:
    """A back where the data's backs sit is in place; a back under the seat, or a part of a label
    the category's training shapes never have, is misplaced."""
    places = {"back": np.array([[0.0, 0.5, -0.3], [0.0, 0.4, -0.35]]), "leg": np.array([[0.3, -0.5, 0.3]])}
    assert not misplaced(places, "back", np.array([0.0, 0.55, -0.25]), 0.15)
    assert misplaced(places, "back", np.array([0.0, 0.0, 0.0]), 0.15)
    assert misplaced(places, "wing", np.array([0.0, 0.5, -0.3]), 0.15)
    assert misplaced(places, None, np.array([0.0, 0.5, -0.3]), 0.15)
    index = _Index(["seat", "back", "leg"])
    chain = _result([_node(0, 1, [0.0, 0.5, -0.3]), _node(1, 2, [0.0, 0.9, 0.0])])
    rec = measure_run(index, {"seat", "back"}, 0, chain, AssemblyEvalSettings(contact=False),  # type: ignore[arg-type]
                      places=places)
    assert rec["misplaced"] == [False, True]
    runs = [{**rec, "category": "chair"}]
    data = [{"category": "chair", "stacked": False, "misplaced": False}]
    assert summarize(runs, data, ["chair"])["chair"]["misplaced"] == 0.5
    assert summarize(runs, data, ["chair"])["chair"]["data_misplaced"] == 0.0
    assert "misplaced" not in measure_run(index, {"seat"}, 0, chain, AssemblyEvalSettings(contact=False))  # type: ignore[arg-type]


def test_more_parts_of_a_label_than_any_shape_has_is_too_many() -> None:
    """Two seats where every chair has one, five legs where chairs have four at most: too many;
    four legs, or a label the data never counted (never more than zero), are judged alike."""
    most = Counter({"seat": 1, "leg": 4, "back": 1})
    assert too_many(most, ["seat", "leg", "leg", "back"]) == []
    assert too_many(most, ["seat", "seat", "leg", "leg", "leg", "leg", "leg"]) == ["leg", "seat"]
    assert too_many(most, ["seat", "wing", None]) == ["wing"]
    index = _Index(["seat", "seat", "leg"])
    chain = _result([_node(0, 1, [0.0, 1.0, 0.0]), _node(1, 2, [0.0, -1.0, 0.0])])
    rec = measure_run(index, {"seat", "leg"}, 0, chain, AssemblyEvalSettings(contact=False),  # type: ignore[arg-type]
                      most=most)
    assert rec["too_many"] == ["seat"] and rec["good"]   # "good" does not ask it (a measure beside)
    summary = summarize([{**rec, "category": "chair"}], [{"category": "chair", "too_many": False}], ["chair"])
    assert summary["chair"]["too_many"] == 1.0 and summary["chair"]["data_too_many"] == 0.0


def test_the_datas_own_shapes_are_measured_by_the_same_stacked_rule() -> None:
    """A shape whose two wheel parts (tyres, hubs) share one box is stacked, as a run would be;
    parts of one label apart, or of two labels in one box, are not."""
    index = _Index(["wheel", "wheel", "body", "roof", "roof"])
    index.catalog.records = [{"shape_id": "car"}] * 3 + [{"shape_id": "other"}] * 2
    index.catalog.translations = np.array([[0, 0, 0], [0.02, 0, 0], [0, 0, 0], [0, 1, 0], [0, -1, 0]], float)
    index.rows = {"car": np.array([0, 1, 2]), "other": np.array([3, 4])}
    settings = AssemblyEvalSettings(contact=False)
    assert data_stacked(index, 2, settings)  # type: ignore[arg-type]
    assert not data_stacked(index, 3, settings)  # type: ignore[arg-type]
    # Counted as a run is: complete and nothing stacked (the car is stacked, the other shape
    # lacks a body, and holds every label asked of it only when that is its roof alone).
    assert not data_good(index, {"wheel", "body"}, 2, settings)  # type: ignore[arg-type]
    assert not data_good(index, {"body", "roof"}, 3, settings)  # type: ignore[arg-type]
    assert data_good(index, {"roof"}, 3, settings)  # type: ignore[arg-type]
    run = {"category": "car", "start": "car-0001/0", "good": True, "complete": True, "stacked": [],
           "empty": False, "parts": ["a"], "stop_reason": "complete", "seconds": 0.1}
    data = [{"category": "car", "stacked": True, "good": False},
            {"category": "car", "stacked": False, "good": True}]
    assert summarize([run], data, ["car"])["car"]["data_good"] == 0.5


def test_the_interval_of_good_runs_resamples_start_shapes_not_runs() -> None:
    """Starts from one shape share it: ten shapes of ten starts each, five shapes all good and
    five all bad, tell less than a hundred shapes of one start each with the same share."""
    from training.evaluate.metrics import cluster_share_interval

    def runs(shapes: int, per_shape: int) -> list[dict[str, object]]:
        return [{"category": "chair", "start": f"chair-{s:04d}/{i}", "good": s % 2 == 0}
                for s in range(shapes) for i in range(per_shape)]

    clustered, independent = good_interval(runs(10, 10), seed=0), good_interval(runs(100, 1), seed=0)
    assert clustered[0] < independent[0] < 0.5 < independent[1] < clustered[1]
    assert independent[0] > 0.35 and independent[1] < 0.65            # about +-0.1 for 100 draws
    assert good_interval(runs(10, 10), seed=0) == clustered            # seeded
    # Each category's shapes are drawn within the category: a category all good stays all good.
    both = good_interval([*runs(100, 1), *({"category": "car", "start": f"car-{s}/0", "good": True}
                                             for s in range(100))], seed=0)
    assert both[0] > 0.7 and both[1] < 0.83                           # 0.75 +- 0.05
    summary = summarize([{**r, "complete": True, "stacked": [], "empty": False, "parts": [],
                          "stop_reason": "complete", "seconds": 0.1} for r in runs(10, 10)], [], ["chair"])
    assert summary["chair"]["good_interval"] == clustered and summary["chair"]["good"] == 0.5
    assert all(np.isnan(v) for v in cluster_share_interval([], seed=0))


def test_summary_and_report_block(tmp_path: Path) -> None:
    runs = [{"category": "chair", "start": "chair-0001/0", "good": True, "complete": True, "stacked": [],
             "empty": False, "parts": ["a"], "stop_reason": "complete", "seconds": 0.1, "floating": [False],
             "interpenetrating": [True]},
            {"category": "chair", "start": "chair-0002/0", "good": False, "complete": False, "stacked": [],
             "empty": True, "parts": [], "stop_reason": "unlikely", "seconds": 0.2}]
    data = [{"category": "chair", "floating": False, "interpenetrating": True, "stacked": True},
            {"category": "chair", "stacked": False}]   # a one-part shape: no contact measured
    summary = summarize(runs, data, ["chair"])
    assert summary["chair"]["good"] == 0.5 and summary["chair"]["empty"] == 0.5
    assert summary["chair"]["data_stacked"] == 0.5 and summary["chair"]["data_floating"] == 0.0
    assert summary["chair"]["interpenetrating"] == 1.0 and summary["all"]["data_interpenetrating"] == 1.0
    results = {"command": "complementme evaluate-assembly", "seconds": 1.0, "model_version": "m",
               "artifacts": "exported", "date": "2026-12-02", "essential_labels": {"chair": ["back", "seat"]},
               "summary": {"greedy": summary}}
    doc = tmp_path / "modeling.md"
    doc.write_text("# Modeling\n\nbefore\n")
    write_report(results, doc)
    write_report(results, doc)   # a second run replaces the block, it does not add one
    write_report({**results, "artifacts": "runs/v3-exported"}, doc)   # another model: its own block
    text = doc.read_text()
    for tag in ("exported", "v3-exported"):
        start, end = report_markers(tag)
        assert text.count(start) == 1 and text.count(end) == 1
    assert "before" in text and text.count("| chair | 2 | 50% | 0%-100% |") == 2
    assert "From a complete shape's part" in text and "| 50% | 0%-100% | n/a | n/a (0) |" in text
    assert "Data: stacked" in text
    assert "| n/a | n/a | 100% | 50% | n/a | n/a | complete 1, unlikely 1 |" in text


class _Shapes:
    """The parts of ShapeIndex that start_parts reads: two categories, shapes in both splits."""

    def __init__(self) -> None:
        names = [f"{c}-{s}{i}" for c in ("chair", "lamp") for s in ("train", "test") for i in range(4)]
        self.rows = {sid: [3 * k + j for j in range(3)] for k, sid in enumerate(names)}  # rows unique
        self.category = {sid: sid.split("-")[0] for sid in self.rows}
        self.split = {sid: "train" if "train" in sid else "test" for sid in self.rows}

    def shapes(self, category: str, split: str) -> list[str]:
        return sorted(s for s in self.rows if self.category[s] == category and self.split[s] == split)

    def categories(self) -> list[str]:
        return ["chair", "lamp"]


def test_start_parts_never_repeat_and_keep_their_first_pass() -> None:
    """Past the number of shapes a category's starts are other components of the same shapes, never
    one twice; with more starts asked than components, each component once; the first pass (one
    per shape) is the same whatever the number asked."""
    index = _Shapes()  # 4 test shapes of 3 components per category
    ten = start_parts(index, 10, seed=0)  # type: ignore[arg-type]
    for c in ("chair", "lamp"):
        rows = [row for cat, row in ten if cat == c]
        assert len(rows) == 10 and len(set(rows)) == 10
        first = [row for cat, row in start_parts(index, 4, seed=0) if cat == c]  # type: ignore[arg-type]
        assert rows[:4] == first
        assert len({next(s for s in index.shapes(c, "test") if r in index.rows[s]) for r in first}) == 4
    every = start_parts(index, 50, seed=0)  # type: ignore[arg-type]
    assert len(every) == 24 and len(set(every)) == 24
    assert start_parts(index, 10, seed=1) != ten  # type: ignore[arg-type]


def test_start_parts_come_from_the_split_asked_for() -> None:
    """The reported split is test; train starts are for choosing settings without looking at it."""
    index = _Shapes()
    for split in ("test", "train"):
        starts = start_parts(index, 6, seed=0, split=split)  # type: ignore[arg-type]
        assert [c for c, _ in starts] == ["chair"] * 6 + ["lamp"] * 6
        assert all(any(row in index.rows[sid] for sid in index.shapes(c, split)) for c, row in starts)
    assert start_parts(index, 6, seed=0) == start_parts(index, 6, seed=0, split="test")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="split must be train or test"):
        AssemblyEvalSettings(split="val").validate()


@pytest.mark.skipif(not (SHIPPED / "manifest.json").is_file(), reason="no trained artifacts in exported/ yet")
def test_evaluate_assembly_command_on_the_shipped_model(tmp_path: Path) -> None:
    """One start per category, contacts measured: the command writes its results and its block."""
    from typer.testing import CliRunner

    from training.cli import app

    report = tmp_path / "modeling.md"
    args = ["evaluate-assembly", "--artifacts", str(SHIPPED), "--starts", "1", "--out", str(tmp_path / "out"),
            "--report", str(report), "--no-progress", "--max-parts", "3"]
    result = CliRunner().invoke(app, [*args, "--pictures", "1"])
    assert result.exit_code == 0, result.output
    res = json.loads((tmp_path / "out" / "results.json").read_text())
    # One picture per category, linked from the report's block relative to the report.
    assert sorted(res["pictures"]) == sorted(res["essential_labels"])
    for category, name in res["pictures"].items():
        with Image.open(tmp_path / "out" / name) as picture:
            assert picture.width > 100 and picture.height > 100
            assert len(picture.convert("RGB").getcolors(1 << 20) or []) > 20  # shaded meshes, not blank
        assert f"![{category}](out/{name})" in report.read_text()
    run = res["runs"][0]
    assert len(run["translations"]) == len(run["scales"]) == len(run["parts"])
    # Run times live beside the results (they differ on every re-run), one per run, in run order.
    timings = json.loads((tmp_path / "out" / "timings.json").read_text())["runs"]
    order = [(r["start"], r["strategy"]) for r in res["runs"]]
    assert [(t["start"], t["strategy"]) for t in timings] == order
    assert all(t["seconds"] > 0 for t in timings) and not any("seconds" in r for r in res["runs"])
    runs = res["runs"]
    assert len(runs) == len(res["essential_labels"])  # one start per category
    assert all(len(r["parts"]) <= 3 for r in runs)
    assert all(r["start"].split("/")[0] not in {p.split("/")[0] for p in r["parts"]} for r in runs)
    placed = [r for r in runs if r["parts"]]
    assert all(len(r["gap"]) == len(r["parts"]) == len(r["misplaced"]) for r in placed)
    # The held-out shapes' own parts lie where the training shapes have their labels.
    assert res["summary"]["greedy"]["all"]["data_misplaced"] == 0.0
    assert all(isinstance(r["too_many"], list) for r in runs)
    assert 0.0 <= res["summary"]["greedy"]["all"]["good"] <= 1.0
    assert report_markers("exported")[0] in report.read_text()
    # Seeded: the same command draws the same starts.
    again = CliRunner().invoke(app, [*args, "--no-contact", "--out", str(tmp_path / "again")])
    assert again.exit_code == 0, again.output
    res2 = json.loads((tmp_path / "again" / "results.json").read_text())
    assert [r["start"] for r in res2["runs"]] == [r["start"] for r in runs]


def _colour_pixels(path: Path, colour: str) -> int:
    """Pixels of ``path`` whose chromaticity is ``colour``'s (any shade of it; white and grey
    pixels do not count)."""
    import matplotlib.colors

    rgb = np.asarray(Image.open(path).convert("RGB"), dtype=np.float64)
    total = rgb.sum(axis=2, keepdims=True)
    coloured = (rgb.max(axis=2) - rgb.min(axis=2)) > 40            # not white, grey or black text
    target = np.asarray(matplotlib.colors.to_rgb(colour))
    chroma = rgb / np.maximum(total, 1.0)
    close = np.abs(chroma - target / target.sum()).sum(axis=2) < 0.06
    return int(np.sum(close & coloured))


@pytest.mark.skipif(not (SHIPPED / "manifest.json").is_file(), reason="no trained artifacts in exported/ yet")
def test_a_picture_hides_what_lies_behind_another_part_triangle_by_triangle(tmp_path: Path) -> None:
    """A pole through a plate: from the pictures' raised camera the plate hides the pole's lower
    half and the pole's upper half hides some of the plate. Drawn part by part as wholes, one of
    the two would show in full."""
    from service.artifacts.loading import load_artifacts
    from training.evaluate.assembly_pictures import COLOURS, draw_runs

    catalog = load_artifacts(SHIPPED).catalog
    extent = catalog.bbox_max - catalog.bbox_min                            # (P, 3), y up
    flat = int(np.argmax(np.minimum(extent[:, 0], extent[:, 2]) / np.maximum(extent[:, 1], 1e-3)))
    tall = int(np.argmax(extent[:, 1] / np.maximum(extent[:, [0, 2]].max(axis=1), 1e-3)))
    # Per-axis scales that make the plate 1.2 wide and 0.05 thick, the pole 1.2 tall and 0.12 wide.
    plate_scale = tuple(float(v) for v in np.array([1.2, 0.05, 1.2]) / extent[flat])
    pole_scale = tuple(float(v) for v in np.array([0.12, 1.2, 0.12]) / extent[tall])
    tiny = (1e-3, 1e-3, 1e-3)
    # The start is never scaled: the catalog's smallest part, in a corner, with a near-invisible
    # part in the opposite corner: they fix the drawn box, so the three pictures share one scale.
    small = catalog.part_ids[int(np.argmin(extent.max(axis=1)))]

    def picture(name: str, plate: tuple[float, ...], pole: tuple[float, ...]) -> Path:
        run = {"start": small, "start_translation": [-1.0, -1.0, -1.0],
               "parts": [catalog.part_ids[flat], catalog.part_ids[tall], small],
               "translations": [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0]],
               "scales": [list(plate), list(pole), list(tiny)],
               "empty": False, "stacked": [], "missing": []}
        path = tmp_path / f"{name}.png"
        draw_runs(catalog, [run], path, name)
        return path

    both = picture("both", plate_scale, pole_scale)
    plate_alone = picture("plate", plate_scale, tiny)
    pole_alone = picture("pole", tiny, pole_scale)
    plate, pole = COLOURS[1], COLOURS[2]
    assert _colour_pixels(plate_alone, plate) > 1000 and _colour_pixels(pole_alone, pole) > 300
    # Each part loses a real share of its pixels to the other.
    assert _colour_pixels(both, plate) < 0.95 * _colour_pixels(plate_alone, plate)
    assert _colour_pixels(both, pole) < 0.9 * _colour_pixels(pole_alone, pole)
