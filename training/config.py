"""Configuration of the networks and of a training run, with named presets.

Two dataclasses: ``ModelConfig`` (everything needed to rebuild the networks; stored in every
checkpoint and in the exported manifest) and ``TrainConfig`` (the run: data, budget, optimiser,
validation). The ``help`` metadata of each field is its comment and also the CLI's help text:
``training.cli`` generates one option per field.

Values are resolved in this order, later winning: dataclass defaults < preset < ``--config``
JSON file < explicit command-line options.
"""

from __future__ import annotations

import dataclasses
import json
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


def _help(text: str) -> dict[str, str]:
    return {"help": text}


@dataclass
class ModelConfig:
    """Layer sizes and output parametrisation of f (embedding), g (retrieval) and h (placement)."""

    # Shared per-point layers (Conv1d with kernel 1) of every PointNet encoder. Paper: 64,64,64,128,1024.
    point_layers: tuple[int, ...] = field(
        default=(64, 128, 256),
        metadata=_help("Per-point layer widths of every PointNet encoder (paper: 64,64,64,128,1024)."))
    # Fully connected layers after the max-pool. Paper: 512, 256.
    fc_layers: tuple[int, ...] = field(
        default=(256,), metadata=_help("FC layer widths after the max-pool (paper: 512,256)."))
    batch_norm: bool = field(default=True, metadata=_help("Batch norm after every hidden layer."))
    # Dropout after each FC layer of the encoders (PointNet uses 0.3 before its classifier).
    dropout: float = field(default=0.0, metadata=_help("Dropout probability after each encoder FC layer."))
    embedding_dim: int = field(default=50, metadata=_help("D, dimension of the part embedding (paper: 50)."))
    # Not in the paper (0 = off, the paper's unconstrained R^D): embeddings and mixture means on
    # a sphere of this radius. Equation 2 alone rewards means far outside the embedded parts (the
    # energy gap grows linearly with the distance), which makes the mixture rank parts by a
    # linear projection; on a sphere a mean can only point towards the parts it should retrieve.
    embedding_radius: float = field(default=0.0, metadata=_help("Radius of the embedding sphere (0 = R^D)."))
    n_modes: int = field(default=8, metadata=_help("K, Gaussians in the mixture predicted by g (paper: 8)."))
    # The paper caps sigma at 0.05 so the likelihood cannot be gamed by ever wider Gaussians.
    sigma_max: float = field(default=0.05, metadata=_help("Upper limit of every sigma (paper: 0.05)."))
    sigma_min: float = field(default=1e-3, metadata=_help("Lower limit of every sigma (keeps log finite)."))
    # "sigmoid": sigma = min + (max - min) * sigmoid(raw), smooth everywhere.
    # "exp_clip": sigma = clamp(exp(raw + sigma_log_bias), min, max), the paper's exponential;
    # its gradient vanishes at the clip, so the bias must start well below log(sigma_max).
    sigma_param: str = field(default="sigmoid", metadata=_help("Sigma parametrisation: sigmoid | exp_clip."))
    sigma_log_bias: float = field(
        default=-4.0, metadata=_help("Initial bias of raw log-sigma for exp_clip (exp(-4) = 0.018)."))
    # Placement network h: two encoders (query X, part Y), then an MLP on their concatenation.
    placement_point_layers: tuple[int, ...] = field(
        default=(64, 128, 256), metadata=_help("Per-point layer widths of h's two encoders."))
    placement_fc_layers: tuple[int, ...] = field(
        default=(256,), metadata=_help("FC widths of h's encoders; the last is the feature size Fq = Fp."))
    placement_head_layers: tuple[int, ...] = field(
        default=(256, 128), metadata=_help("Hidden widths of h's head MLP (then a linear layer to xyz)."))
    # Not in the paper (0 = off): a linear head on g's PointNet feature that names the query's
    # category, trained from the collection's category folders (how users organise collections;
    # no part labels). The service infers the category of a request that names none from it.
    n_categories: int = field(default=0, metadata=_help("Categories of g's category head (0 = no head)."))
    # Not in the paper: h also predicts the per-axis log scale that fits a retrieved part to the
    # query (trained on positives rescaled at random, see TrainConfig.scale_augment).
    predict_scale: bool = field(default=False, metadata=_help("h predicts a per-axis log scale too."))

    def validate(self) -> None:
        for name in ("point_layers", "fc_layers", "placement_point_layers", "placement_fc_layers"):
            value = getattr(self, name)
            if not value or any(int(v) <= 0 for v in value):
                raise ValueError(f"model config: {name} must be a non-empty list of positive ints, "
                                 f"got {value!r}")
        if any(int(v) <= 0 for v in self.placement_head_layers):
            raise ValueError("model config: placement_head_layers must be positive, "
                             f"got {self.placement_head_layers!r}")
        if self.embedding_radius < 0:
            raise ValueError(f"model config: embedding_radius must be >= 0, got {self.embedding_radius}")
        if self.embedding_dim <= 0 or self.n_modes <= 0:
            raise ValueError("model config: embedding_dim and n_modes must be positive")
        if not 0.0 < self.sigma_min < self.sigma_max:
            raise ValueError(f"model config: need 0 < sigma_min < sigma_max, "
                             f"got {self.sigma_min}, {self.sigma_max}")
        if self.sigma_param not in ("sigmoid", "exp_clip"):
            raise ValueError("model config: sigma_param must be 'sigmoid' or 'exp_clip', "
                             f"got {self.sigma_param!r}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"model config: dropout must be in [0, 1), got {self.dropout}")
        if self.n_categories < 0:
            raise ValueError(f"model config: n_categories must be >= 0, got {self.n_categories}")



def check_negative_shares(query: float, lookalike: float, shape: float, owner: str) -> None:
    """The one rule on the hard negatives' shares (the rest of the negatives are random parts):
    each share >= 0 and together at most 1. ``owner`` starts the error (who was given them)."""
    shares = (query, lookalike, shape)
    if min(shares) < 0 or sum(shares) > 1:
        raise ValueError(f"{owner}: query_negative_fraction, lookalike_negative_fraction and "
                         f"shape_negative_fraction must be >= 0 and sum to at most 1, got {shares}")


@dataclass
class TrainConfig:
    """One training run: data, budget, optimiser, validation and logging."""

    data: str = field(default="data/processed", metadata=_help("Processed dataset folder."))
    # Also --run-dir: torchrun's own argument parser takes --run as an abbreviation of its --run-path.
    run: str = field(default="runs/default",
                     metadata={**_help("Run folder: checkpoints, split, logs, plots (alias --run-dir)."),
                               "aliases": ("--run-dir",)})
    seed: int = field(default=0, metadata=_help("Seed of the split, the initial weights and the sampling."))
    test_fraction: float = field(default=0.2, metadata=_help("Fraction of each category's shapes held out."))
    # Budget: training stops at whichever comes first. `minutes` counts this invocation only,
    # so a resumed run gets a fresh budget; `steps` is the total over all invocations.
    steps: int = field(default=20000, metadata=_help("Total optimisation steps (over all resumes)."))
    minutes: float = field(default=0.0, metadata=_help(
        "Wall-clock budget of this invocation; 0 = none. The learning-rate schedule follows it "
        "(the model then depends on the host's speed); --max-minutes is the guard that does not."))
    # A guard, not a budget: the run stops if this invocation passes it, but the learning rate
    # follows the steps alone, so the same seed gives the same model on a faster or slower host.
    max_minutes: float = field(default=0.0,
                               metadata=_help("Stop (as a guard) after this many minutes; LR ignores it."))
    batch_size: int = field(default=32, metadata=_help("Triplets per step and per process (paper: 32)."))
    # The paper samples 1000 points; max-pooling makes the nets accept any N, and 512 halves the cost.
    n_points: int = field(default=512, metadata=_help("Points per assembly or part during training."))
    lr: float = field(default=1e-3, metadata=_help("Initial Adam learning rate (paper: 1e-3)."))
    lr_decay: float = field(default=0.8, metadata=_help("LR factor per decay period (paper: 0.8)."))
    lr_decay_steps: int = field(default=50000, metadata=_help("Steps per decay period (paper: 50000)."))
    lr_staircase: bool = field(default=False, metadata=_help("Decay in steps instead of continuously."))
    # "exp": the paper's lr * decay^(step / decay_steps). "cosine": from lr down to
    # lr * lr_final_fraction along a half cosine over the run's progress, the larger of
    # step / steps and (with --minutes) the elapsed share of this invocation's time budget, so
    # a time-budgeted run ends at a low rate whatever the machine's speed.
    lr_schedule: str = field(default="exp", metadata=_help("Learning-rate schedule: exp | cosine."))
    lr_final_fraction: float = field(default=0.02, metadata=_help("cosine: final lr as a fraction of lr."))
    margin: float = field(default=10.0, metadata=_help("Triplet margin m of Equation 2 (paper: 10)."))
    # Not in the paper: Equation 2 only compares E(X,Y) with E(X,Z), and its gap grows with the
    # distance of a mean from the parts, so g learns means far outside the embedded parts (2.5
    # away on a catalog of spread 1, measured): the mixture then ranks by a linear projection and
    # every query retrieves the same extreme parts. A weight on E(X,Y) itself pulls the modes
    # onto the positives (label precision@5 after 500 steps: 0.30 without, 0.37 at 0.01, 0.44 at
    # 0.1), but it also moves the mixture weight onto one central mode. The relaxed
    # winner-takes-all pull (losses.relaxed_wta_pull) pulls only the nearest mode and ignores
    # the weights.
    nll_weight: float = field(default=0.0,
                              metadata=_help("Weight of the positive's NLL E(X,Y) added to Eq. 2."))
    wta_weight: float = field(default=0.0,
                              metadata=_help("Weight of the relaxed winner-takes-all pull of the modes."))
    wta_epsilon: float = field(default=0.05,
                               metadata=_help("Share of that pull spread over the other modes."))
    # Not in the paper: plain WTA lets the mode nearest to everything win every positive; the
    # others stop moving and their weights die (live modes 2.88 at step 1,000, 1.23 at 8,000,
    # measured on the v3 preset). The evolving WTA pulls the K nearest modes at first and
    # narrows to one over this share of the steps (losses.wta_winners).
    wta_anneal: float = field(default=0.0,
                              metadata=_help("Share of the steps in which the WTA pull narrows K to 1."))
    # Not in the paper: the weights learn how often each mode wins a positive (cross-entropy of
    # log phi against the winner), so a weight says what share of the complements its mode
    # explains instead of which mode Equation 2 prefers for this triplet.
    wta_weight_ce: float = field(default=0.0,
                                 metadata=_help("Weight of g's weights' cross-entropy on the WTA winner."))
    # Not in the paper: the pull's Gaussian with this sigma instead of g's, so the pull is a plain
    # squared distance of the winning mean: a mode that cannot reach its positives cannot widen
    # its sigma to lower the pull (the tenfold pull took the sigmas from 0.05 to 0.11).
    wta_sigma: float = field(default=0.0,
                             metadata=_help("Sigma of the WTA pull's Gaussians (0 = g's own sigmas)."))
    # The pulls fit g's mixture to the embedded positives; letting their gradient reach f as
    # well shrinks the whole embedding towards the modes (measured: catalog spread below sigma).
    pull_moves_embedding: bool = field(default=False,
                                       metadata=_help("Let the NLL / winner-takes-all pulls train f too."))
    # Not in the paper: the share of triplets whose negative Z is one of the query's own
    # components (see data.sampling.TripletSampler). Validation keeps the paper's negatives.
    query_negative_fraction: float = field(
        default=0.0, metadata=_help("Share of negatives drawn from the query's own components."))
    lookalike_negative_fraction: float = field(
        default=0.0, metadata=_help("Share of negatives that look like a query component (other shapes)."))
    # Not in the paper: the share of negatives that do the positive's job in another shape of the
    # category but differ from it in shape (data.sampling.shape_lookalikes): which style of the
    # missing part this assembly wants, not only which part is missing.
    shape_negative_fraction: float = field(
        default=0.0,
        metadata=_help("Share of negatives that do the positive's job in another shape but differ in shape."))
    # Equation 2's margin for those: the full margin asks the part of another style to rank below
    # parts of other jobs too, where a smaller one only asks it to rank below the right style.
    shape_negative_margin: float = field(
        default=-1.0, metadata=_help("Margin of Equation 2 for shape negatives (-1 = --margin)."))
    # Not in the paper: Y drawn among X's adjacent components with probability proportional to
    # its box diagonal to this power (0: uniformly, as the paper); see data.sampling.TripletSampler.
    positive_size_power: float = field(
        default=0.0,
        metadata=_help("Draw Y with probability ~ (box diagonal)^p among X's neighbours (0 = uniform)."))
    # Not in the paper: the share of queries drawn as "the shape minus a connected group" (X may
    # then be disconnected, as in the benchmark's all-but-one-part queries).
    removal_query_fraction: float = field(
        default=0.0, metadata=_help("Share of queries that are a shape minus a connected group of parts."))
    # Not in the paper: each query is also scored against up to this many of its valid
    # complements (the components of its shape that it lacks; the first is the paper's adjacent
    # positive Y). With one positive per query the mixture learns one mode: a seat alone is
    # trained towards a leg, a back or an arm by turns, and the winner of each pull takes all.
    # Fitting the whole set at once (set_nll_weight) is an MDN trained on every answer of X.
    positives: int = field(default=1, metadata=_help("Valid complements drawn per query (1 = the paper)."))
    set_nll_weight: float = field(
        default=0.0, metadata=_help("Weight of the mean mixture NLL of the query's complement set."))
    # Not in the paper: with positives > 1, the WTA pull sees only Y and the weights' fit
    # (wta_weight_ce) only the other positives, so a size-drawn Y (positive_size_power) moves the
    # modes towards a kind's main piece while the weights keep the kinds' shares of uniform draws.
    split_positive_fits: bool = field(default=False, metadata=_help(
        "Pull the modes onto Y alone and fit the weights to the other positives (needs positives > 1)."))
    # Not in the paper: a query's complements matched one-to-one to modes (Hungarian, per-mode
    # NLL as cost; losses.matched_modes); each matched mode pulled onto its complement, and the
    # weights fitted to the shares of the matching. Measured: the set NLL with the relaxed WTA
    # pull still gave 1.03 modes of weight >= 0.05 after 1,000 steps (the nearest mode wins
    # every complement, the others get no responsibility and die).
    match_weight: float = field(default=0.0, metadata=_help("Weight of the matched modes' pull."))
    match_weight_ce: float = field(
        default=0.0, metadata=_help("Weight of the cross-entropy of g's weights against the matching."))
    # Not in the paper: cross-entropy of g's category head against the shape's category folder.
    category_weight: float = field(default=0.0, metadata=_help("Weight of g's category loss."))
    # Not in the paper: h's positive part is rescaled per axis by exp(U(-a, a)) and h learns the
    # log scale that undoes it (a retrieved leg from a taller chair must be shortened).
    scale_augment: float = field(default=0.0, metadata=_help("a of the positive's random log rescale for h."))
    scale_weight: float = field(default=0.0, metadata=_help("Weight of h's log-scale regression."))
    # Not in the paper: for this share of h's examples the part is a look-alike of the positive
    # from another shape of the category (data.sampling.TripletSampler.substitute), to be placed
    # where the positive was and fitted to its size: what the service asks of h.
    substitute_fraction: float = field(
        default=0.0, metadata=_help("Share of h's examples whose part is a look-alike of the positive."))
    # Not in the paper: queries mixed from several shapes' parts (data.sampling.TripletSampler):
    # /assemble and modellers build assemblies from catalog parts of many shapes, which g and h
    # otherwise only ever see whole. Tried as a third stage at 0.5 (docs/training.md): chairs got
    # their backs more often, rifles lost bodies and retrieval lost 0.013 mAP: off.
    mixed_query_fraction: float = field(
        default=0.0, metadata=_help("Share of queries whose components are swapped half for look-alikes."))
    # Not in the paper: what real collections bring (docs/training.md): anisotropic rescaling of
    # the whole shape, small rotations about the up axis, frames off centre and scale, point
    # noise, missing surface and density changes, in the ranges of data.sampling.Augmentation.
    augment: float = field(default=0.0, metadata=_help("Share of triplets augmented (0 = off)."))
    # How wide: 1 is data.sampling.Augmentation's ranges; 2 doubles the per-axis and whole-shape
    # rescales, the yaw, the frame offset and the noise (what the benchmark's robustness table
    # perturbs by; docs/training.md, "Wider augmentation").
    augment_strength: float = field(default=1.0, metadata=_help(
        "Multiplier of the augmentation's rescale, yaw, offset and noise ranges (1 = as listed)."))
    # Whether the positive and negatives take the query's augmentation too (as shipped). Off: f and
    # g see them as the catalog holds them, so g learns to point at the catalog's parts from a
    # perturbed query rather than at perturbed parts no catalog holds (docs/training.md, "Wider
    # augmentation"); h's part and translation target are augmented either way.
    augment_parts: bool = field(default=True, metadata=_help(
        "Augment the positive and negatives with the query (off: as the catalog holds them)."))
    # Not in the paper: the shape's layout warped per axis (data.sampling.layout_warp: parts move
    # and rescale with a random monotone map, contacts kept), so h reads where the query leaves
    # room instead of where each kind of part sat in the training styles (docs/training.md).
    layout_warp: float = field(default=0.0,
                               metadata=_help("Share of triplets whose layout is warped (0 = off)."))
    # Measurement only: "styles" holds out one style per category (leave-one-style-out
    # benchmark); styles are never read by the training itself.
    split: str = field(default="random", metadata=_help("Test split: random | styles (one style held out)."))
    # Which shapes (or, with split styles, which style per category) are held out depends on this
    # seed alone, so the same held-out draw can be trained with other seeds and a figure judged
    # over several draws (docs/training.md, "How much the figure owes to the draw").
    split_seed: int = field(default=-1, metadata=_help("Seed of the train/test split (-1 = --seed)."))
    placement_lr: float = field(default=1e-3, metadata=_help("Initial Adam learning rate of h."))
    # Fine-tuning: the run starts from an exported model's networks (read back from its graphs by
    # training.from_onnx) instead of random weights. Batch norm is frozen (eval mode) throughout:
    # the export folded the per-point batch norms into their convolutions, so batch statistics
    # would change the function the run starts from.
    init_from: str = field(default="", metadata=_help(
        "Artifact folder whose f, g and h start the run (fine-tuning, batch norm frozen); '' = random."))
    train_retrieval: bool = field(default=True, metadata=_help("Train f and g."))
    train_placement: bool = field(default=True, metadata=_help("Train h (same batches, own optimiser)."))
    # Not in the paper: a stage that trains g alone on a fixed f. Equation 2 and the pulls are
    # then a fit of g's mixture to the embedded parts as they are: a stronger pull cannot be met
    # by f spreading the embedding instead (docs/training.md, the tenfold pull).
    train_embedding: bool = field(default=True, metadata=_help(
        "With train_retrieval: train f too (off = g alone on a fixed f, in eval mode)."))
    val_every: int = field(default=500, metadata=_help("Steps between validations (0 = only at the end)."))
    val_triplets: int = field(default=512, metadata=_help("Fixed held-out triplets used by validation."))
    val_precision_k: int = field(default=5, metadata=_help("k of label precision@k."))
    ckpt_every: int = field(default=500, metadata=_help("Steps between checkpoints (one more at the end)."))
    log_every: int = field(default=25, metadata=_help("Steps between rows of the loss log."))
    num_workers: int = field(default=1, metadata=_help("DataLoader workers sampling batches (0 = inline)."))
    threads: int = field(default=0, metadata=_help("Torch threads per process (0 = cores / processes)."))
    model: ModelConfig = field(default_factory=ModelConfig)

    def validate(self) -> None:
        self.model.validate()
        positive = ("steps", "batch_size", "n_points", "lr_decay_steps", "val_triplets", "val_precision_k",
                    "ckpt_every", "log_every")
        for name in positive:
            if getattr(self, name) <= 0:
                raise ValueError(f"train config: {name} must be positive, got {getattr(self, name)}")
        for name in ("minutes", "max_minutes", "val_every", "num_workers", "threads", "set_nll_weight",
                     "category_weight", "scale_augment", "scale_weight", "augment", "match_weight",
                     "match_weight_ce", "wta_weight_ce", "wta_sigma", "positive_size_power"):
            if getattr(self, name) < 0:
                raise ValueError(f"train config: {name} must be >= 0, got {getattr(self, name)}")
        if not 0.0 < self.test_fraction < 1.0:
            raise ValueError(f"train config: test_fraction must be in (0, 1), got {self.test_fraction}")
        if self.lr_schedule not in ("exp", "cosine") or not 0 <= self.lr_final_fraction <= 1:
            raise ValueError(f"train config: lr_schedule must be exp or cosine (got {self.lr_schedule!r}) "
                             f"and lr_final_fraction in [0, 1] (got {self.lr_final_fraction})")
        if self.lr <= 0 or self.placement_lr <= 0 or not 0 < self.lr_decay <= 1:
            raise ValueError("train config: learning rates must be > 0 and lr_decay in (0, 1]")
        if self.nll_weight < 0 or self.wta_weight < 0 or not 0 <= self.wta_epsilon < 1:
            raise ValueError("train config: nll_weight and wta_weight must be >= 0 and wta_epsilon in [0, 1)")
        if not 0.0 <= self.wta_anneal <= 1.0:
            raise ValueError(f"train config: wta_anneal must be in [0, 1], got {self.wta_anneal}")
        check_negative_shares(self.query_negative_fraction, self.lookalike_negative_fraction,
                              self.shape_negative_fraction, "train config")
        if self.shape_negative_margin < 0 and self.shape_negative_margin != -1:
            raise ValueError("train config: shape_negative_margin must be >= 0 or -1 (the margin), "
                             f"got {self.shape_negative_margin}")
        if not 0.0 <= self.substitute_fraction <= 1.0:
            raise ValueError("train config: substitute_fraction must be in [0, 1], "
                             f"got {self.substitute_fraction}")
        if not 0.0 <= self.layout_warp <= 1.0:
            raise ValueError(f"train config: layout_warp must be in [0, 1], got {self.layout_warp}")
        if not 0.0 <= self.mixed_query_fraction <= 1.0:
            raise ValueError("train config: mixed_query_fraction must be in [0, 1], "
                             f"got {self.mixed_query_fraction}")
        if not 0.0 <= self.removal_query_fraction <= 1.0:
            raise ValueError("train config: removal_query_fraction must be in [0, 1], "
                             f"got {self.removal_query_fraction}")
        if not 0.0 <= self.augment <= 1.0:
            raise ValueError(f"train config: augment must be in [0, 1], got {self.augment}")
        if not 0.0 < self.augment_strength <= 4.0:
            raise ValueError(f"train config: augment_strength must be in (0, 4], got {self.augment_strength}")
        if self.split_seed < -1:
            raise ValueError(f"train config: split_seed must be >= 0, or -1 for the seed, got "
                             f"{self.split_seed}")
        if self.positives < 1 or self.split not in ("random", "styles"):
            raise ValueError(f"train config: positives must be >= 1 (got {self.positives}) and split "
                             f"random or styles (got {self.split!r})")
        if self.split_positive_fits and self.positives < 2:
            raise ValueError("train config: split_positive_fits needs positives >= 2 (the weights' fit "
                             f"sees the positives after Y), got {self.positives}")
        if not (self.train_retrieval or self.train_placement):
            raise ValueError("train config: nothing to train "
                             "(train_retrieval and train_placement are both off)")


# Named starting points. "shipped" is what the lead trains in <= 60 minutes on a 2-core CPU.
PRESETS: dict[str, dict[str, Any]] = {
    # A few seconds per hundred steps: tests and smoke runs.
    "tiny": {
        "batch_size": 8, "n_points": 128, "val_every": 0, "val_triplets": 32, "ckpt_every": 1000,
        "log_every": 1, "num_workers": 0, "threads": 1,
        "model": {"point_layers": (16, 32), "fc_layers": (32,), "embedding_dim": 8, "n_modes": 3,
                  "placement_point_layers": (16, 32), "placement_fc_layers": (32,),
                  "placement_head_layers": (32,)},
    },
    # Slim PointNets at N = 512: about 0.3 s per joint f+g+h step on 2 cores.
    "shipped": {
        "steps": 100000, "n_points": 512, "val_every": 1000, "ckpt_every": 500,
        # A time-budgeted run that ends at a low learning rate.
        "lr_schedule": "cosine",
        # The NLL pull (0.1 in the first shipped model) moved ~99% of the mixture weight onto one
        # mode, which pointed at a part the query already had in 60% of all-but-one queries; the
        # winner-takes-all pull keeps the modes apart (largest weight 0.26 on average, measured).
        "nll_weight": 0.0, "wta_weight": 0.1,
        # Label-free hard negatives and disconnected all-but-some queries (data.sampling).
        "query_negative_fraction": 0.25, "lookalike_negative_fraction": 0.5, "removal_query_fraction": 0.3,
        "model": {},
    },
    # Model v3 (docs/training.md): the shipped preset plus a category head, size fitting and
    # augmentations; a fixed number of steps (same seed, same model on any host) with a time
    # guard only. The pull is the shipped preset's winner-takes-all on one positive: the
    # matched-mode pull on three positives (the first v3 candidate) kept more modes alive but
    # retrieved worse (validation label precision@5 0.477 against 0.557, benchmark functional
    # mAP@5 0.627 against 0.694, measured one change at a time). 8,000 steps, not 4,000: 0.752
    # against 0.694 (and 0.727 for the model before v3); N = 512 in the same time: 0.651.
    # The mixture (model v3 as shipped now): sigmas up to 0.15 instead of the paper's 0.05, the
    # evolving winner-takes-all pull (K modes narrowing to 1 over the first half) and weights
    # fitted to the share of wins. Benchmark: functional mAP@5 0.793 against 0.752, 4.49 modes of
    # weight >= 0.05 against 1.26; the same pull with the 0.05 cap collapsed to 1.32 modes at a
    # validation precision of 0.24 by step 5,000 (against 0.59 with the 0.15 cap).
    # 24,000 steps, not 8,000 (shipped 2026-12-03, trained on two threads; since 2026-12-04 the
    # first stage of the shipped model, see v3-finetune): functional mAP@5 0.895 against 0.788,
    # and 0.881 at 16,000. The guard (480 min) only stops a run far slower than the 104 min it
    # took on a 2-core AVX-512 host.
    "v3": {
        "steps": 24000, "max_minutes": 480, "n_points": 256, "val_every": 1000, "ckpt_every": 200,
        "num_workers": 0,
        "lr_schedule": "cosine", "nll_weight": 0.0,
        "wta_weight": 0.1, "wta_anneal": 0.5, "wta_weight_ce": 1.0,
        "query_negative_fraction": 0.25, "lookalike_negative_fraction": 0.5, "removal_query_fraction": 0.3,
        "positives": 1, "set_nll_weight": 0.0, "match_weight": 0.0, "match_weight_ce": 0.0,
        "category_weight": 1.0,
        "scale_augment": 0.4, "scale_weight": 0.3, "augment": 0.5,
        "model": {"predict_scale": True, "sigma_max": 0.15},
    },
    # The paper's sizes (about 5x slower per step on CPU).
    "paper": {
        "n_points": 1000,
        "model": {"point_layers": (64, 64, 64, 128, 1024), "fc_layers": (512, 256), "dropout": 0.3,
                  "placement_point_layers": (64, 64, 64, 128, 1024), "placement_fc_layers": (512, 256),
                  "placement_head_layers": (256, 128)},
    },
}

# The second stage of the shipped model (docs/training.md, "A warm restart"): the v3 run's export
# fine-tuned (train --init-from) for 8,000 more steps, a cosine from 0.3 of v3's learning rate,
# the plain winner-takes-all pull (the modes are already spread: a second evolving pull would
# pull several modes onto each positive again). Benchmark: functional mAP@5 0.903 against 0.895
# for the v3 run alone, Hausdorff 0.168 against 0.175, placement 0.033 against 0.040; about 20
# minutes on two threads of a 2-core AVX-512 host.
PRESETS["v3-finetune"] = {**PRESETS["v3"], "steps": 8000, "max_minutes": 160, "lr": 3e-4,
                          "placement_lr": 3e-4, "wta_anneal": 0.0}

# The third stage of the shipped model (docs/training.md, "h on 512 points"): h alone, from the
# second stage's export, for 6,000 steps on 512 points per cloud (f and g stay as they are and
# keep 256 when serving: export with --n-points 256 --placement-points 512). Validation placement
# error 0.0275 against 0.0319 (and 0.0306 for the same stage on 256 points); 21 min on two
# threads of a 2-core AVX-512 host beside other work.
PRESETS["v3-h512"] = {**PRESETS["v3-finetune"], "steps": 6000, "n_points": 512, "train_retrieval": False}


def _coerce(value: Any, annotation: Any, where: str) -> Any:
    """Convert a JSON or CLI value to a field's annotated type, or raise naming the field."""
    origin = typing.get_origin(annotation)
    if origin is tuple:
        if isinstance(value, str):
            value = [v for v in value.replace(" ", "").split(",") if v]
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{where}: expected a list of ints, got {value!r}")
        try:
            return tuple(int(v) for v in value)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{where}: expected a list of ints, got {value!r}") from exc
    if annotation is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.lower() in ("true", "false", "1", "0", "yes", "no"):
            return value.lower() in ("true", "1", "yes")
        raise ValueError(f"{where}: expected true or false, got {value!r}")
    if annotation in (int, float, str):
        if annotation is int and isinstance(value, float) and not value.is_integer():
            raise ValueError(f"{where}: expected an int, got {value!r}")
        if annotation in (int, float) and isinstance(value, bool):
            raise ValueError(f"{where}: expected a number, got {value!r}")
        try:
            return annotation(value)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{where}: expected {annotation.__name__}, got {value!r}") from exc
    raise TypeError(f"{where}: unsupported field type {annotation!r}")


def field_types(cls: type) -> dict[str, Any]:
    """Resolved annotations of a config dataclass (the module uses postponed annotations)."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in dataclasses.fields(cls)}


def apply_overrides(cfg: TrainConfig, overrides: dict[str, Any], source: str = "overrides") -> TrainConfig:
    """Return a copy of ``cfg`` with ``overrides`` applied.

    ``overrides`` may be nested (``{"model": {...}}``, as in a JSON file) or flat: a key that is
    not a ``TrainConfig`` field is looked up among the ``ModelConfig`` fields. Unknown keys raise
    a ``ValueError`` naming the key and ``source``.
    """
    train_types = field_types(TrainConfig)
    model_types = field_types(ModelConfig)
    train_changes: dict[str, Any] = {}
    model_changes: dict[str, Any] = {}
    for key, value in overrides.items():
        if key == "model":
            if not isinstance(value, dict):
                raise ValueError(f"{source}: 'model' must be an object, got {value!r}")
            for mkey, mvalue in value.items():
                if mkey not in model_types:
                    raise ValueError(f"{source}: unknown model option {mkey!r}")
                model_changes[mkey] = _coerce(mvalue, model_types[mkey], f"{source}: model.{mkey}")
        elif key in train_types:
            train_changes[key] = _coerce(value, train_types[key], f"{source}: {key}")
        elif key in model_types:
            model_changes[key] = _coerce(value, model_types[key], f"{source}: {key}")
        else:
            raise ValueError(f"{source}: unknown option {key!r}")
    model = dataclasses.replace(cfg.model, **model_changes)
    return dataclasses.replace(cfg, **train_changes, model=model)


def resolve_config(preset: str | None = None, config_file: Path | None = None,
                   overrides: dict[str, Any] | None = None) -> TrainConfig:
    """Build a validated ``TrainConfig``: defaults, then preset, then JSON file, then overrides."""
    cfg = TrainConfig()
    if preset is not None:
        if preset not in PRESETS:
            raise ValueError(f"unknown preset {preset!r}; known presets: {', '.join(sorted(PRESETS))}")
        cfg = apply_overrides(cfg, PRESETS[preset], source=f"preset {preset!r}")
    if config_file is not None:
        path = Path(config_file)
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"cannot read config file {path}: {exc}") from exc
        if not isinstance(data, dict):
            raise ValueError(f"config file {path}: expected a JSON object")
        cfg = apply_overrides(cfg, data, source=str(path))
    if overrides:
        cfg = apply_overrides(cfg, overrides, source="command line")
    cfg.validate()
    return cfg


def config_to_dict(cfg: TrainConfig | ModelConfig) -> dict[str, Any]:
    """JSON-ready dict (tuples become lists)."""
    return json.loads(json.dumps(dataclasses.asdict(cfg)))


def config_from_dict(data: dict[str, Any]) -> TrainConfig:
    """Inverse of ``config_to_dict`` for a ``TrainConfig`` (as stored in checkpoints)."""
    cfg = apply_overrides(TrainConfig(), data, source="stored config")
    cfg.validate()
    return cfg


def known_options(data: dict[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """A stored config without the options this code does not know, and their names.

    Why: a run's stored config names every option of the code that trained it, so a run trained
    by another version (a branch with one more option) would not load here at all. Reading its
    weights (export, evaluation) needs only the options this code knows; whether the unknown
    ones changed the networks shows when the weights are loaded (``checkpoint.load_trained``).

    Shapes:
        data: a ``config_to_dict`` dict -> (the same without unknown keys, ["name" | "model.name"]).
    """
    train_names, model_names = field_types(TrainConfig), field_types(ModelConfig)  # as apply_overrides
    known = {k: v for k, v in data.items() if k in train_names}
    dropped = sorted(k for k in data if k not in train_names)
    model = data.get("model")
    if isinstance(model, dict):
        known["model"] = {k: v for k, v in model.items() if k in model_names}
        dropped += sorted(f"model.{k}" for k in model if k not in model_names)
    return known, dropped


def model_config_from_dict(data: dict[str, Any]) -> ModelConfig:
    """Rebuild a ``ModelConfig`` from its dict (as stored in manifests and checkpoints)."""
    return apply_overrides(TrainConfig(), {"model": data}, source="stored model config").model


@dataclass(frozen=True)
class HeadFitSettings:
    """How g's category head is refitted on outside collections (training.category_head)."""

    queries: int = 102400         # partial assemblies drawn in all (about 90 s of g's encoder)
    outside_share: float = 0.1    # of them from the outside collections, split evenly among them
    epochs: int = 30
    batch_size: int = 256
    lr: float = 1e-3
    n_points: int = 256           # points per query, as f and g are served
    seed: int = 0
