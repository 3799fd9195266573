"""`complementme category-head`: g's category head refitted on outside collections, nothing else.

A tiny run with a category head stands in for the shipped model; toy shapes of another seed stand
in for an outside collection.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import onnxruntime as ort
import pytest
from typer.testing import CliRunner

from service.artifacts.layout import CATALOG_ARRAYS, GRAPH_FILES, GRAPH_OUTPUTS, MANIFEST
from training.category_head import check_categories, refit_category_head
from training.config import HeadFitSettings
from training.export import export_run, options_of
from training.from_onnx import trained_from_artifacts
from training.split import load_split


@pytest.fixture(scope="module")
def head_run(tmp_path_factory: pytest.TempPathFactory, toy_dataset_dir: Path) -> tuple[Path, Path]:
    """A tiny run trained with a category head, and its export (h on more points than f and g)."""
    from training.config import resolve_config
    from training.train import train

    root = tmp_path_factory.mktemp("head_run")
    cfg = resolve_config("tiny", overrides={"data": str(toy_dataset_dir), "run": str(root / "run"),
                                            "steps": 10, "log_every": 5, "val_triplets": 16,
                                            "category_weight": 1.0})
    train(cfg, show_progress=False)
    from training.export import ExportOptions

    export_run(root / "run", root / "exported", options=ExportOptions(n_points=96, placement_points=160))
    return root / "run", root / "exported"


@pytest.fixture(scope="module")
def outside_dir(tmp_path_factory: pytest.TempPathFactory, toy_dataset_factory) -> Path:
    folder = tmp_path_factory.mktemp("outside")
    toy_dataset_factory(n_per_category=4, seed=11, categories=("chair", "table")).save(folder)
    return folder


def _graph(folder: Path, graph: str, clouds: np.ndarray) -> dict[str, np.ndarray]:
    session = ort.InferenceSession(str(folder / GRAPH_FILES[graph]), providers=["CPUExecutionProvider"])
    names = [o.name for o in session.get_outputs()]
    return dict(zip(names, session.run(names, {"points": clouds}), strict=True))


def test_the_refit_changes_the_category_head_and_nothing_else(head_run, outside_dir: Path,
                                                              tmp_path: Path) -> None:
    run, exported = head_run
    out = tmp_path / "refitted"
    result = CliRunner().invoke(_app(), ["category-head", "--artifacts", str(exported), "--run", str(run),
                                         "--outside", str(outside_dir), "--out", str(out),
                                         "--queries", "512", "--outside-share", "0.25"])
    assert result.exit_code == 0, result.output
    before = json.loads((exported / MANIFEST).read_text())
    after = json.loads((out / MANIFEST).read_text())
    assert after["model_version"].startswith(before["model_version"].rsplit("-", 1)[0] + "-head-")
    assert after["model_version"] != before["model_version"]
    record = after["training"]["category_head"]
    assert record["queries"] == {"own": 384, str(outside_dir): 128}
    assert set(record["accuracy_after"]) == {"own", str(outside_dir)}
    # Served the same way: the points f, g and h take, and the catalog's embeddings.
    assert (after["n_points"], after["placement_points"]) == (96, 160)
    assert after["categories"] == before["categories"]
    np.testing.assert_allclose(np.load(out / CATALOG_ARRAYS)["embeddings"],
                               np.load(exported / CATALOG_ARRAYS)["embeddings"], atol=1e-5)
    clouds = np.random.default_rng(3).uniform(-0.5, 0.5, (4, 96, 3)).astype(np.float32)
    old, new = _graph(exported, "g", clouds), _graph(out, "g", clouds)
    assert set(old) == set(new) == {*GRAPH_OUTPUTS["g"], "category_probs"}
    for name in ("weights", "means", "sigmas"):
        np.testing.assert_allclose(new[name], old[name], atol=1e-6)
    assert np.abs(new["category_probs"] - old["category_probs"]).max() > 1e-3
    np.testing.assert_allclose(_graph(out, "f", clouds)["embedding"],
                               _graph(exported, "f", clouds)["embedding"], atol=1e-6)
    assert (out / GRAPH_FILES["h_head"]).read_bytes() == (exported / GRAPH_FILES["h_head"]).read_bytes()


def test_the_fit_learns_the_outside_queries(head_run, outside_dir: Path) -> None:
    from training.data.processed import ProcessedDataset

    run, exported = head_run
    trained, _ = trained_from_artifacts(exported)
    own = ProcessedDataset.load(Path(json.loads((exported / MANIFEST).read_text())["dataset"]["path"]))
    own_train = own.subset(load_split(run, own).train)
    report = refit_category_head(trained.pair.g, own_train, {"outside": ProcessedDataset.load(outside_dir)},
                                 own.categories(), HeadFitSettings(queries=1024, outside_share=0.5, epochs=60,
                                                                   lr=1e-2))
    before, after = report["accuracy_before"], report["accuracy_after"]
    assert isinstance(before, dict) and isinstance(after, dict)
    # Ten steps of training leave the head near chance over three categories.
    assert after["outside"] > before["outside"] + 0.1
    assert after["outside"] > 0.6


def test_an_outside_category_the_model_does_not_know_is_refused_by_name(toy_dataset_factory) -> None:
    boats = toy_dataset_factory(n_per_category=2, seed=2, categories=("chair", "lamp"))
    boats.shapes[0]["category"] = "watercraft"
    with pytest.raises(ValueError, match=r"data/boats: categories \['watercraft'\] are not among"):
        check_categories(boats, ["chair", "lamp", "table"], "data/boats")


def test_a_refit_needs_an_outside_collection_and_a_head(head_run, tmp_path: Path) -> None:
    run, exported = head_run
    result = CliRunner().invoke(_app(), ["category-head", "--artifacts", str(exported), "--run", str(run),
                                         "--outside", str(tmp_path / "missing"),
                                         "--out", str(tmp_path / "o")])
    assert result.exit_code == 2
    assert "missing" in result.output
    assert not (tmp_path / "o").exists()


def test_options_of_a_manifest_export_it_the_same_way(head_run) -> None:
    _, exported = head_run
    manifest = json.loads((exported / MANIFEST).read_text())
    opts = options_of(manifest)
    assert (opts.n_points, opts.placement_points) == (96, 160)
    assert opts.catalog_points == manifest["catalog_points"]
    assert opts.duplicate_embedding_radius == manifest["duplicates"]["embedding_radius"]
    assert opts.familiarity_quantile == manifest["familiarity"]["quantile"]


def _app():
    from training.cli import app

    return app


def _outside_sh(call: str, furniture: Path) -> subprocess.CompletedProcess[str]:
    script = Path(__file__).resolve().parents[2] / "training" / "recipes" / "outside.sh"
    return subprocess.run(["bash", "-c", f'set -euo pipefail; source "{script}"; {call}'],
                          env={"PATH": "/usr/bin:/bin", "FURNITURE": str(furniture)},
                          capture_output=True, text=True, timeout=30, check=False)


def test_the_recipes_refuse_missing_furniture_libraries_by_name(tmp_path: Path) -> None:
    """shipped.sh checks the head's libraries before it trains for hours; the makers on the two
    sides of outside.sh's split never overlap."""
    done = _outside_sh('check_furniture data/none "${HEAD_LIBRARIES[@]}"', tmp_path)
    assert done.returncode == 2
    assert f"{tmp_path}/Scopia.sh3f is missing" in done.stderr and "sweethome3d-furniture" in done.stderr
    for name in ("Scopia", "KatorLegaz"):
        (tmp_path / f"{name}.sh3f").write_bytes(b"")
    assert _outside_sh('check_furniture data/none "${HEAD_LIBRARIES[@]}"', tmp_path).returncode == 0
    sides = _outside_sh('echo "${HEAD_LIBRARIES[*]}"; echo "${HELD_OUT_LIBRARIES[*]}"',
                        tmp_path).stdout.split("\n")
    head, held_out = set(sides[0].split()), set(sides[1].split())
    assert head and held_out and not head & held_out
