"""The five exported networks behind typed calls (the paper's f, g and h; Section 5).

Each method is one ONNX Runtime run on a whole batch; callers batch their work so that a request
costs one run per graph, never one per candidate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import onnxruntime as ort


@dataclass
class Mixture:
    """The Gaussian mixture g predicts over the embedding space, per query.

    Shapes:
        weights: (B, K) float32, softmax weights phi_k.
        means: (B, K, D) float32, mu_k.
        sigmas: (B, K, D) float32, per-dimension standard deviations sigma_k.
    """

    weights: np.ndarray
    means: np.ndarray
    sigmas: np.ndarray


@dataclass
class Networks:
    """ONNX sessions of the embedding f, retrieval g and the three parts of the placement h."""

    f: ort.InferenceSession
    g: ort.InferenceSession
    h_query: ort.InferenceSession
    h_part: ort.InferenceSession
    h_head: ort.InferenceSession

    def embed(self, points: np.ndarray) -> np.ndarray:
        """Embed centred part point clouds: (B, S, 3) float32 -> (B, D) float32."""
        return self.f.run(["embedding"], {"points": _f32(points)})[0]

    def mixture(self, points: np.ndarray) -> Mixture:
        """Predict the complement distribution of partial assemblies: (B, N, 3) -> Mixture."""
        w, mu, sigma = self.g.run(["weights", "means", "sigmas"], {"points": _f32(points)})
        return Mixture(weights=w, means=mu, sigmas=sigma)

    def query_features(self, points: np.ndarray) -> np.ndarray:
        """Placement features of partial assemblies: (B, N, 3) -> (B, Fq) float32."""
        return self.h_query.run(["query_feature"], {"points": _f32(points)})[0]

    def part_features(self, points: np.ndarray) -> np.ndarray:
        """Placement features of centred parts: (B, S, 3) -> (B, Fp) float32."""
        return self.h_part.run(["part_feature"], {"points": _f32(points)})[0]

    def place(self, query_features: np.ndarray, part_features: np.ndarray) -> np.ndarray:
        """Translations of parts next to queries, row by row: (B, Fq), (B, Fp) -> (B, 3) float32."""
        return self.h_head.run(["translation"], {"query_feature": _f32(query_features),
                                                 "part_feature": _f32(part_features)})[0]


def _f32(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32)
