"""Joint training of f and g (triplet loss, Section 5.3) and of the placement network h.

f+g and h are trained in the same loop on the same batches, each with its own Adam optimiser
and schedule: sampling a batch is shared, and h's loss never reaches f or g. A run stops at
``cfg.steps`` total steps or after ``cfg.minutes`` of this invocation, whichever comes first.

Distributed data-parallel: launched under ``torchrun`` (``WORLD_SIZE`` > 1) every process joins
a process group (gloo on CPU, nccl on GPUs), samples with its own seed offset, and gradients are
averaged by ``DistributedDataParallel``; rank 0 alone validates and writes checkpoints and logs.

Run folder contents: ``config.json``, ``split.json``, ``checkpoint.pt``, ``losses.csv``,
``validation.csv``, ``losses.png``, ``validation.png``, ``summary.json``.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import nn
from torch.nn.parallel import DistributedDataParallel
from tqdm import tqdm

from service.artifacts.layout import MANIFEST, write_json_atomic
from training.batches import batch_stream
from training.checkpoint import (
    CONFIG_FILE,
    SUMMARY_FILE,
    checkpoint_path,
    load_checkpoint,
    make_state,
    save_checkpoint,
)
from training.config import TrainConfig, apply_overrides, config_from_dict, config_to_dict
from training.data.processed import ProcessedDataset
from training.from_onnx import load_exported_networks
from training.losses import (
    component_log_density,
    matched_modes,
    mixture_nll,
    placement_loss,
    relaxed_wta_pull,
    triplet_loss,
    wta_winners,
)
from training.models import build_models, count_parameters
from training.plots import (
    LOSSES_CSV,
    LOSSES_PNG,
    VALIDATION_CSV,
    VALIDATION_PNG,
    CsvLog,
    plot_columns,
    truncate_after,
)
from training.split import SPLIT_FILE, Split, load_split, make_split, save_split
from training.validation import ValidationSet, build_validation_set, validate

log = logging.getLogger(__name__)

LOSS_FIELDS = ["step", "elapsed_s", "lr", "triplet_loss", "e_pos", "e_neg", "batch_triplet_accuracy",
               "placement_loss", "category_loss", "scale_loss", "placement_lr", "seconds_per_step"]
# Settings a resumed run may change; anything else must match the checkpoint.
RESUMABLE = {"steps", "minutes", "max_minutes", "val_every", "ckpt_every", "log_every", "num_workers",
             "threads", "run"}


@dataclass
class TrainResult:
    """What a finished (or budget-stopped) run reached."""

    run_dir: Path
    step: int
    elapsed_seconds: float
    final_losses: dict[str, float] = field(default_factory=dict)
    validation: dict[str, float] = field(default_factory=dict)


@dataclass
class _Dist:
    rank: int = 0
    world: int = 1
    local_world: int = 1
    owns_group: bool = False

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def _setup_distributed() -> _Dist:
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return _Dist()
    owns = False
    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if torch.cuda.is_available() else "gloo")
        owns = True
    return _Dist(rank=dist.get_rank(), world=dist.get_world_size(),
                 local_world=int(os.environ.get("LOCAL_WORLD_SIZE", str(world))), owns_group=owns)


def lr_factor(cfg: TrainConfig, step: int, progress: float) -> float:
    """Multiplier of the initial learning rate at ``step`` (``progress`` in [0, 1] for cosine)."""
    if cfg.lr_schedule == "cosine":
        p = min(max(progress, 0.0), 1.0)
        return cfg.lr_final_fraction + (1.0 - cfg.lr_final_fraction) * 0.5 * (1.0 + math.cos(math.pi * p))
    periods = step // cfg.lr_decay_steps if cfg.lr_staircase else step / cfg.lr_decay_steps
    return float(cfg.lr_decay ** periods)


def retrieval_objective(cfg: TrainConfig, pos_emb: torch.Tensor, owner: torch.Tensor, first: torch.Tensor,
                        z_emb: torch.Tensor, log_w: torch.Tensor, means: torch.Tensor, log_s: torch.Tensor,
                        step: int = 0, z_shape: torch.Tensor | None = None
                        ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The loss of f and g: Equation 2, plus the optional fits of the mixture to the positives.

    ``pos_emb`` holds every drawn complement of every query (``owner`` says whose; ``first``
    indexes each query's paper positive Y). Equation 2 compares Y with Z. The set NLL is the
    mixture NLL of all of a query's complements, averaged per query, so that each query weighs
    the same however many parts it lacks; the relaxed winner-takes-all pull pulls the nearest
    mode onto each of them. Returns (loss, mean hinge, e_pos, e_neg). Unless
    ``cfg.pull_moves_embedding``, the fits see the embeddings detached: they move g's mixture,
    and f is shaped by Equation 2 alone. ``z_shape`` marks the triplets whose Z is a shape
    look-alike of Y: their margin is ``cfg.shape_negative_margin`` when that is set.

    Shapes:
        pos_emb (M, D), owner (M,) int64, first (B,) int64, z_emb (B, D); log_w (B, K);
        means, log_s (B, K, D); z_shape (B,) bool.
    """
    margin: float | torch.Tensor = cfg.margin
    if z_shape is not None and cfg.shape_negative_margin >= 0:
        margin = torch.where(z_shape, cfg.shape_negative_margin, cfg.margin).to(z_emb.dtype)
    hinge, e_pos, e_neg = triplet_loss(pos_emb[first], z_emb, log_w, means, log_s, margin)
    loss = hinge
    y_fit = pos_emb if cfg.pull_moves_embedding else pos_emb.detach()
    b = len(first)
    share = _shares(owner, torch.ones(len(owner), dtype=torch.bool), b, y_fit.dtype)  # (M,) sums to 1
    pull_share = ce_share = share
    if cfg.split_positive_fits:
        # The pull moves the modes onto each query's first positive Y, the weights' fit counts
        # the others (the first too where a query has no other): Y's draw may favour the main
        # piece of a kind without g's weights learning to favour its kind.
        is_first = torch.zeros(len(owner), dtype=torch.bool)
        is_first[first] = True
        has_other = torch.bincount(owner[~is_first], minlength=b) > 0                  # (B,)
        pull_share = _shares(owner, is_first, b, y_fit.dtype)
        ce_share = _shares(owner, ~is_first | ~has_other[owner], b, y_fit.dtype)
    if cfg.nll_weight:
        loss = loss + cfg.nll_weight * mixture_nll(y_fit[first], log_w, means, log_s).mean()
    if cfg.set_nll_weight:
        nll = mixture_nll(y_fit, log_w[owner], means[owner], log_s[owner])
        loss = loss + cfg.set_nll_weight * (share * nll).sum()
    if cfg.wta_weight:
        winners = wta_winners(step, cfg.steps, means.shape[1], cfg.wta_anneal)
        pull_log_s = log_s[owner]
        if cfg.wta_sigma:
            pull_log_s = torch.full_like(pull_log_s, math.log(cfg.wta_sigma))
        pull = relaxed_wta_pull(y_fit, means[owner], pull_log_s, cfg.wta_epsilon, winners)
        loss = loss + cfg.wta_weight * (pull_share * pull).sum()
    if cfg.wta_weight_ce:
        per_mode = -component_log_density(y_fit, means[owner], log_s[owner]).detach()  # (M, K)
        winner = per_mode.argmin(dim=1)                                                 # (M,)
        loss = loss - cfg.wta_weight_ce * (ce_share * log_w[owner, winner]).sum()
    if cfg.match_weight or cfg.match_weight_ce:
        per_mode = -component_log_density(y_fit, means[owner], log_s[owner])        # (M, K)
        mode = matched_modes(per_mode, owner, b)                                      # (M,)
        rows = torch.arange(len(mode))
        # Each matched mode is pulled onto its complement, and the weights learn the shares of
        # the matching: a seat alone whose complements are a back and legs gets two live modes.
        loss = loss + cfg.match_weight * (share * per_mode[rows, mode]).sum()
        loss = loss - cfg.match_weight_ce * (share * log_w[owner, mode]).sum()
    return loss, hinge, e_pos, e_neg


def _shares(owner: torch.Tensor, keep: torch.Tensor, b: int, dtype: torch.dtype) -> torch.Tensor:
    """Each kept positive's share of a fit in which every query weighs the same (kept rows of a
    query split its 1/B evenly; dropped rows get 0).

    Shapes:
        owner (M,) int64, keep (M,) bool -> (M,) ``dtype``, summing to 1 over the queries with a
        kept row.
    """
    per_query = torch.bincount(owner[keep], minlength=b).clamp(min=1).to(dtype)   # (B,)
    return keep.to(dtype) / (per_query[owner] * b)


def config_for_resume(run_dir: Path, overrides: dict[str, Any]) -> TrainConfig:
    """The stored config of a run, with the few settings a resume may change applied."""
    state = load_checkpoint(checkpoint_path(run_dir))
    stored = config_from_dict(state["config"])
    bad = sorted(k for k in overrides if k not in RESUMABLE)
    if bad:
        changed = [k for k in bad if getattr(stored, k, getattr(stored.model, k, None)) != overrides[k]]
        if changed:
            raise ValueError(f"cannot change {changed} when resuming {run_dir}; "
                             f"only {sorted(RESUMABLE)} may change")
    allowed = {k: v for k, v in overrides.items() if k in RESUMABLE}
    cfg = apply_overrides(stored, allowed, source="command line")
    cfg = dataclasses.replace(cfg, run=str(run_dir))
    cfg.validate()
    return cfg


def _unwrap(m: nn.Module) -> nn.Module:
    return m.module if isinstance(m, DistributedDataParallel) else m


def _mean(values: list[float]) -> float:
    return float(np.mean(values)) if values else math.nan


def train(cfg: TrainConfig, resume: bool = False, show_progress: bool = True) -> TrainResult:
    """Train f, g and h as ``cfg`` says, writing checkpoints and logs into ``cfg.run``."""
    cfg.validate()
    env = _setup_distributed()
    try:
        return _train(cfg, resume, show_progress, env)
    finally:
        if env.owns_group:
            dist.destroy_process_group()


def _train(cfg: TrainConfig, resume: bool, show_progress: bool, env: _Dist) -> TrainResult:
    threads = cfg.threads or max(1, (os.cpu_count() or 1) // env.local_world)
    torch.set_num_threads(threads)
    run_dir = Path(cfg.run)
    ds = ProcessedDataset.load(Path(cfg.data))
    if ds.grouped_by_label:
        raise ValueError(f"{cfg.data}: its components were grouped by their labels for the paper-protocol "
                         "benchmark (complementme evaluate --database grouped); training never reads "
                         "labels, so it does not train on it")
    _prepare_run_dir(run_dir, resume, env)
    split = _split_of(cfg, ds, run_dir, env)
    cfg = _with_category_head(cfg, ds)
    run = _Run(cfg, env, run_dir, threads)
    if resume:
        run.restore()  # a fine-tuned run resumes from its checkpoint, not from init_from again
    elif cfg.init_from:
        run.start_from(Path(cfg.init_from))
    if env.is_main:
        run.open_logs(ds, split)
    stream = batch_stream(ds.subset(split.train), cfg.n_points, cfg.batch_size, seed=cfg.seed, rank=env.rank,
                          start_step=run.step, num_workers=cfg.num_workers, sampler_options={
                              "query_negative_fraction": cfg.query_negative_fraction,
                              "lookalike_negative_fraction": cfg.lookalike_negative_fraction,
                              "shape_negative_fraction": cfg.shape_negative_fraction,
                              "positive_size_power": cfg.positive_size_power,
                              "removal_query_fraction": cfg.removal_query_fraction,
                              "positives": cfg.positives, "augment": cfg.augment,
                              "augment_strength": cfg.augment_strength, "augment_parts": cfg.augment_parts,
                              "scale_augment": cfg.scale_augment,
                              "substitute_fraction": cfg.substitute_fraction,
                              "mixed_query_fraction": cfg.mixed_query_fraction,
                              "layout_warp": cfg.layout_warp,
                              "categories": ds.categories()})
    run.start_clock()
    bar = tqdm(total=cfg.steps, initial=run.step, disable=not (show_progress and env.is_main),
               desc="train", dynamic_ncols=True)
    while run.step < cfg.steps:
        progress = run.progress()
        if run.should_stop(progress):
            break
        run.set_learning_rates(lr_factor(cfg, run.step, progress))
        batch = next(stream)
        if cfg.train_retrieval:
            run.retrieval_step(batch)
        if cfg.train_placement:
            run.placement_step(batch)
        run.step += 1
        run.steps_in_window += 1
        bar.update(1)
        if run.step % cfg.log_every == 0 or run.step == cfg.steps:
            bar.set_postfix(run.log_row())
        if cfg.val_every and run.step % cfg.val_every == 0:
            run.validate()
        if run.step % cfg.ckpt_every == 0:
            run.checkpoint()
    bar.close()
    return run.finish()


def _prepare_run_dir(run_dir: Path, resume: bool, env: _Dist) -> None:
    """Refuse to overwrite a run, or to resume one that does not exist; make the folder."""
    ckpt = checkpoint_path(run_dir)
    if env.is_main:
        if ckpt.exists() and not resume:
            raise FileExistsError(f"{ckpt} exists: pass --resume to continue that run, "
                                  "or choose another --run")
        if resume and not ckpt.exists():
            raise FileNotFoundError(f"cannot resume: {ckpt} does not exist")
        run_dir.mkdir(parents=True, exist_ok=True)
    if env.world > 1:
        dist.barrier()


def _split_of(cfg: TrainConfig, ds: ProcessedDataset, run_dir: Path, env: _Dist) -> Split:
    """The run's train/test split: the stored one when resuming, else a new one saved beside it."""
    if (run_dir / SPLIT_FILE).exists():
        split = load_split(run_dir, ds)
    else:
        seed = cfg.seed if cfg.split_seed < 0 else cfg.split_seed
        split = make_split(ds, cfg.test_fraction, seed, by_style=cfg.split == "styles")
        if env.is_main:
            save_split(split, ds, run_dir)
    if len(split.test) == 0:
        raise ValueError(f"{cfg.data}: too few shapes per category to hold out a test split")
    return split


def _with_category_head(cfg: TrainConfig, ds: ProcessedDataset) -> TrainConfig:
    """``cfg`` with the category head sized to the dataset's category folders when it is trained."""
    if cfg.category_weight > 0 and cfg.model.n_categories == 0:
        # The head's classes are the collection's category folders (ProcessedDataset.categories).
        n_categories = len(ds.categories())
        cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, n_categories=n_categories))
    if cfg.model.n_categories not in (0, len(ds.categories())):
        raise ValueError(f"{cfg.data}: the dataset has {len(ds.categories())} categories, the model's "
                         f"category head {cfg.model.n_categories}")
    return cfg


class _Run:
    """One invocation of a training run: its networks, optimisers, position, logs and clocks.

    Each method is one named step of the loop in ``_train``; rank 0 alone writes files.
    """

    def __init__(self, cfg: TrainConfig, env: _Dist, run_dir: Path, threads: int) -> None:
        self.cfg, self.env, self.run_dir, self.threads = cfg, env, run_dir, threads
        self.ckpt = checkpoint_path(run_dir)
        torch.manual_seed(cfg.seed)
        self.pair, self.placement = build_models(cfg.model)
        if not cfg.train_embedding:
            self.pair.f.requires_grad_(False)
        trained = self.pair.parameters() if cfg.train_embedding else self.pair.g.parameters()
        self.opt_r = torch.optim.Adam(trained, lr=cfg.lr)
        self.opt_p = torch.optim.Adam(self.placement.parameters(), lr=cfg.placement_lr)
        self.step, self.elapsed_before = 0, 0.0
        self.last_validation: dict[str, float] = {}
        self.started_from: str | None = None  # model_version of the export the run started from
        self.validated_at = -1
        self.train_mode()
        self.pair_run: nn.Module = DistributedDataParallel(self.pair) if env.world > 1 else self.pair
        self.place_run: nn.Module = (DistributedDataParallel(self.placement) if env.world > 1
                                     else self.placement)
        self.vset: ValidationSet | None = None
        self.loss_log: CsvLog | None = None
        self.val_log: CsvLog | None = None
        self.window: dict[str, list[float]] = {k: [] for k in LOSS_FIELDS[3:10]}
        self.recent: dict[str, deque[float]] = {k: deque(maxlen=100)
                                                 for k in ("triplet_loss", "placement_loss")}
        self.t_start = time.monotonic()
        self.t_window = self.t_start
        self.steps_in_window = 0

    def start_from(self, artifacts: Path) -> None:
        """Copy the networks of an exported model into this run's (``init_from``)."""
        pair, placement, model_cfg = load_exported_networks(artifacts)
        if model_cfg != self.cfg.model:
            raise ValueError(f"{artifacts / MANIFEST}: its model config {model_cfg} is not this run's "
                             f"{self.cfg.model}; give the preset it was trained with")
        self.started_from = str(json.loads((artifacts / MANIFEST).read_text())["model_version"])
        self.pair.load_state_dict(pair.state_dict())
        self.placement.load_state_dict(placement.state_dict())
        log.info("starting from the networks of %s (batch norm frozen)", artifacts)

    def train_mode(self) -> None:
        """Training mode for f, g and h; batch norm stays in eval mode when fine-tuning, and a
        fixed f (``train_embedding`` off) is in eval mode throughout (no dropout, no statistics)."""
        for net in (self.pair, self.placement):
            net.train()
            if self.cfg.init_from:
                for m in net.modules():
                    if isinstance(m, nn.modules.batchnorm._BatchNorm):
                        m.eval()
        if not self.cfg.train_embedding:
            self.pair.f.eval()

    def restore(self) -> None:
        """Continue from the checkpoint: weights, optimisers, step, time, last validation."""
        state = load_checkpoint(self.ckpt)
        self.pair.load_state_dict(state["retrieval"])
        self.placement.load_state_dict(state["placement"])
        self.opt_r.load_state_dict(state["optimizers"]["retrieval"])
        self.opt_p.load_state_dict(state["optimizers"]["placement"])
        self.step, self.elapsed_before = int(state["step"]), float(state["elapsed_seconds"])
        self.last_validation = dict(state.get("validation", {}))
        self.started_from = state.get("started_from")
        log.info("resuming %s at step %d (%.1f min trained)", self.run_dir, self.step,
                 self.elapsed_before / 60)
        if self.env.is_main:
            truncate_after(self.run_dir / LOSSES_CSV, self.step)
            truncate_after(self.run_dir / VALIDATION_CSV, self.step)

    def open_logs(self, ds: ProcessedDataset, split: Split) -> None:
        """Write the config, build the fixed validation set and open the CSV logs (rank 0)."""
        cfg = self.cfg
        write_json_atomic(self.run_dir / CONFIG_FILE, config_to_dict(cfg))
        log.info("f+g: %d parameters, h: %d parameters, %d train / %d test shapes, %d threads x %d processes",
                 count_parameters(self.pair), count_parameters(self.placement), len(split.train),
                 len(split.test), self.threads, self.env.world)
        self.vset = build_validation_set(ds, split.test, cfg.val_triplets, cfg.n_points, cfg.seed)
        self.loss_log = CsvLog(self.run_dir / LOSSES_CSV, LOSS_FIELDS)
        self.val_log = CsvLog(self.run_dir / VALIDATION_CSV, ["step", "elapsed_s", *_validation_keys(cfg)])

    def start_clock(self) -> None:
        """Time starts here, when the loop starts (set-up and the validation set are not counted)."""
        self.t_start = self.t_window = time.monotonic()

    def elapsed(self) -> float:
        return self.elapsed_before + time.monotonic() - self.t_start

    def progress(self) -> float:
        """Progress through the budget: steps, or this invocation's share of --minutes (all ranks agree)."""
        cfg = self.cfg
        progress = self.step / cfg.steps
        if cfg.minutes > 0:
            progress = max(progress, (time.monotonic() - self.t_start) / (cfg.minutes * 60))
        if self.env.world > 1:  # every rank must stop at the same step and use the same learning rate
            shared = torch.tensor([progress], dtype=torch.float64)
            dist.all_reduce(shared, op=dist.ReduceOp.MAX)
            progress = float(shared.item())
        return progress

    def should_stop(self, progress: float) -> bool:
        """True when the time budget, or the time guard, ends the run before its last step."""
        cfg = self.cfg
        if cfg.minutes > 0 and progress >= 1.0:
            log.info("time budget of %.1f min reached at step %d", cfg.minutes, self.step)
            return True
        guard = time.monotonic() - self.t_start >= cfg.max_minutes * 60 if cfg.max_minutes > 0 else False
        if self.env.world > 1:
            flag = torch.tensor([float(guard)])
            dist.all_reduce(flag, op=dist.ReduceOp.MAX)
            guard = bool(flag.item())
        if guard:
            log.warning("time guard of %.1f min reached at step %d of %d: the run stops early",
                        cfg.max_minutes, self.step, cfg.steps)
        return guard

    def set_learning_rates(self, factor: float) -> None:
        for group in self.opt_r.param_groups:
            group["lr"] = self.cfg.lr * factor
        for group in self.opt_p.param_groups:
            group["lr"] = self.cfg.placement_lr * factor

    def retrieval_step(self, batch: dict[str, torch.Tensor]) -> None:
        """One optimiser step of f (unless ``train_embedding`` is off) and g on a batch (and of g's
        category head, when trained)."""
        cfg, window = self.cfg, self.window
        X, Z = batch["X"], batch["Z"]
        mask = batch["P_mask"]
        pos = batch["P"][mask]                                   # (M, N, 3), each query's Y first
        counts = mask.sum(dim=1)
        first = torch.cumsum(counts, 0) - counts                 # (B,) index of each query's Y
        owner = torch.repeat_interleave(torch.arange(len(X)), counts)
        emb, log_w, means, log_s, logits = self.pair_run(X, torch.cat([pos, Z]))
        m = len(pos)
        loss, hinge, e_pos, e_neg = retrieval_objective(cfg, emb[:m], owner, first, emb[m:], log_w, means,
                                                        log_s, self.step, batch.get("Z_shape"))
        if cfg.category_weight and logits is not None:
            closs = F.cross_entropy(logits, batch["category"])
            loss = loss + cfg.category_weight * closs
            window["category_loss"].append(closs.item())
        if not torch.isfinite(loss):
            raise FloatingPointError(f"triplet loss is {loss.item()} at step {self.step}")
        self.opt_r.zero_grad(set_to_none=True)
        loss.backward()
        self.opt_r.step()
        window["triplet_loss"].append(hinge.item())
        window["e_pos"].append(e_pos.mean().item())
        window["e_neg"].append(e_neg.mean().item())
        window["batch_triplet_accuracy"].append((e_pos < e_neg).float().mean().item())
        self.recent["triplet_loss"].append(hinge.item())

    def placement_step(self, batch: dict[str, torch.Tensor]) -> None:
        """One optimiser step of h (and of its scale head, when the model has one)."""
        out = self.place_run(batch["X"], batch["Y_h"])
        T = batch["Y_translation"]
        if isinstance(out, tuple):
            translation, log_scale = out
            sloss = (log_scale - batch["Y_log_scale"]).square().mean()
            self.window["scale_loss"].append(sloss.item())
            ploss = placement_loss(translation, T) + self.cfg.scale_weight * sloss
        else:
            ploss = placement_loss(out, T)
        if not torch.isfinite(ploss):
            raise FloatingPointError(f"placement loss is {ploss.item()} at step {self.step}")
        self.opt_p.zero_grad(set_to_none=True)
        ploss.backward()
        self.opt_p.step()
        self.window["placement_loss"].append(ploss.item())
        self.recent["placement_loss"].append(ploss.item())

    def log_row(self) -> dict[str, str]:
        """Append the window's means to losses.csv, start a new window; the progress bar's postfix."""
        now = time.monotonic()
        row = {"step": self.step, "elapsed_s": self.elapsed(), "lr": self.opt_r.param_groups[0]["lr"],
               "placement_lr": self.opt_p.param_groups[0]["lr"],
               "seconds_per_step": (now - self.t_window) / max(self.steps_in_window, 1),
               **{k: _mean(v) for k, v in self.window.items()}}
        if self.loss_log is not None:
            self.loss_log.append(row)
        self.window = {k: [] for k in self.window}
        self.t_window, self.steps_in_window = now, 0
        shown = ("triplet_loss", "placement_loss", "seconds_per_step")
        return {k: f"{row[k]:.3g}" for k in shown if not math.isnan(row[k])}

    def validate(self) -> None:
        """Validate on the fixed held-out triplets, log and plot (rank 0); all ranks wait."""
        cfg = self.cfg
        self.validated_at = self.step
        if self.env.is_main:
            assert self.vset is not None and self.val_log is not None
            self.last_validation = validate(self.pair if cfg.train_retrieval else None,
                                            self.placement if cfg.train_placement else None,
                                            self.vset, cfg.margin, cfg.val_precision_k)
            self.val_log.append({"step": self.step, "elapsed_s": self.elapsed(), **self.last_validation})
            plot_columns(self.run_dir / VALIDATION_CSV, self.run_dir / VALIDATION_PNG, _validation_keys(cfg),
                         "validation (test split)")
            log.info("step %d validation: %s", self.step,
                     ", ".join(f"{k}={v:.4g}" for k, v in self.last_validation.items()))
            self.train_mode()  # validate() restores plain training mode, batch norm included
        if self.env.world > 1:
            dist.barrier()

    def checkpoint(self) -> None:
        if self.env.is_main:
            optimizers: dict[str, torch.optim.Optimizer] = {"retrieval": self.opt_r, "placement": self.opt_p}
            save_checkpoint(self.ckpt, make_state(self.cfg, self.step, self.elapsed(), self.pair,
                                                  self.placement, optimizers,
                                                  {"validation": self.last_validation,
                                                   "started_from": self.started_from}))

    def finish(self) -> TrainResult:
        """Validate if the last step was not, checkpoint, plot and write summary.json."""
        if self.validated_at != self.step:
            self.validate()
        self.checkpoint()
        final_losses = {k: _mean(list(v)) for k, v in self.recent.items() if v}
        result = TrainResult(run_dir=self.run_dir, step=self.step, elapsed_seconds=self.elapsed(),
                             final_losses=final_losses, validation=dict(self.last_validation))
        if self.env.is_main:
            plot_columns(self.run_dir / LOSSES_CSV, self.run_dir / LOSSES_PNG,
                         ["triplet_loss", "batch_triplet_accuracy", "placement_loss", "lr",
                          "seconds_per_step"],
                         "training losses (rank 0 batches)", log_y=False)
            write_json_atomic(self.run_dir / SUMMARY_FILE, {
                "step": self.step, "wall_minutes": result.elapsed_seconds / 60, "final_losses": final_losses,
                "validation": self.last_validation, "processes": self.env.world,
                "threads_per_process": self.threads,
            })
            log.info("finished at step %d after %.1f min: %s", self.step, result.elapsed_seconds / 60,
                     final_losses)
        if self.env.world > 1:
            dist.barrier()
        return result


def _validation_keys(cfg: TrainConfig) -> list[str]:
    keys: list[str] = []
    if cfg.train_retrieval:
        k = cfg.val_precision_k
        keys += ["triplet_accuracy", "triplet_loss", f"label_precision_at_{k}", f"category_precision_at_{k}",
                 "precision_queries", "mean_sigma", "live_modes"]
    if cfg.train_placement:
        keys += ["placement_mean_error", "placement_median_error"]
    return keys
