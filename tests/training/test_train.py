"""Training end to end (tiny config): losses fall, resume continues, the CLI and torchrun work."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import faiss
import numpy as np
import onnxruntime as ort
import pytest
import torch
from typer.testing import CliRunner

from service.artifacts.layout import GRAPH_FILES, INDEX_FILE, read_manifest
from training.checkpoint import load_checkpoint, load_trained, save_checkpoint
from training.cli import app
from training.config import resolve_config
from training.export import export_run
from training.plots import LOSSES_CSV, VALIDATION_CSV, read_csv
from training.split import load_split, make_split, save_split
from training.train import config_for_resume, lr_factor, retrieval_objective, train

REPO = Path(__file__).resolve().parents[2]


def _tiny(data: Path, run: Path, **overrides):
    return resolve_config("tiny", overrides={"data": str(data), "run": str(run), **overrides})


@pytest.mark.slow
def test_train_then_export_end_to_end(generated_dataset_dir: Path, tmp_path: Path):
    """Generated and preprocessed shapes -> training -> export -> the artifact folder loads."""
    run = tmp_path / "run"
    steps = 150
    result = train(_tiny(generated_dataset_dir, run, steps=steps, val_every=75, seed=3), show_progress=False)
    assert result.step == steps

    log = read_csv(run / LOSSES_CSV)
    assert log["step"] == [float(s) for s in range(1, steps + 1)]
    for key in ("triplet_loss", "placement_loss"):
        first, last = np.mean(log[key][:15]), np.mean(log[key][-15:])
        assert last < 0.7 * first, f"{key} did not fall: first 15 steps {first:.3g}, last 15 {last:.3g}"
    val = read_csv(run / VALIDATION_CSV)
    assert val["step"] == [75.0, 150.0]
    for name in ("losses.png", "validation.png", "split.json", "config.json", "summary.json"):
        assert (run / name).is_file(), name

    out = tmp_path / "exported"
    manifest = export_run(run, out)
    assert read_manifest(out)["model_version"] == manifest["model_version"]
    for graph, name in GRAPH_FILES.items():
        sess = ort.InferenceSession(str(out / name), providers=["CPUExecutionProvider"])
        assert sess.get_inputs()[0].shape[0] == "batch", graph
    index = faiss.read_index(str(out / INDEX_FILE))
    assert index.ntotal == manifest["part_count"]
    assert manifest["training"]["steps"] == steps
    shipped_accuracy = manifest["training"]["validation"]["triplet_accuracy"]
    assert shipped_accuracy == pytest.approx(val["triplet_accuracy"][-1], abs=1e-5)


def test_resume_continues_where_the_checkpoint_stopped(toy_dataset_dir: Path, tmp_path: Path):
    run = tmp_path / "run"
    train(_tiny(toy_dataset_dir, run, steps=8), show_progress=False)
    first = load_checkpoint(run / "checkpoint.pt")
    assert first["step"] == 8
    with pytest.raises(FileExistsError, match="--resume"):
        train(_tiny(toy_dataset_dir, run, steps=12), show_progress=False)
    result = train(_tiny(toy_dataset_dir, run, steps=12), resume=True, show_progress=False)
    assert result.step == 12
    state = load_checkpoint(run / "checkpoint.pt")
    assert state["step"] == 12 and state["elapsed_seconds"] > first["elapsed_seconds"]
    assert read_csv(run / LOSSES_CSV)["step"] == [float(s) for s in range(1, 13)]
    # The optimiser state came back: Adam's step count continues from 8.
    adam_steps = [int(s["step"]) for s in state["optimizers"]["retrieval"]["state"].values()]
    assert set(adam_steps) == {12}
    trained = load_trained(run)
    assert trained.config.steps == 12


def test_a_run_of_another_version_loads_for_its_weights_and_never_resumes(
        toy_dataset_dir: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture):
    """Options the code does not know (a run trained by a branch with one more option) are
    ignored when only the weights are read; if the weights then do not fit, the error names
    them; resuming such a run is refused."""
    run = tmp_path / "run"
    train(_tiny(toy_dataset_dir, run, steps=2), show_progress=False)
    path = run / "checkpoint.pt"
    state = load_checkpoint(path)
    state["config"] = {**state["config"], "future_option": 0.5,
                       "model": {**state["config"]["model"], "future_layer": 0}}
    save_checkpoint(path, state)
    with caplog.at_level("WARNING", logger="training.checkpoint"):
        trained = load_trained(run)
    assert "future_option, model.future_layer" in caplog.text
    assert trained.config.steps == 2
    with pytest.raises(ValueError, match=r"stored config: unknown (model )?option"):
        config_for_resume(run, {})
    # Weights of a network this version cannot build: the unknown options are named.
    state["placement"] = {**state["placement"], "query.extra.weight": torch.zeros(1)}
    save_checkpoint(path, state)
    with pytest.raises(ValueError, match=r"does not know \(future_option, model.future_layer\)"):
        load_trained(run)


def test_cli_train_and_export(toy_dataset_dir: Path, tmp_path: Path):
    run, out = tmp_path / "run", tmp_path / "exported"
    runner = CliRunner()
    res = runner.invoke(app, ["train", "--preset", "tiny", "--data", str(toy_dataset_dir), "--run", str(run),
                              "--steps", "5", "--point-layers", "8,16", "--no-progress",
                              "--embedding-dim", "4"])
    assert res.exit_code == 0, res.output
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["steps"] == 5
    assert cfg["model"]["point_layers"] == [8, 16] and cfg["model"]["embedding_dim"] == 4
    res = runner.invoke(app, ["train", "--resume", "--run", str(run), "--steps", "7", "--no-progress"])
    assert res.exit_code == 0, res.output
    assert load_checkpoint(run / "checkpoint.pt")["step"] == 7
    res = runner.invoke(app, ["train", "--resume", "--run", str(run), "--embedding-dim", "9"])
    assert res.exit_code == 2 and "cannot change ['embedding_dim']" in res.output
    res = runner.invoke(app, ["export", "--run", str(run), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert read_manifest(out)["embedding_dim"] == 4


def test_cli_rejects_bad_values(toy_dataset_dir: Path, tmp_path: Path):
    runner = CliRunner()
    res = runner.invoke(app, ["train", "--preset", "tiny", "--data", str(toy_dataset_dir),
                              "--run", str(tmp_path / "r"), "--point-layers", "8,x"])
    assert res.exit_code == 2 and "point_layers" in res.output
    res = runner.invoke(app, ["train", "--preset", "nope"])
    assert res.exit_code == 2 and "unknown preset 'nope'" in res.output
    res = runner.invoke(app, ["train", "--data", str(tmp_path / "missing"), "--run", str(tmp_path / "r2")])
    assert res.exit_code == 2 and "missing" in res.output


def test_time_budget_stops_the_run(toy_dataset_dir: Path, tmp_path: Path):
    result = train(_tiny(toy_dataset_dir, tmp_path / "run", steps=100000, minutes=0.02), show_progress=False)
    assert 0 < result.step < 100000
    assert load_checkpoint(tmp_path / "run" / "checkpoint.pt")["step"] == result.step


def test_split_is_per_category_seeded_and_checked(toy_dataset, tmp_path: Path):
    split = make_split(toy_dataset, 0.2, seed=1)
    assert sorted(np.concatenate([split.train, split.test]).tolist()) == list(range(toy_dataset.n_shapes))
    cats = [s["category"] for s in toy_dataset.shapes]
    for cat in set(cats):
        n = cats.count(cat)
        held = sum(cats[s] == cat for s in split.test.tolist())
        assert held == max(1, round(0.2 * n))
    again = make_split(toy_dataset, 0.2, seed=1)
    assert (again.test == split.test).all()
    assert any((make_split(toy_dataset, 0.2, seed=s).test != split.test).any() for s in range(2, 6))
    save_split(split, toy_dataset, tmp_path)
    assert (load_split(tmp_path, toy_dataset).test == split.test).all()
    other = toy_dataset.subset(list(range(1, toy_dataset.n_shapes)))
    with pytest.raises(ValueError, match=r"split\.json"):
        load_split(tmp_path, other)


def test_split_seed_picks_the_held_out_draw_apart_from_the_seed(toy_dataset, toy_dataset_dir: Path,
                                                               tmp_path: Path):
    """--split-seed fixes which shapes are held out whatever --seed trains with; -1 follows --seed."""
    held = {}
    for name, seed, split_seed in (("a", 0, 3), ("b", 5, 3), ("c", 5, -1)):
        train(_tiny(toy_dataset_dir, tmp_path / name, steps=1, seed=seed, split_seed=split_seed),
              show_progress=False)
        held[name] = load_split(tmp_path / name, toy_dataset).test
    assert (held["a"] == held["b"]).all() and (held["a"] == make_split(toy_dataset, 0.2, seed=3).test).all()
    assert (held["c"] == make_split(toy_dataset, 0.2, seed=5).test).all()
    assert (held["c"] != held["b"]).any()
    with pytest.raises(ValueError, match="split_seed"):
        _tiny(toy_dataset_dir, tmp_path / "d", split_seed=-2).validate()

def test_lr_schedules():
    exp = resolve_config(overrides={"lr_decay": 0.8, "lr_decay_steps": 100})
    assert lr_factor(exp, 0, 0.0) == 1.0
    assert lr_factor(exp, 100, 0.5) == pytest.approx(0.8)
    assert lr_factor(exp, 150, 0.9) == pytest.approx(0.8 ** 1.5)
    stair = resolve_config(overrides={"lr_decay": 0.8, "lr_decay_steps": 100, "lr_staircase": True})
    assert lr_factor(stair, 150, 0.0) == pytest.approx(0.8)
    cos = resolve_config(overrides={"lr_schedule": "cosine", "lr_final_fraction": 0.1})
    assert lr_factor(cos, 0, 0.0) == pytest.approx(1.0)
    assert lr_factor(cos, 7, 0.5) == pytest.approx(0.55)
    assert lr_factor(cos, 7, 1.0) == pytest.approx(0.1)
    assert lr_factor(cos, 7, 3.0) == pytest.approx(0.1)


@pytest.mark.slow
def test_torchrun_two_processes(toy_dataset_dir: Path, tmp_path: Path):
    """Data-parallel on two CPU processes (gloo): rank 0 writes, both ranks train."""
    run = tmp_path / "run"
    torchrun = Path(sys.executable).parent / "torchrun"
    cmd = [str(torchrun), "--standalone", "--nproc_per_node", "2", "-m", "training", "train",
           "--preset", "tiny", "--data", str(toy_dataset_dir), "--run-dir", str(run), "--steps", "6",
           "--no-progress", "--threads", "1"]
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    # Own session, so a hang kills torchrun and both workers, not only torchrun.
    proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)
    try:
        output, _ = proc.communicate(timeout=240)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        output, _ = proc.communicate()
        pytest.fail(f"torchrun did not finish in 240 s:\n{output}")
    assert proc.returncode == 0, output
    summary = json.loads((run / "summary.json").read_text())
    assert summary["processes"] == 2 and summary["step"] == 6
    assert load_checkpoint(run / "checkpoint.pt")["step"] == 6
    assert read_csv(run / LOSSES_CSV)["step"] == [float(s) for s in range(1, 7)]


@pytest.mark.parametrize("moves", [False, True])
def test_pulls_reach_the_embedding_only_when_asked(moves: bool):
    torch.manual_seed(0)
    y = torch.randn(4, 3, requires_grad=True)
    z = torch.randn(4, 3) + 3.0                       # far negatives: the hinge is inactive
    log_w = torch.log_softmax(torch.randn(4, 2), dim=1)
    means = torch.randn(4, 2, 3, requires_grad=True)
    log_s = torch.log(torch.full((4, 2, 3), 0.05))
    cfg = resolve_config(overrides={"nll_weight": 0.1, "wta_weight": 0.1, "set_nll_weight": 0.1,
                                    "pull_moves_embedding": moves, "margin": 0.001})
    owner, first = torch.arange(4), torch.arange(4)
    loss, hinge, _, _ = retrieval_objective(cfg, y, owner, first, z, log_w, means, log_s)
    assert hinge.item() == 0.0
    loss.backward()
    assert means.grad is not None and means.grad.abs().sum() > 0
    assert (y.grad is not None and y.grad.abs().sum() > 0) == moves


def test_a_fixed_pull_sigma_leaves_g_s_sigmas_out_of_the_pull():
    """With ``wta_sigma`` the pull is the winning mean's squared distance at that sigma: it gives
    g's sigmas no gradient (a mode cannot widen to lower it) and grows with the distance alone."""
    y = torch.tensor([[0.3, 0.0, 0.0]])
    z = torch.full((1, 3), 5.0)                       # a far negative: the hinge is inactive
    log_w = torch.zeros(1, 1)
    means = torch.zeros(1, 1, 3, requires_grad=True)
    owner, first = torch.arange(1), torch.arange(1)
    for wta_sigma, expect_sigma_grad in ((0.0, True), (0.1, False)):
        log_s = torch.log(torch.full((1, 1, 3), 0.05)).requires_grad_(True)
        cfg = resolve_config(overrides={"wta_weight": 1.0, "wta_sigma": wta_sigma, "margin": 0.001})
        loss, hinge, _, _ = retrieval_objective(cfg, y, owner, first, z, log_w, means, log_s)
        assert hinge.item() == 0.0
        loss.backward()
        assert (log_s.grad is not None and log_s.grad.abs().sum().item() > 0) == expect_sigma_grad
    # 0.5 * |y - mu|^2 / sigma^2 plus the Gaussian's constant: the distance term is 0.09 / 0.02 = 4.5
    cfg = resolve_config(overrides={"wta_weight": 1.0, "wta_sigma": 0.1, "margin": 0.001})
    near, _, _, _ = retrieval_objective(cfg, y * 0, owner, first, z, log_w, means.detach(), log_s.detach())
    far, _, _, _ = retrieval_objective(cfg, y, owner, first, z, log_w, means.detach(), log_s.detach())
    assert (far - near).item() == pytest.approx(4.5, rel=1e-4)
    with pytest.raises(ValueError, match="wta_sigma"):
        resolve_config(overrides={"wta_sigma": -0.1}).validate()


def test_split_positive_fits_pull_onto_y_and_fit_the_weights_to_the_others():
    """With ``split_positive_fits`` the pull moves only the mode nearest Y (the first positive) and
    the weights' fit raises only the weight of the mode nearest the other positive; without it both
    fits see both. A query with no other positive keeps its Y in the weights' fit. It needs two
    positives."""
    # Query 0: Y at +x next to mode 0, its other positive at -x next to mode 1. Query 1: Y alone.
    pos = torch.tensor([[0.3, 0.0, 0.0], [-0.3, 0.0, 0.0], [0.3, 0.0, 0.0]])
    owner, first = torch.tensor([0, 0, 1]), torch.tensor([0, 2])
    z = torch.full((2, 3), 5.0)                       # far negatives: the hinge is inactive
    centres = torch.tensor([[0.25, 0.0, 0.0], [-0.25, 0.0, 0.0]]).expand(2, 2, 3)
    log_s = torch.log(torch.full((2, 2, 3), 0.05))
    base = {"wta_weight": 1.0, "wta_weight_ce": 1.0, "wta_epsilon": 0.0, "wta_anneal": 0.0,
            "margin": 0.001, "positives": 2}
    grads = {}
    for split in (False, True):
        means = centres.clone().requires_grad_(True)
        log_w = torch.log(torch.full((2, 2), 0.5)).requires_grad_(True)
        cfg = resolve_config(overrides={**base, "split_positive_fits": split})
        cfg.validate()
        loss, hinge, _, _ = retrieval_objective(cfg, pos, owner, first, z, log_w, means, log_s)
        assert hinge.item() == 0.0
        loss.backward()
        assert means.grad is not None and log_w.grad is not None
        grads[split] = (means.grad[0].abs().sum(dim=1), -log_w.grad[0], -log_w.grad[1])
    pull, fit, alone = grads[False]
    assert (pull > 0).all() and (fit > 0).all()       # both modes pulled, both weights raised
    pull, fit, alone = grads[True]
    assert pull[0] > 0 and pull[1] == 0               # only Y's mode is pulled
    assert fit[0] == 0 and fit[1] > 0                 # only the other positive's mode is fitted
    assert alone[0] > 0                               # Y counts where there is no other
    with pytest.raises(ValueError, match="split_positive_fits"):
        resolve_config(overrides={"split_positive_fits": True, "positives": 1}).validate()


def test_shape_negatives_take_their_own_margin():
    """Triplets whose Z is a shape look-alike of Y are held to ``shape_negative_margin``; the
    others keep Equation 2's margin, and -1 leaves every triplet at that margin."""
    torch.manual_seed(0)
    y, z = torch.zeros(2, 3), torch.full((2, 3), 0.1)
    log_w = torch.zeros(2, 1)
    means, log_s = torch.zeros(2, 1, 3), torch.log(torch.full((2, 1, 3), 0.05))
    owner, first = torch.arange(2), torch.arange(2)
    z_shape = torch.tensor([True, False])
    cfg = resolve_config(overrides={"margin": 50.0, "shape_negative_margin": 1.0})
    _, _, e_pos, e_neg = retrieval_objective(cfg, y, owner, first, z, log_w, means, log_s)
    gap = float((e_neg - e_pos)[0])
    assert 1.0 < gap < 50.0                         # inside the full margin, outside the small one
    _, hinge, _, _ = retrieval_objective(cfg, y, owner, first, z, log_w, means, log_s, z_shape=z_shape)
    assert hinge.item() == pytest.approx((50.0 - gap) / 2, rel=1e-5)   # only the plain triplet counts
    off = resolve_config(overrides={"margin": 50.0})
    _, full, _, _ = retrieval_objective(off, y, owner, first, z, log_w, means, log_s, z_shape=z_shape)
    assert full.item() == pytest.approx(50.0 - gap, rel=1e-5)


def test_set_nll_spreads_the_modes_over_a_query_s_complements():
    """Two distinct complements of one query: fitting the set puts a live mode on each.

    With one positive per query the winner of each pull takes all the weight; the set NLL is an
    MDN fitted to every answer of X, so two modes end up on the two answers with weight ~1/2 each.
    """
    torch.manual_seed(0)
    answers = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    pos = answers.repeat(8, 1)                                   # 8 queries x 2 complements
    owner = torch.arange(8).repeat_interleave(2)
    first = torch.arange(0, 16, 2)
    z = torch.full((8, 3), 5.0)
    logits = torch.zeros(8, 3, requires_grad=True)
    means = (0.1 * torch.randn(8, 3, 3)).requires_grad_(True)
    log_s = torch.log(torch.full((8, 3, 3), 0.3))
    cfg = resolve_config(overrides={"set_nll_weight": 1.0, "wta_weight": 0.1, "margin": 0.001})
    opt = torch.optim.Adam([logits, means], lr=0.05)
    for _ in range(300):
        log_w = torch.log_softmax(logits, dim=1)
        loss, _, _, _ = retrieval_objective(cfg, pos, owner, first, z, log_w, means, log_s)
        opt.zero_grad()
        loss.backward()
        opt.step()
    w = torch.softmax(logits, dim=1)[0].detach()
    dist = torch.cdist(answers, means[0].detach())                # (2 answers, 3 modes)
    assert float(dist.min(dim=1).values.max()) < 0.1              # a mode on each answer
    mass = [float(w[dist[i] < 0.1].sum()) for i in range(2)]      # (two modes may share one)
    assert all(abs(m - 0.5) < 0.05 for m in mass), mass


def _fit_shared_mixture(anneal: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One query X answered by two complements in turn (one positive per draw, as in v3).

    Mode 0 starts between the answers and the others far off. Returns (answers, weights, means)
    after the fit.
    """
    torch.manual_seed(0)
    answers = torch.tensor([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    pos = answers.repeat(4, 1)                                     # 8 draws, alternating answers
    owner = first = torch.arange(8)
    z = torch.full((8, 3), 5.0)
    logits = torch.zeros(3, requires_grad=True)
    start = torch.tensor([[0.0, 0.0, 0.0], [0.0, 3.0, 0.0], [0.0, -3.0, 0.0]])
    means = (start + 0.05 * torch.randn(3, 3)).requires_grad_(True)
    log_s = torch.log(torch.full((8, 3, 3), 0.3))
    steps = 400
    cfg = resolve_config(overrides={"wta_weight": 0.1, "wta_anneal": anneal, "wta_weight_ce": 1.0,
                                    "margin": 0.001, "steps": steps})
    opt = torch.optim.Adam([logits, means], lr=0.05)
    for step in range(steps):
        log_w = torch.log_softmax(logits, dim=0).expand(8, 3)
        loss, _, _, _ = retrieval_objective(cfg, pos, owner, first, z, log_w, means.expand(8, 3, 3), log_s,
                                            step)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return answers, torch.softmax(logits, dim=0).detach(), means.detach()


def test_evolving_wta_and_winner_weights_give_each_answer_a_live_mode():
    answers, w, means = _fit_shared_mixture(anneal=0.5)
    dist = torch.cdist(answers, means)                            # (2 answers, 3 modes)
    assert float(dist.min(dim=1).values.max()) < 0.1              # a mode on each answer
    mass = [float(w[dist[i] < 0.1].sum()) for i in range(2)]
    assert all(abs(m - 0.5) < 0.1 for m in mass), mass           # weights = share of wins
    # The hinge is inactive here (far negatives): without the winner cross-entropy the weights
    # would stay at 1/3 each.

