"""The five exported networks behind typed calls (the paper's f, g and h; Section 5).

Each method is one ONNX Runtime run on a whole batch; callers batch their work so that a request
costs one run per graph, never one per candidate.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import onnxruntime as ort


@dataclass
class Mixture:
    """The Gaussian mixture g predicts over the embedding space, per query.

    Shapes:
        weights: (B, K) float32, softmax weights phi_k.
        means: (B, K, D) float32, mu_k.
        sigmas: (B, K, D) float32, per-dimension standard deviations sigma_k.
        category_probs: (B, C) float32 over the manifest's categories, or None when g has no
            category head (models before v3).
    """

    weights: np.ndarray
    means: np.ndarray
    sigmas: np.ndarray
    category_probs: np.ndarray | None = None

    def take(self, rows: list[int]) -> Mixture:
        """The mixtures of some queries of the batch, in the order of ``rows``."""
        probs = None if self.category_probs is None else self.category_probs[rows]
        return Mixture(self.weights[rows], self.means[rows], self.sigmas[rows], probs)


@dataclass
class Networks:
    """ONNX sessions of the embedding f, retrieval g and the three parts of the placement h.

    Point-cloud graphs run on at most ``max_points_per_run`` points (batch x points per cloud)
    at a time: per-point activations of a larger run fall out of the CPU caches, and a run
    then costs more per cloud than several smaller ones.
    """

    f: ort.InferenceSession
    g: ort.InferenceSession
    h_query: ort.InferenceSession
    h_part: ort.InferenceSession
    h_head: ort.InferenceSession
    max_points_per_run: int = 1024

    def _run_points(self, session: ort.InferenceSession, outputs: list[str], points: np.ndarray
                    ) -> list[np.ndarray]:
        """Run a graph on (B, N, 3) points in chunks of rows; outputs concatenated on axis 0."""
        points = _f32(points)
        rows = max(1, self.max_points_per_run // max(1, points.shape[1]))
        if len(points) <= rows:
            return session.run(outputs, {"points": points})
        parts = [session.run(outputs, {"points": points[i:i + rows]}) for i in range(0, len(points), rows)]
        return [np.concatenate([p[j] for p in parts]) for j in range(len(outputs))]

    def embed(self, points: np.ndarray) -> np.ndarray:
        """Embed centred part point clouds: (B, S, 3) float32 -> (B, D) float32."""
        return self._run_points(self.f, ["embedding"], points)[0]

    # Read once per load: the graphs do not change, and every batch asks.
    @cached_property
    def has_category_head(self) -> bool:
        return any(o.name == "category_probs" for o in self.g.get_outputs())

    @cached_property
    def has_scale_head(self) -> bool:
        return any(o.name == "log_scale" for o in self.h_head.get_outputs())

    def mixture(self, points: np.ndarray) -> Mixture:
        """Predict the complement distribution of partial assemblies: (B, N, 3) -> Mixture."""
        names = ["weights", "means", "sigmas"] + (["category_probs"] if self.has_category_head else [])
        out = self._run_points(self.g, names, points)
        return Mixture(weights=out[0], means=out[1], sigmas=out[2],
                       category_probs=out[3] if len(out) > 3 else None)

    def query_features(self, points: np.ndarray) -> np.ndarray:
        """Placement features of partial assemblies: (B, N, 3) -> (B, Fq) float32."""
        return self._run_points(self.h_query, ["query_feature"], points)[0]

    def part_features(self, points: np.ndarray) -> np.ndarray:
        """Placement features of centred parts: (B, S, 3) -> (B, Fp) float32."""
        return self._run_points(self.h_part, ["part_feature"], points)[0]

    def place(self, query_features: np.ndarray, part_features: np.ndarray) -> np.ndarray:
        """Translations of parts next to queries, row by row: (B, Fq), (B, Fp) -> (B, 3) float32."""
        return self.place_and_fit(query_features, part_features)[0]

    def place_and_fit(self, query_features: np.ndarray, part_features: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
        """Translations and per-axis fitting scales, row by row (scale 1 without a scale head).

        Shapes:
            (B, Fq), (B, Fp) -> translation (B, 3) float32, scale (B, 3) float32.
        """
        feed = {"query_feature": _f32(query_features), "part_feature": _f32(part_features)}
        if not self.has_scale_head:
            translation = self.h_head.run(["translation"], feed)[0]
            return translation, np.ones_like(translation)
        translation, log_scale = self.h_head.run(["translation", "log_scale"], feed)
        return translation, scales_of(log_scale)


def scales_of(log_scale: np.ndarray) -> np.ndarray:
    """h_head's ``log_scale`` output as per-axis scales.

    A query far outside the model's frame can drive the head to huge values: the engine clips
    scales to its settings' range anyway, so clip here before exp can overflow.

    Shapes:
        (B, 3) -> (B, 3) float32.
    """
    return np.exp(np.clip(log_scale, -20.0, 20.0)).astype(np.float32)


def _f32(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)
