"""Checkpoints of a run: weights, optimiser states, step, elapsed time and config.

(The learning rate is a function of the step and the run's progress, so no scheduler state.)

One loader (``load_trained``) serves resume, evaluation and export, so they all rebuild the
networks from the config stored next to the weights.
"""

from __future__ import annotations

import io
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from service.artifacts.files import write_file_atomic
from training.config import TrainConfig, config_from_dict, config_to_dict, known_options
from training.models import PlacementNet, RetrievalPair, build_models

CHECKPOINT_FILE = "checkpoint.pt"
CONFIG_FILE = "config.json"
SUMMARY_FILE = "summary.json"
CHECKPOINT_FORMAT = 1

log = logging.getLogger(__name__)


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
    return _stored_config(json.loads(path.read_text()), path)[0]


def _stored_config(data: dict[str, Any], source: Path) -> tuple[TrainConfig, list[str]]:
    """A stored config read for its weights: options this version does not know are ignored
    (``config.known_options`` says why), with a warning; returns the config and their names."""
    known, unknown = known_options(data)
    if unknown:
        log.warning("%s: ignoring options of the stored config that this version does not know: %s",
                    source, ", ".join(unknown))
    return config_from_dict(known), unknown


def load_trained(run_dir: Path) -> Trained:
    """Rebuild f, g and h of a run folder from its checkpoint (eval mode, CPU).

    Options of the stored config that this code does not know (a run trained by another version)
    are ignored with a warning; if the weights then do not fit the networks, the error names them.
    Resuming such a run is refused (``train.config_for_resume`` reads the config strictly).
    """
    path = checkpoint_path(run_dir)
    state = load_checkpoint(path)
    cfg, unknown = _stored_config(state["config"], path)
    pair, placement = build_models(cfg.model)
    try:
        pair.load_state_dict(state["retrieval"])
        placement.load_state_dict(state["placement"])
    except RuntimeError as exc:
        why = (f"; the run was trained with options this version does not know ({', '.join(unknown)}), "
               "which may change the networks" if unknown else "")
        raise ValueError(f"{path}: weights do not match the stored config{why} ({exc})") from exc
    pair.eval()
    placement.eval()
    return Trained(config=cfg, pair=pair, placement=placement, state=state)
