"""Checkpoints of a run: weights, optimiser states, step, elapsed time and config.

(The learning rate is a function of the step and the run's progress, so no scheduler state.)

One loader (``load_trained``) serves resume, evaluation and export, so they all rebuild the
networks from the config stored next to the weights.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from service.artifacts.files import write_file_atomic
from training.config import TrainConfig, config_from_dict, config_to_dict
from training.models import PlacementNet, RetrievalPair, build_models

CHECKPOINT_FILE = "checkpoint.pt"
CONFIG_FILE = "config.json"
SUMMARY_FILE = "summary.json"
CHECKPOINT_FORMAT = 1


def summary_of(run_dir: Path) -> dict[str, Any]:
    """The ``summary.json`` of a finished run (empty when the run never finished)."""
    path = Path(run_dir) / SUMMARY_FILE
    return json.loads(path.read_text()) if path.is_file() else {}


def checkpoint_path(run_dir: Path) -> Path:
    return Path(run_dir) / CHECKPOINT_FILE


def save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write a checkpoint through a temporary file and a rename (a crash never leaves half a file)."""
    buf = io.BytesIO()
    torch.save({"format": CHECKPOINT_FORMAT, **state}, buf)
    write_file_atomic(Path(path), buf.getvalue())


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Read a checkpoint written by ``save_checkpoint``; errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises many types for a truncated or foreign file
        raise ValueError(f"cannot read checkpoint {path}: {exc}") from exc
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: not a checkpoint of format {CHECKPOINT_FORMAT}")
    for key in ("config", "step", "retrieval", "placement"):
        if key not in state:
            raise ValueError(f"{path}: checkpoint lacks {key!r}")
    return state


def make_state(cfg: TrainConfig, step: int, elapsed_seconds: float, pair: RetrievalPair,
               placement: PlacementNet, optimizers: dict[str, torch.optim.Optimizer],
               extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """Everything a resume needs, as a dict of tensors and plain values."""
    return {
        "config": config_to_dict(cfg),
        "step": step,
        "elapsed_seconds": elapsed_seconds,
        "retrieval": pair.state_dict(),
        "placement": placement.state_dict(),
        "optimizers": {k: v.state_dict() for k, v in optimizers.items()},
        **(extra or {}),
    }


@dataclass
class Trained:
    """The networks of a run, in eval mode, with the config and checkpoint they came from."""

    config: TrainConfig
    pair: RetrievalPair
    placement: PlacementNet
    state: dict[str, Any]


def load_trained_config(run_dir: Path) -> TrainConfig:
    """The config a run was started with (its ``config.json``), without loading its weights."""
    path = Path(run_dir) / CONFIG_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{path} does not exist: {run_dir} is not a training run folder")
    return config_from_dict(json.loads(path.read_text()))


def load_trained(run_dir: Path) -> Trained:
    """Rebuild f, g and h of a run folder from its checkpoint (eval mode, CPU)."""
    state = load_checkpoint(checkpoint_path(run_dir))
    cfg = config_from_dict(state["config"])
    pair, placement = build_models(cfg.model)
    try:
        pair.load_state_dict(state["retrieval"])
        placement.load_state_dict(state["placement"])
    except RuntimeError as exc:
        raise ValueError(f"{checkpoint_path(run_dir)}: weights do not match the stored config ({exc})") \
            from exc
    pair.eval()
    placement.eval()
    return Trained(config=cfg, pair=pair, placement=placement, state=state)
