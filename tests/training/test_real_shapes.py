"""`complementme evaluate-real` (training.evaluate.real_shapes) on the shipped artifacts."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from training.cli import app
from training.data.processed import ProcessedDataset
from training.evaluate.real_shapes import (
    MEASURES,
    SETS,
    RealEvalSettings,
    chamfer,
    markdown,
    run_real_evaluation,
)

SHIPPED = Path(__file__).resolve().parents[2] / "exported"
pytestmark = pytest.mark.skipif(not (SHIPPED / "manifest.json").is_file(),
                                reason="no trained artifacts in exported/ yet")


def test_chamfer_is_the_mean_nearest_distance_both_ways() -> None:
    a = np.array([[0.0, 0, 0], [1, 0, 0]])
    assert chamfer(a, a) == 0.0
    assert chamfer(a, a + np.array([0, 0.1, 0])) == pytest.approx(0.1)
    # One far point in b: b -> a averages it in, a -> b does not see it.
    b = np.vstack([a, [[0, 3, 0]]])
    assert chamfer(a, b) == pytest.approx(0.5 * (0 + 3 / 3))


@pytest.fixture(scope="module")
def collection(generated_dataset_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Generated chairs, lamps and tables standing in for an outside collection (same ids as the
    catalog's: the evaluation must keep each shape's own parts out of its answers)."""
    ds = ProcessedDataset.load(generated_dataset_dir)
    keep = [s for s, m in enumerate(ds.shapes) if m["category"] in ("chair", "lamp", "table")]
    folder = tmp_path_factory.mktemp("outside")
    ds.subset(keep).save(folder)
    return folder


def test_shapes_like_the_training_ones_score_like_the_held_out_set(collection: Path, tmp_path: Path) -> None:
    report = run_real_evaluation(RealEvalSettings(data=collection, artifacts=SHIPPED, queries_per_shape=1,
                                                  out=tmp_path))
    assert json.loads((tmp_path / "results.json").read_text()) == report
    for name in SETS:
        res = report["results"][name]
        assert set(res) == {"chair", "lamp", "table", "all"}
        assert set(MEASURES) <= set(res["all"])
        assert res["all"]["queries"] == sum(res[c]["queries"] for c in ("chair", "lamp", "table"))
        for m in ("category_right", "in_category", "guess_warned", "frame_up", "frame_good"):
            assert 0.0 <= res["all"][m] <= 1.0
        # The model knows these shapes: it names their category and its picks beat chance.
        assert res["all"]["category_right"] >= 0.9, res["all"]
        assert res["all"]["named_best5"] < res["all"]["random_best5"], res["all"]
        # ... and fits the frame of most of them from a random caller frame.
        assert res["all"]["frame_good"] >= 0.6 and res["all"]["frame_up"] >= res["all"]["frame_good"]
    assert report["results"]["outside"]["all"]["shapes"] == 18
    # A catalog without a held-out split has no reference set, and the report says so.
    table = markdown({**report, "results": {**report["results"], "held-out": {}}})
    assert "**held-out**: no queries (the catalog has no held-out split)" in table
    assert "| named: Chamfer, best of the top 5 as placed |" in table


def test_command_refuses_a_folder_without_a_collection(tmp_path: Path) -> None:
    result = CliRunner().invoke(app, ["evaluate-real", "--data", str(tmp_path)])
    assert result.exit_code == 2 and "holds no processed collection" in result.output
