"""Shapes and invariances of f, g and h, the sigma parametrisations, and the config."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from training.config import PRESETS, ModelConfig, TrainConfig, apply_overrides, config_to_dict, resolve_config
from training.models import PlacementNet, PointNetEncoder, RetrievalNet, build_models

TINY = ModelConfig(point_layers=(8, 16), fc_layers=(16,), embedding_dim=6, n_modes=3,
                   placement_point_layers=(8, 16), placement_fc_layers=(12,), placement_head_layers=(10,))


def _points(b: int, n: int, seed: int = 0) -> torch.Tensor:
    return torch.rand(b, n, 3, generator=torch.Generator().manual_seed(seed)) - 0.5


def test_output_shapes():
    pair, placement = build_models(TINY)
    pair.eval()
    placement.eval()
    X, Y = _points(4, 50), _points(4, 30, seed=1)
    assert pair.f(Y).shape == (4, 6)
    w, mu, sigma = pair.g(X)
    assert w.shape == (4, 3) and mu.shape == (4, 3, 6) and sigma.shape == (4, 3, 6)
    assert placement(X, Y).shape == (4, 3)
    assert placement.query(X).shape == (4, 12) and placement.part(Y).shape == (4, 12)


def test_paper_size_encoder_layers():
    enc = PointNetEncoder((64, 64, 64, 128, 1024), (512, 256))
    convs = [m for m in enc.point_mlp if isinstance(m, torch.nn.Conv1d)]
    assert [c.out_channels for c in convs] == [64, 64, 64, 128, 1024]
    assert enc.out_dim == 256


def test_encoders_ignore_point_order_and_accept_any_point_count():
    torch.manual_seed(0)
    pair, placement = build_models(TINY)
    pair.eval()
    placement.eval()
    X = _points(3, 64)
    perm = torch.randperm(64)
    with torch.no_grad():
        torch.testing.assert_close(pair.f(X), pair.f(X[:, perm]))
        torch.testing.assert_close(placement(X, X), placement(X[:, perm], X))
        # Repeating the cloud changes N but not the max-pooled features.
        torch.testing.assert_close(pair.f(X), pair.f(torch.cat([X, X], dim=1)))


@pytest.mark.parametrize("param", ["sigmoid", "exp_clip"])
def test_mixture_is_a_distribution_with_bounded_sigmas(param: str):
    cfg = dataclasses.replace(TINY, sigma_param=param)
    g = RetrievalNet(cfg).eval()
    with torch.no_grad():
        w, _, sigma = g(_points(5, 40) * 20)       # large inputs push raw sigmas to extremes
        log_w, _, log_s = g.forward_log(_points(5, 40) * 20)
    torch.testing.assert_close(w.sum(1), torch.ones(5))
    assert (w >= 0).all()
    assert (sigma >= cfg.sigma_min - 1e-7).all() and (sigma <= cfg.sigma_max + 1e-7).all()
    assert torch.isfinite(log_w).all() and torch.isfinite(log_s).all()


def test_sigmoid_sigmas_start_inside_the_limits_with_a_gradient():
    """The pitfall: exp(raw) clipped at 0.05 with raw ~ 0 sits at the clip, with zero gradient."""
    torch.manual_seed(0)
    g = RetrievalNet(TINY).train()
    _, _, log_s = g.forward_log(_points(8, 32))
    sigma = log_s.exp()
    assert (sigma < TINY.sigma_max * 0.99).all() and (sigma > TINY.sigma_min * 1.01).all()
    log_s.sum().backward()
    assert g.sigma_head.weight.grad is not None and g.sigma_head.weight.grad.abs().sum() > 0


def test_exp_clip_starts_below_the_clip_thanks_to_its_bias():
    torch.manual_seed(0)
    cfg = dataclasses.replace(TINY, sigma_param="exp_clip", sigma_log_bias=-4.0)
    g = RetrievalNet(cfg).eval()
    with torch.no_grad():
        _, _, sigma = g(_points(8, 32))
    assert (sigma < cfg.sigma_max).float().mean() > 0.95


def test_placement_splits_into_query_part_and_head():
    torch.manual_seed(0)
    h = PlacementNet(TINY).eval()
    X, Y = _points(4, 40), _points(4, 20, seed=3)
    with torch.no_grad():
        torch.testing.assert_close(h(X, Y), h.head(h.query(X), h.part(Y)))


@pytest.mark.parametrize("hidden,batch_norm,scale",
                         [((10, 7), True, True), ((10,), False, False), ((), True, False)])
def test_exported_placement_graphs_compose_to_h(hidden: tuple[int, ...], batch_norm: bool, scale: bool):
    """h_head on the projected branches (what the service runs) is h, at any head depth."""
    torch.manual_seed(0)
    cfg = dataclasses.replace(TINY, placement_head_layers=hidden, batch_norm=batch_norm, predict_scale=scale)
    h = PlacementNet(cfg).eval()
    graphs = h.exported_modules()
    X, Y = _points(4, 40), _points(4, 20, seed=3)
    with torch.no_grad():
        qf, pf = graphs["h_query"](X), graphs["h_part"](Y)
        assert qf.shape == (4, h.query_dim) and pf.shape == (4, h.part_dim)
        torch.testing.assert_close(graphs["h_head"](qf, pf), h(X, Y))


def test_a_checkpoint_with_the_concatenated_head_loads_as_the_same_function():
    """Runs trained before the head's first layer was split (one Linear over the concatenation,
    ``mlp.*``) load into the split head and compute what the old head computed."""
    torch.manual_seed(0)
    cfg = dataclasses.replace(TINY, placement_head_layers=(10, 7), predict_scale=True)
    h = PlacementNet(cfg)
    fq, fp = h.query.out_dim, h.part.out_dim
    nn = torch.nn
    old = nn.Sequential(nn.Linear(fq + fp, 10, bias=False), nn.BatchNorm1d(10), nn.ReLU(),
                        nn.Linear(10, 7, bias=False), nn.BatchNorm1d(7), nn.ReLU(), nn.Linear(7, 6))
    for m in old:
        if isinstance(m, torch.nn.BatchNorm1d):   # not the identity, so a misplaced buffer shows
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
    state = {k: v for k, v in h.state_dict().items() if not k.startswith("head.")}
    state.update({f"head.mlp.{k}": v for k, v in old.state_dict().items()})
    h.load_state_dict(state)
    h.eval()
    old.eval()
    X, Y = _points(4, 40), _points(4, 20, seed=3)
    with torch.no_grad():
        want = old(torch.cat([h.query(X), h.part(Y)], dim=1))
        translation, log_scale = h(X, Y)
    torch.testing.assert_close(torch.cat([translation, log_scale], dim=1), want)


def test_config_presets_resolve_and_validate():
    for name in PRESETS:
        cfg = resolve_config(name)
        assert isinstance(cfg, TrainConfig)
    paper = resolve_config("paper")
    assert paper.model.point_layers == (64, 64, 64, 128, 1024) and paper.model.fc_layers == (512, 256)
    cfg = resolve_config("shipped",
                         overrides={"point_layers": "32,64", "steps": 7, "sigma_param": "exp_clip"})
    assert cfg.model.point_layers == (32, 64) and cfg.steps == 7 and cfg.model.sigma_param == "exp_clip"
    # Round trip through the stored dict.
    assert apply_overrides(TrainConfig(), config_to_dict(cfg)) == cfg


def test_config_errors_name_the_bad_option():
    with pytest.raises(ValueError, match="unknown option 'stepz'"):
        resolve_config(overrides={"stepz": 3})
    with pytest.raises(ValueError, match="unknown preset"):
        resolve_config("huge")
    with pytest.raises(ValueError, match="sigma_param"):
        resolve_config(overrides={"sigma_param": "softplus"})
    with pytest.raises(ValueError, match="point_layers"):
        resolve_config(overrides={"point_layers": "64,x"})
    with pytest.raises(ValueError, match="batch_size"):
        resolve_config(overrides={"batch_size": 0})


def test_config_file_is_read(tmp_path):
    path = tmp_path / "c.json"
    path.write_text('{"steps": 12, "model": {"embedding_dim": 10}}')
    cfg = resolve_config("tiny", path, {"steps": 13})
    assert cfg.steps == 13 and cfg.model.embedding_dim == 10
    assert cfg.batch_size == PRESETS["tiny"]["batch_size"]
    path.write_text("[1, 2]")
    with pytest.raises(ValueError, match=str(path)):
        resolve_config(config_file=path)


def test_embedding_sphere_puts_embeddings_and_means_at_the_radius():
    torch.manual_seed(0)
    cfg = dataclasses.replace(TINY, embedding_radius=2.0)
    pair, _ = build_models(cfg)
    pair.eval()
    with torch.no_grad():
        emb = pair.f(_points(4, 30))
        _, means, _ = pair.g(_points(4, 30))
    torch.testing.assert_close(emb.norm(dim=1), torch.full((4,), 2.0))
    torch.testing.assert_close(means.norm(dim=2), torch.full((4, 3), 2.0))
