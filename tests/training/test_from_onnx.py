"""Torch networks read back from an exported folder compute what the trained ones did."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch

from service.artifacts.layout import CATALOG_ARRAYS, GRAPH_FILES, MANIFEST
from training.checkpoint import load_trained
from training.export import export_run, graph_modules
from training.from_onnx import (
    check_parity,
    load_exported_networks,
    load_graph_weights,
    trained_from_artifacts,
)


@pytest.fixture(scope="module")
def exported(tiny_run: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("from_onnx") / "exported"
    export_run(tiny_run, out)
    return out


def test_read_back_networks_match_the_trained_ones(exported: Path, tiny_run: Path) -> None:
    trained = load_trained(tiny_run)
    pair, placement, cfg = load_exported_networks(exported)
    assert cfg == trained.config.model
    gen = torch.Generator().manual_seed(1)
    query, part = torch.rand(4, 300, 3, generator=gen) - 0.5, torch.rand(4, 200, 3, generator=gen) - 0.5
    with torch.no_grad():
        for got, want in zip(pair.g(query), trained.pair.g(query), strict=True):
            torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-4)
        torch.testing.assert_close(pair.f(part), trained.pair.f(part), atol=1e-5, rtol=1e-4)
        torch.testing.assert_close(placement(query, part), trained.placement(query, part),
                                   atol=1e-5, rtol=1e-4)


def test_a_wrong_weight_fails_the_parity_check(exported: Path, tiny_run: Path) -> None:
    trained = load_trained(tiny_run)
    module = graph_modules(trained.pair, trained.placement)["g"]
    path = exported / GRAPH_FILES["g"]
    load_graph_weights(module, onnx.load(str(path)), str(path))
    check_parity(module, "g", path, trained.placement)  # read back as exported: the same
    with torch.no_grad():
        module.encoder.point_mlp[0].weight.mul_(1.5)
    with pytest.raises(ValueError, match="torch and onnxruntime differ"):
        check_parity(module, "g", path, trained.placement)


def test_a_manifest_that_does_not_describe_the_graphs_is_refused(exported: Path, tmp_path: Path) -> None:
    folder = tmp_path / "exported"
    shutil.copytree(exported, folder)
    manifest = json.loads((folder / MANIFEST).read_text())
    manifest["model_config"]["point_layers"] = [*manifest["model_config"]["point_layers"], 32]
    (folder / MANIFEST).write_text(json.dumps(manifest))
    with pytest.raises(ValueError, match="unnamed layers in the graph"):
        load_exported_networks(folder)


def test_an_export_with_the_concatenated_head_is_refused_by_name(exported: Path, tmp_path: Path) -> None:
    """Exports made before h's head was split (h_head starting with a concatenation of its two
    inputs) serve as before but cannot be read back into the split head: the error says so."""
    folder = tmp_path / "exported"
    shutil.copytree(exported, folder)
    h = onnx.helper
    width = json.loads((folder / MANIFEST).read_text())["query_feature_dim"]
    graph = h.make_graph(
        [h.make_node("Concat", ["query_feature", "part_feature"], ["joined"], axis=1),
         h.make_node("ReduceSum", ["joined", "axes"], ["translation"], keepdims=1)],
        "old_head",
        [h.make_tensor_value_info(n, onnx.TensorProto.FLOAT, ["batch", width])
         for n in ("query_feature", "part_feature")],
        [h.make_tensor_value_info("translation", onnx.TensorProto.FLOAT, ["batch", 1])],
        [onnx.numpy_helper.from_array(np.array([1], np.int64), "axes")])
    onnx.save(h.make_model(graph), str(folder / GRAPH_FILES["h_head"]))
    with pytest.raises(ValueError, match="exported before h's head was split"):
        load_exported_networks(folder)


def test_an_exported_model_recatalogued_over_a_run_split_serves_the_same_function(
        exported: Path, tiny_run: Path, tmp_path: Path) -> None:
    """`export --from-artifacts`: the exported networks, a catalog rebuilt from the run's split and data."""
    out = tmp_path / "recatalogued"
    manifest = export_run(tiny_run, out, networks=trained_from_artifacts(exported))
    before = json.loads((exported / MANIFEST).read_text())
    assert manifest["model_version"].startswith(before["model_version"].rsplit("-", 1)[0] + "-recatalogued-")
    assert manifest["model_config"] == before["model_config"]
    assert manifest["training"]["steps"] == before["training"]["steps"]
    assert manifest["training"]["final_losses"] == before["training"]["final_losses"]
    assert manifest["part_count"] == before["part_count"]
    old = np.load(exported / CATALOG_ARRAYS)["embeddings"]
    new = np.load(out / CATALOG_ARRAYS)["embeddings"]
    np.testing.assert_allclose(new, old, atol=1e-4)


def test_recatalogue_names_a_missing_artifact_folder(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match=r"manifest\.json"):
        trained_from_artifacts(tmp_path / "nowhere")


def test_a_run_started_from_an_export_starts_from_its_function_with_batch_norm_frozen(
        exported: Path, tiny_run: Path, toy_dataset_dir: Path, tmp_path: Path) -> None:
    from training.config import resolve_config
    from training.train import train

    trained = load_trained(tiny_run)
    cfg = resolve_config("tiny", overrides={
        "data": str(toy_dataset_dir), "run": str(tmp_path / "ft"), "steps": 3, "log_every": 1,
        "val_triplets": 16, "init_from": str(exported), "lr": 1e-12, "placement_lr": 1e-12})
    train(cfg, show_progress=False)
    tuned = load_trained(tmp_path / "ft")
    # Running statistics are frozen: batch norm in training mode would have moved them.
    start = load_exported_networks(exported)[0].state_dict()
    for name, value in tuned.pair.state_dict().items():
        if name.endswith("running_mean") or name.endswith("running_var"):
            assert torch.equal(value, start[name]), name
    gen = torch.Generator().manual_seed(2)
    query, part = torch.rand(4, 300, 3, generator=gen) - 0.5, torch.rand(4, 200, 3, generator=gen) - 0.5
    with torch.no_grad():
        torch.testing.assert_close(tuned.pair.f(part), trained.pair.f(part), atol=1e-4, rtol=1e-3)
        for got, want in zip(tuned.pair.g(query), trained.pair.g(query), strict=True):
            torch.testing.assert_close(got, want, atol=1e-4, rtol=1e-3)
    # The fine-tuned model's manifest names the model it started from.
    source = json.loads((exported / MANIFEST).read_text())["model_version"]
    export_run(tmp_path / "ft", tmp_path / "ft-exported")
    manifest = json.loads((tmp_path / "ft-exported" / MANIFEST).read_text())
    assert manifest["training"]["started_from"] == source


def test_a_stage_without_the_embedding_trains_g_alone(exported: Path, toy_dataset_dir: Path,
                                                     tmp_path: Path) -> None:
    """``train_embedding`` off: f's weights leave the run as they came in, g's move."""
    from training.config import resolve_config
    from training.train import train

    cfg = resolve_config("tiny", overrides={
        "data": str(toy_dataset_dir), "run": str(tmp_path / "g"), "steps": 4, "val_triplets": 16,
        "init_from": str(exported), "train_placement": False, "train_embedding": False})
    train(cfg, show_progress=False)
    before = load_exported_networks(exported)[0]
    after = load_trained(tmp_path / "g").pair
    f_before, f_after = before.f.state_dict(), after.f.state_dict()
    g_before, g_after = before.g.state_dict(), after.g.state_dict()
    assert all(torch.equal(f_before[k], f_after[k]) for k in f_before)
    assert any(not torch.allclose(g_before[k], g_after[k]) for k in g_before)


def test_a_run_started_from_an_export_of_another_model_is_refused(
        exported: Path, toy_dataset_dir: Path, tmp_path: Path) -> None:
    from training.config import resolve_config
    from training.train import train

    cfg = resolve_config("tiny", overrides={
        "data": str(toy_dataset_dir), "run": str(tmp_path / "ft"), "steps": 2, "init_from": str(exported),
        "embedding_dim": 7})
    with pytest.raises(ValueError, match=r"manifest\.json: its model config"):
        train(cfg, show_progress=False)


def test_a_fine_tuned_run_resumes_from_its_checkpoint_without_its_start(
        exported: Path, toy_dataset_dir: Path, tmp_path: Path) -> None:
    from training.config import resolve_config
    from training.train import config_for_resume, train

    start = tmp_path / "start"
    shutil.copytree(exported, start)
    cfg = resolve_config("tiny", overrides={
        "data": str(toy_dataset_dir), "run": str(tmp_path / "ft"), "steps": 2, "ckpt_every": 1,
        "val_triplets": 16, "init_from": str(start)})
    train(cfg, show_progress=False)
    shutil.rmtree(start)  # the export it started from is gone (or replaced) by the time it resumes
    train(config_for_resume(tmp_path / "ft", {"steps": 4}), resume=True, show_progress=False)
    state = torch.load(tmp_path / "ft" / "checkpoint.pt", weights_only=False)
    assert state["step"] == 4
    assert state["started_from"] == json.loads((exported / MANIFEST).read_text())["model_version"]
