"""The peer baseline: the shipped model served as a user would write it without this project.

What it does per request, on purpose the straightforward way:

- a plain ``def`` FastAPI handler with a pydantic body (a JSON list of points);
- the points subsampled to the training point count (seeded, as the service does);
- g in torch eager: the shipped networks in torch, their weights read back from the exported
  graphs (``training.from_onnx``; the training checkpoint is not committed, and this way the peer
  serves exactly the function the service serves);
- nearest catalog parts of each mixture mean by brute-force numpy over the catalog embeddings
  (the same ``catalog.npz`` embeddings the service's index holds), their union scored by the
  mixture log-likelihood in numpy, the top k kept;
- the whole placement network h (query and part encoders and head) re-run in torch eager on
  every kept candidate, from the candidate's stored point samples (not cached part features);
  when the artifacts give h its own point count (the manifest's ``placement_points``), h takes
  that many of the request's points and of samples of each part's catalog mesh (drawn once at
  start-up, seeded; the export drew the service's cached features from the dataset's own clouds,
  so the peer's h sees other samples of the same surfaces, as with the stored samples before);
- the answer returned as a dict through FastAPI's default JSON response.

No duplicate collapse and no contact refinement: those are this project's features, and leaving
them out only makes the peer faster. Run with ``uvicorn bench.peer.app:app`` (1 worker); the
artifact folder comes from ``PEER_ARTIFACTS`` (default ``exported/``).
"""

from __future__ import annotations

import json
import os
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from fastapi import FastAPI, HTTPException
from pydantic import BaseModel, Field

from service.geometry.mesh import sample_surface
from training.from_onnx import load_exported_networks
from training.models import PlacementNet, RetrievalNet

REPO = Path(__file__).resolve().parents[2]


class SuggestIn(BaseModel):
    points: list[list[float]]
    k: int = Field(default=10, ge=1, le=100)


@dataclass
class PeerModel:
    """The networks and catalog arrays the peer serves from.

    Shapes:
        embeddings: (P, D) float32.   part_points: (P, S, 3) float32 tensor.
    """

    g: RetrievalNet
    h: PlacementNet
    n_points: int
    placement_points: int
    embeddings: np.ndarray
    part_points: torch.Tensor
    part_ids: list[str]
    neighbours: int
    seed: int


def load_peer(artifacts: Path, neighbours: int = 64, seed: int = 0) -> PeerModel:
    """Rebuild g and h in torch from the artifact folder's graphs and read its catalog arrays."""
    pair, placement, _ = load_exported_networks(artifacts)
    manifest = json.loads((artifacts / "manifest.json").read_text())
    n_points = int(manifest["n_points"])
    h_points = int(manifest.get("placement_points", n_points))
    with np.load(artifacts / "catalog.npz") as data:
        embeddings = data["embeddings"].astype(np.float32)
        if h_points == n_points:
            points = data["points"].astype(np.float32)
        else:
            # Each key of an npz is read from the archive on access: read the meshes once.
            v, f = data["mesh_vertices"].astype(np.float64), data["mesh_faces"]
            vf, ff = data["vertex_first"], data["face_first"]
            points = np.stack([sample_surface(v[vf[i]:vf[i + 1]], f[ff[i]:ff[i + 1]], h_points, seed)
                               for i in range(len(embeddings))])
    records = json.loads((artifacts / "catalog.json").read_text())
    records = records["parts"] if isinstance(records, dict) else records
    return PeerModel(g=pair.g, h=placement, n_points=n_points, placement_points=h_points,
                     embeddings=embeddings, part_points=torch.from_numpy(points),
                     part_ids=[r["part_id"] for r in records], neighbours=neighbours, seed=seed)


def subsample(points: np.ndarray, n: int, seed: int) -> np.ndarray:
    """``n`` of the points, a seeded subset (repeats when fewer): (M, 3) -> (n, 3)."""
    rng = np.random.default_rng(seed)
    if len(points) >= n:
        return points[np.sort(rng.choice(len(points), size=n, replace=False))]
    return np.concatenate([points, points[rng.integers(0, len(points), n - len(points))]])


def mixture_log_likelihood(y: np.ndarray, w: np.ndarray, mu: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """log sum_k w_k N(y | mu_k, diag(sigma_k^2)) per row of y: (C, D) -> (C,)."""
    z = (y[:, None, :] - mu[None]) / sigma[None]                       # (C, K, D)
    log_n = -0.5 * (z ** 2).sum(-1) - np.log(sigma).sum(-1) - 0.5 * y.shape[1] * np.log(2 * np.pi)
    a = np.log(np.maximum(w, 1e-30)) + log_n                            # (C, K)
    m = a.max(axis=1, keepdims=True)
    return (m + np.log(np.exp(a - m).sum(axis=1, keepdims=True)))[:, 0]


def suggest(model: PeerModel, points: np.ndarray, k: int) -> list[dict[str, Any]]:
    """Ranked, placed suggestions for one partial assembly (canonical frame)."""
    x = torch.from_numpy(np.ascontiguousarray(subsample(points, model.n_points, model.seed),
                                              dtype=np.float32))[None]          # (1, N, 3)
    xh = x if model.placement_points == model.n_points else torch.from_numpy(np.ascontiguousarray(
        subsample(points, model.placement_points, model.seed), dtype=np.float32))[None]   # (1, N_h, 3)
    with torch.no_grad():
        w, mu, sigma = (t[0].numpy().astype(np.float64) for t in model.g(x)[:3])  # (K,), (K, D), (K, D)
    emb = model.embeddings
    dist = ((emb[None, :, :] - mu[:, None, :].astype(np.float32)) ** 2).sum(-1)  # (K, P)
    nn = min(model.neighbours, len(emb))
    cand = np.unique(np.argpartition(dist, nn - 1, axis=1)[:, :nn])
    ll = mixture_log_likelihood(emb[cand].astype(np.float64), w, mu, sigma)
    order = np.argsort(-ll, kind="stable")[:k]
    top, scores = cand[order], ll[order]
    with torch.no_grad():
        placed = model.h(xh.expand(len(top), -1, -1), model.part_points[top])
    # A model with a scale head (v3) answers (translations, log scales); the peer places only.
    translations = (placed[0] if isinstance(placed, tuple) else placed).numpy()
    return [{"rank": r + 1, "part_id": model.part_ids[i], "score": float(s), "translation": t.tolist()}
            for r, (i, s, t) in enumerate(zip(top.tolist(), scores, translations, strict=True))]


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    artifacts = Path(os.environ.get("PEER_ARTIFACTS", REPO / "exported"))
    app.state.model = load_peer(artifacts)
    yield


app = FastAPI(title="peer baseline", lifespan=lifespan)


@app.get("/healthz")
def get_healthz() -> dict[str, Any]:
    return {"status": "ok", "torch_threads": torch.get_num_threads()}


@app.post("/suggest")
def post_suggest(body: SuggestIn) -> dict[str, Any]:
    points = np.asarray(body.points, dtype=np.float32)
    if points.ndim != 2 or points.shape[1] != 3 or len(points) < 16:
        raise HTTPException(422, "points must be at least 16 [x, y, z] triples")
    return {"suggestions": suggest(app.state.model, points, body.k)}
