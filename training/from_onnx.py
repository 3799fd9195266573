"""The torch networks of an exported artifact folder, with their weights read back from its graphs.

Why: the shipped model is its ONNX graphs; the training checkpoint stays behind in ``runs/``,
which is not committed. Code that needs the shipped model in torch (the benchmark's peer
baseline) rebuilds it here from ``manifest.json``'s model config and the graphs' initializers,
and gets exactly the function the service serves.

What the exporter changed, and how it is undone:

* parameters and batch-norm buffers that stayed in the graph keep their torch names (``fc.1.*``,
  ``mean_head.*``): copied as they are;
* each per-point ``Conv1d`` + ``BatchNorm1d`` pair became one ``Conv`` with a bias: the torch
  conv takes the folded weight and its batch norm becomes the identity plus that bias
  (weight 1, mean 0, variance ``1 - eps`` so the divisor is exactly 1);
* a ``Linear`` without a bias became a ``MatMul`` by its transposed weight (h's branches end
  with their half of the head's first layer, ``models.ProjectedBranch``).

Those two kinds have anonymous initializers; they are matched to the torch layers in order
(graph order is module order for these feed-forward nets). Every graph is then run in both
onnxruntime and torch on the same input, and a mismatch is an error, not a silent difference.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import numpy_helper
from torch import nn

from service.artifacts.layout import GRAPH_FILES, GRAPH_INPUTS, MANIFEST
from service.artifacts.loading import build_session
from training.checkpoint import Trained
from training.config import ModelConfig, TrainConfig, model_config_from_dict
from training.export import example_inputs, graph_modules, output_names
from training.models import PlacementNet, RetrievalPair, build_models

# Largest difference between onnxruntime's and torch's outputs accepted as "the same network".
PARITY_ATOL = 1e-4


def load_exported_networks(artifacts: Path) -> tuple[RetrievalPair, PlacementNet, ModelConfig]:
    """f, g and h of an artifact folder in torch (eval mode, CPU), checked against its graphs."""
    artifacts = Path(artifacts)
    manifest = json.loads((artifacts / MANIFEST).read_text())
    cfg = model_config_from_dict(manifest["model_config"])
    pair, placement = build_models(cfg)
    pair.eval()
    placement.eval()
    for graph, module in graph_modules(pair, placement).items():
        path = artifacts / GRAPH_FILES[graph]
        model = onnx.load(str(path))
        if graph == "h_head" and any(node.op_type == "Concat" for node in model.graph.node):
            raise ValueError(f"{path}: exported before h's head was split between its branches "
                             "(training.models.PlacementHead); export the run again to read it here")
        load_graph_weights(module, model, str(path))
        check_parity(module, graph, path, placement)
    return pair, placement, cfg


def trained_from_artifacts(artifacts: Path, suffix: str = "recatalogued") -> tuple[Trained, str]:
    """The networks of an artifact folder as a run's ``Trained``, and a name for their re-export
    (the model's name with ``suffix`` in place of its graphs' hash).

    The stored training record of the manifest stands in for the checkpoint (step, wall time,
    validation, N): re-exporting a shipped model over another dataset (``complementme export
    --from-artifacts``) keeps what it was trained with, and only its catalog changes.
    """
    pair, placement, model_cfg = load_exported_networks(artifacts)
    manifest = json.loads((Path(artifacts) / MANIFEST).read_text())
    record = manifest.get("training", {})
    cfg = TrainConfig(model=model_cfg, n_points=int(record.get("n_points", manifest["n_points"])),
                      batch_size=int(record.get("batch_size", TrainConfig.batch_size)),
                      seed=int(record.get("seed", 0)))
    state = {"step": int(record.get("steps", 0)),
             "elapsed_seconds": 60.0 * float(record.get("wall_minutes", 0.0)),
             "validation": dict(record.get("validation", {})),
             "final_losses": dict(record.get("final_losses", {})),
             **({"started_from": record["started_from"]} if record.get("started_from") else {})}
    # "shipped-s7115-f41e768a7b" -> "shipped-s7115-recatalogued": the graphs' hash is added again.
    name = str(manifest["model_version"]).rsplit("-", 1)[0] + "-" + suffix
    return Trained(config=cfg, pair=pair, placement=placement, state=state), name


def load_graph_weights(module: nn.Module, model: onnx.ModelProto, source: str) -> None:
    """Set ``module``'s parameters and buffers from one exported graph (see the module doc)."""
    inits = {t.name: numpy_helper.to_array(t) for t in model.graph.initializer}
    state = {name: t.clone() for name, t in module.state_dict().items()}
    for name in state:
        if name in inits:
            state[name] = _tensor(inits[name], state[name], f"{source}: {name}")
    folded = _folded_layers(model, inits)
    layers = [(name, m) for name, m in module.named_modules()
              if isinstance(m, (nn.Conv1d, nn.Linear)) and f"{name}.weight" not in inits]
    if len(layers) != len(folded):
        raise ValueError(f"{source}: {len(folded)} unnamed layers in the graph, {len(layers)} in the "
                         "network the manifest describes")
    for (name, layer), (weight, bias) in zip(layers, folded, strict=True):
        state[f"{name}.weight"] = _tensor(weight, state[f"{name}.weight"], f"{source}: {name}.weight")
        if bias is None:
            continue
        if layer.bias is not None:
            state[f"{name}.bias"] = _tensor(bias, state[f"{name}.bias"], f"{source}: {name}.bias")
            continue
        norm = _next_batch_norm(module, name)
        if norm is None:
            raise ValueError(f"{source}: {name} has a bias in the graph but neither a bias nor a batch norm")
        state[f"{norm}.weight"] = torch.ones_like(state[f"{norm}.weight"])
        state[f"{norm}.bias"] = _tensor(bias, state[f"{norm}.bias"], f"{source}: {norm}.bias")
        state[f"{norm}.running_mean"] = torch.zeros_like(state[f"{norm}.running_mean"])
        eps = float(module.get_submodule(norm).eps)  # type: ignore[arg-type]
        state[f"{norm}.running_var"] = torch.full_like(state[f"{norm}.running_var"], 1.0 - eps)
    module.load_state_dict(state)


def _folded_layers(model: onnx.ModelProto, inits: dict[str, np.ndarray]
                   ) -> list[tuple[np.ndarray, np.ndarray | None]]:
    """(torch-shaped weight, bias or None) of each Conv or MatMul whose weight lost its name."""
    layers: list[tuple[np.ndarray, np.ndarray | None]] = []
    for node in model.graph.node:
        if node.op_type == "Conv" and node.input[1] in inits and not _named(node.input[1]):
            bias = inits[node.input[2]] if len(node.input) > 2 else None
            layers.append((inits[node.input[1]], bias))
        elif node.op_type == "MatMul" and node.input[1] in inits and not _named(node.input[1]):
            layers.append((inits[node.input[1]].T, None))
    return layers


def _named(initializer: str) -> bool:
    """Whether the exporter kept a torch name (``onnx::Conv_63`` is one it made up)."""
    return not initializer.startswith("onnx::")


def _next_batch_norm(module: nn.Module, layer: str) -> str | None:
    """Name of the batch norm right after ``layer`` in its ``nn.Sequential``, if there is one."""
    parent, _, index = layer.rpartition(".")
    container = module.get_submodule(parent) if parent else module
    if not isinstance(container, nn.Sequential) or not index.isdigit() or int(index) + 1 >= len(container):
        return None
    follower = container[int(index) + 1]
    return f"{parent}.{int(index) + 1}" if isinstance(follower, nn.BatchNorm1d) else None


def _tensor(value: np.ndarray, like: torch.Tensor, what: str) -> torch.Tensor:
    if tuple(value.shape) != tuple(like.shape):
        raise ValueError(f"{what}: shape {tuple(value.shape)} in the graph, "
                         f"{tuple(like.shape)} in the network")
    return torch.tensor(np.asarray(value), dtype=like.dtype)


def check_parity(module: nn.Module, graph: str, path: Path, placement: PlacementNet) -> None:
    """Run the graph in onnxruntime and ``module`` in torch on one input; ``ValueError`` if they differ."""
    inputs = example_inputs(graph, placement, batch=3, n=128)
    session = build_session(path, torch.get_num_threads())
    names = output_names(graph, module)   # with the optional heads (category, scale) it has
    expected = session.run(names, {name: x.numpy() for name, x in
                                                  zip(GRAPH_INPUTS[graph], inputs, strict=True)})
    with torch.no_grad():
        got = module(*inputs)
    got = got if isinstance(got, tuple) else (got,)
    for name, a, b in zip(names, expected, got, strict=True):
        diff = float(np.abs(a - b.numpy()).max())
        if not diff <= PARITY_ATOL:
            raise ValueError(f"{path}: torch and onnxruntime differ by {diff:.2e} on {name!r} "
                             f"(more than {PARITY_ATOL:g}): the weights were not read back correctly")
