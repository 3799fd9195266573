"""The three networks of the paper: embedding f, retrieval g (a mixture density network) and
placement h, all on PointNet encoders without spatial transformers (Section 5, Figure 4).

Every module takes points as ``(B, N, 3)`` and transposes inside, so the exported ONNX graphs have
the service's input layout; per-point layers are ``Conv1d`` with kernel 1 (3-4x faster in
onnxruntime than ``Linear`` over ``(B, N, C)``). Max-pooling over points makes every network
accept any N: training may use fewer points than serving.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from training.config import ModelConfig


class PointNetEncoder(nn.Module):
    """PointNet feature extractor: shared per-point MLP, max-pool over points, FC layers.

    Args:
        point_layers: widths of the shared per-point layers (paper: 64, 64, 64, 128, 1024).
        fc_layers: widths of the fully connected layers after the pool (paper: 512, 256).
        batch_norm: batch norm after every layer (before the ReLU).
        dropout: dropout probability after each FC layer.

    Shapes:
        points (B, N, 3) -> features (B, fc_layers[-1]).
    """

    def __init__(self, point_layers: tuple[int, ...], fc_layers: tuple[int, ...], batch_norm: bool = True,
                 dropout: float = 0.0):
        super().__init__()
        convs: list[nn.Module] = []
        width = 3
        for out in point_layers:
            convs.append(nn.Conv1d(width, out, kernel_size=1, bias=not batch_norm))
            if batch_norm:
                convs.append(nn.BatchNorm1d(out))
            convs.append(nn.ReLU())
            width = out
        self.point_mlp = nn.Sequential(*convs)
        fcs: list[nn.Module] = []
        for out in fc_layers:
            fcs.append(nn.Linear(width, out, bias=not batch_norm))
            if batch_norm:
                fcs.append(nn.BatchNorm1d(out))
            fcs.append(nn.ReLU())
            if dropout > 0:
                fcs.append(nn.Dropout(dropout))
            width = out
        self.fc = nn.Sequential(*fcs)
        self.out_dim = width

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        x = points.transpose(1, 2)          # (B, 3, N)
        x = self.point_mlp(x)               # (B, C, N)
        x = torch.amax(x, dim=2)            # (B, C): symmetric in the points
        return self.fc(x)                   # (B, F)


def to_sphere(x: torch.Tensor, radius: float) -> torch.Tensor:
    """Scale vectors along the last axis to length ``radius`` (identity when radius is 0)."""
    if radius <= 0:
        return x
    return x * (radius / torch.sqrt((x * x).sum(dim=-1, keepdim=True) + 1e-12))


class EmbeddingNet(nn.Module):
    """f: a part's points to its coordinates in the D-dimensional embedding space.

    Shapes:
        points (B, N, 3), centred at the part's bounding-box centre -> embedding (B, D).
    """

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.encoder = PointNetEncoder(cfg.point_layers, cfg.fc_layers, cfg.batch_norm, cfg.dropout)
        self.out = nn.Linear(self.encoder.out_dim, cfg.embedding_dim)
        self.radius = cfg.embedding_radius

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return to_sphere(self.out(self.encoder(points)), self.radius)


class RetrievalNet(nn.Module):
    """g: a partial assembly's points to a mixture of K diagonal Gaussians over the embedding.

    One linear layer per mixture parameter on the PointNet feature, as in the paper: softmax for
    the weights, linear for the means, and a positive, bounded activation for the sigmas. The
    paper's ``exp`` with a clip at 0.05 gives zero gradient whenever the clip is active, and with
    a raw value near 0 at initialisation every sigma starts (and stays) clipped; the default
    ``sigmoid`` parametrisation ``sigma_min + (sigma_max - sigma_min) * sigmoid(raw)`` keeps a
    gradient everywhere. ``exp_clip`` keeps the paper's form with a low initial bias.

    Shapes:
        points (B, N, 3) in the shape frame -> weights (B, K), means (B, K, D), sigmas (B, K, D).
    """

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.k, self.d = cfg.n_modes, cfg.embedding_dim
        self.sigma_param = cfg.sigma_param
        self.sigma_min, self.sigma_max = cfg.sigma_min, cfg.sigma_max
        self.radius = cfg.embedding_radius
        self.encoder = PointNetEncoder(cfg.point_layers, cfg.fc_layers, cfg.batch_norm, cfg.dropout)
        width = self.encoder.out_dim
        self.weight_head = nn.Linear(width, self.k)
        self.mean_head = nn.Linear(width, self.k * self.d)
        self.sigma_head = nn.Linear(width, self.k * self.d)
        if self.sigma_param == "exp_clip":
            nn.init.constant_(self.sigma_head.bias, cfg.sigma_log_bias)
        # The category head reads the same feature as the mixture: what the query is decides
        # what complements it, so the two share the encoder.
        self.category_head = nn.Linear(width, cfg.n_categories) if cfg.n_categories > 0 else None

    def forward_log(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Mixture parameters in the form the loss needs: log weights, means and log sigmas.

        Shapes:
            points (B, N, 3) -> log_weights (B, K), means (B, K, D), log_sigmas (B, K, D).
        """
        return self._mixture(self.encoder(points))

    def forward_train(self, points: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """``forward_log`` plus the category logits (None without a category head).

        Shapes:
            points (B, N, 3) -> as ``forward_log``, and category_logits (B, C).
        """
        feat = self.encoder(points)
        logits = self.category_head(feat) if self.category_head is not None else None
        return (*self._mixture(feat), logits)

    def _mixture(self, feat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        log_weights = F.log_softmax(self.weight_head(feat), dim=1)    # (B, K)
        means = to_sphere(self.mean_head(feat).view(-1, self.k, self.d), self.radius)  # (B, K, D)
        raw = self.sigma_head(feat).view(-1, self.k, self.d)          # (B, K, D)
        if self.sigma_param == "sigmoid":
            sigmas = self.sigma_min + (self.sigma_max - self.sigma_min) * torch.sigmoid(raw)
        else:
            sigmas = torch.clamp(torch.exp(raw), self.sigma_min, self.sigma_max)
        return log_weights, means, torch.log(sigmas)

    def forward(self, points: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The exported graph: weights, means, sigmas (and category probabilities with the head).

        Shapes:
            points (B, N, 3) -> weights (B, K), means (B, K, D), sigmas (B, K, D)[, category_probs (B, C)].
        """
        log_weights, means, log_sigmas, logits = self.forward_train(points)
        out = (torch.exp(log_weights), means, torch.exp(log_sigmas))
        return out if logits is None else (*out, torch.softmax(logits, dim=1))


class ProjectedHead(nn.Module):
    """h's head after its first layer, on the two projected features: what h_head exports.

    Shapes:
        query_feature (B, W), part_feature (B, W) -> translation (B, 3)[, log_scale (B, 3)].
    """

    def __init__(self, rest: nn.Sequential, predict_scale: bool):
        super().__init__()
        self.rest = rest
        self.predict_scale = predict_scale

    def forward(self, query_feature: torch.Tensor, part_feature: torch.Tensor
                ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        out = self.rest(query_feature + part_feature)
        if not self.predict_scale:
            return out
        return out[:, :3], out[:, 3:]


class PlacementHead(nn.Module):
    """The MLP of h on the query and part features, ending in a translation.

    Its first layer is a linear map of the concatenated features, written as two maps that are
    summed (``query_in`` and ``part_in``: the same function as one map of the concatenation),
    then ``after`` (the other layers). Why: the export folds each half into its branch's graph,
    so the service projects a query once and every catalog part once, ahead of time, and the
    head's per-candidate cost is ``after`` alone (about a fifth of the work at the shipped sizes;
    the head runs on every shortlisted candidate of every request).

    With ``predict_scale`` the last layer also gives the per-axis log scale that fits the part
    to the query (a second output; the catalog geometry itself is never changed).

    Shapes:
        query_feature (B, Fq), part_feature (B, Fp) -> translation (B, 3)[, log_scale (B, 3)].
    """

    def __init__(self, query_dim: int, part_dim: int, hidden: tuple[int, ...], batch_norm: bool = True,
                 predict_scale: bool = False):
        super().__init__()
        n_out = 6 if predict_scale else 3
        self.width = hidden[0] if hidden else n_out   # the first layer's width: the projected features'
        self.query_in = nn.Linear(query_dim, self.width, bias=not (batch_norm and hidden))
        self.part_in = nn.Linear(part_dim, self.width, bias=False)
        layers: list[nn.Module] = []
        width = self.width
        for out in hidden[1:]:
            layers += [nn.BatchNorm1d(width)] if batch_norm else []
            layers += [nn.ReLU(), nn.Linear(width, out, bias=not batch_norm)]
            width = out
        if hidden:
            layers += [nn.BatchNorm1d(width)] if batch_norm else []
            layers += [nn.ReLU(), nn.Linear(width, n_out)]
        self.predict_scale = predict_scale
        self.after = ProjectedHead(nn.Sequential(*layers), predict_scale)
        self._register_load_state_dict_pre_hook(_split_concatenated_head, with_module=True)

    def forward(self, query_feature: torch.Tensor, part_feature: torch.Tensor
                ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        return self.after(self.query_in(query_feature), self.part_in(part_feature))


def _split_concatenated_head(module: nn.Module, state_dict: dict[str, torch.Tensor], prefix: str,
                             *_: object) -> None:
    """Read a checkpoint written before the head's first layer was split in two (``mlp.*``).

    Why: the runs of model v3 were trained with one ``Linear`` over the concatenated features
    (``mlp.0``) followed by ``mlp.1...``; the same function is ``query_in`` (the weight's first
    Fq columns, and the bias), ``part_in`` (the other columns) and ``after.rest`` (``mlp.1...``).
    """
    first = prefix + "mlp.0.weight"
    if first not in state_dict or not isinstance(module, PlacementHead):
        return
    weight = state_dict.pop(first)
    fq = module.query_in.in_features
    state_dict[prefix + "query_in.weight"] = weight[:, :fq]
    state_dict[prefix + "part_in.weight"] = weight[:, fq:]
    if prefix + "mlp.0.bias" in state_dict:
        state_dict[prefix + "query_in.bias"] = state_dict.pop(prefix + "mlp.0.bias")
    for key in [k for k in state_dict if k.startswith(prefix + "mlp.")]:
        index, _dot, name = key[len(prefix + "mlp."):].partition(".")
        state_dict[f"{prefix}after.rest.{int(index) - 1}.{name}"] = state_dict.pop(key)


class ProjectedBranch(nn.Module):
    """One branch of h followed by its half of the head's first layer: what h_query and h_part export.

    Shapes:
        points (B, N, 3) -> projected feature (B, W).
    """

    def __init__(self, encoder: PointNetEncoder, project: nn.Linear):
        super().__init__()
        self.encoder = encoder
        self.project = project

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        return self.project(self.encoder(points))


class PlacementNet(nn.Module):
    """h: where a part goes, given the partial assembly (two PointNet branches and a head).

    Split into ``query`` (X, in the shape frame), ``part`` (Y, centred) and ``head`` so the export
    writes three graphs (``exported_modules``) and the service encodes each catalog part once,
    ahead of time.

    Shapes:
        query (B, N, 3), part (B, M, 3) -> translation (B, 3), the part's bounding-box centre
        [, log_scale (B, 3) with ``predict_scale``].
    """

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.query = PointNetEncoder(cfg.placement_point_layers, cfg.placement_fc_layers, cfg.batch_norm,
                                     cfg.dropout)
        self.part = PointNetEncoder(cfg.placement_point_layers, cfg.placement_fc_layers, cfg.batch_norm,
                                    cfg.dropout)
        self.head = PlacementHead(self.query.out_dim, self.part.out_dim, cfg.placement_head_layers,
                                  cfg.batch_norm, cfg.predict_scale)

    @property
    def query_dim(self) -> int:
        """Width of the exported query feature (h_query's output: the branch, then its projection)."""
        return self.head.width

    @property
    def part_dim(self) -> int:
        """Width of the exported part feature (h_part's output, stored per catalog part)."""
        return self.head.width

    def exported_modules(self) -> dict[str, nn.Module]:
        """The modules behind h's three graphs: each branch with its half of the head's first
        layer, and the head's other layers (``PlacementHead`` says why)."""
        return {"h_query": ProjectedBranch(self.query, self.head.query_in),
                "h_part": ProjectedBranch(self.part, self.head.part_in),
                "h_head": self.head.after}

    def forward(self, query: torch.Tensor, part: torch.Tensor
                ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        return self.head(self.query(query), self.part(part))


class RetrievalPair(nn.Module):
    """f and g together, so one forward (and one DistributedDataParallel wrapper) serves a triplet.

    The positive and negative parts go through f as one batch of 2B: one pass instead of two,
    and batch-norm statistics over both.

    Shapes:
        X (B, N, 3), parts (M, N, 3) -> embeddings (M, D), log_weights (B, K), means (B, K, D),
        log_sigmas (B, K, D), category_logits (B, C) or None.
    """

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.f = EmbeddingNet(cfg)
        self.g = RetrievalNet(cfg)

    def forward(self, X: torch.Tensor, parts: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None]:
        embeddings = self.f(parts)
        log_weights, means, log_sigmas, logits = self.g.forward_train(X)
        return embeddings, log_weights, means, log_sigmas, logits


def build_models(cfg: ModelConfig) -> tuple[RetrievalPair, PlacementNet]:
    """The networks of one run, freshly initialised from the current torch seed."""
    cfg.validate()
    return RetrievalPair(cfg), PlacementNet(cfg)


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())
