"""The benchmark's query (1000 points, k = 10) and its two request bodies, plus held-out queries.

The query is ``examples/chair-without-legs.json``'s points: a held-out chair without its legs in
the canonical frame. Its own ``k`` and ``category`` are dropped: the acceptance targets are for
one unfiltered /suggest of 1000 points with k = 10.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import orjson

# The framework peer's decoded request owns a query's fields; it cannot import this module instead
# (the peer's own venv has no orjson, nor the service's settings).
from bench.framework.pipeline import Query
from service.geometry.inputs import points_to_base64
from service.geometry.mesh import resample_points

REPO = Path(__file__).resolve().parent.parent
EXAMPLE = REPO / "examples" / "chair-without-legs.json"
BODY_KINDS = ("json", "base64")


@dataclass(frozen=True)
class BenchQuery(Query):
    """The benchmark's request: its points and k, as the framework peer decodes a request (``Query``),
    and the file they came from."""

    source: str

    def body(self, kind: str, **options: Any) -> bytes:
        """The /suggest request body: ``json`` (a list of [x, y, z]) or ``base64`` (float32).

        ``options`` are further request fields (``refine_contact=False``, say).
        """
        if kind == "json":
            # Coordinates rounded as a client's JSON writer would (the example has 4 decimals).
            points: dict[str, Any] = {"points": np.round(self.points.astype(np.float64), 6).tolist()}
        elif kind == "base64":
            points = {"points_base64": points_to_base64(self.points)}
        else:
            raise ValueError(f"unknown body kind {kind!r}; expected one of {', '.join(BODY_KINDS)}")
        return orjson.dumps({**points, "k": self.k, **options})


def load_query(path: Path = EXAMPLE, n_points: int = 1000, k: int = 10, seed: int = 0) -> BenchQuery:
    """The example's points, resampled (seeded) to exactly ``n_points`` if it has another count."""
    try:
        data = json.loads(Path(path).read_text())
        pts = np.asarray(data["points"], dtype=np.float32)
    except (OSError, json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path}: expected a JSON object with 'points': [[x, y, z], ...] ({exc})") from exc
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) == 0:
        raise ValueError(f"{path}: 'points' must have shape (N, 3), found {pts.shape}")
    if len(pts) != n_points:
        pts = resample_points(pts, n_points, seed)
    return BenchQuery(points=np.ascontiguousarray(pts, dtype=np.float32), k=k, source=str(path))
