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

from service.catalog import Catalog
from service.geometry import resample_points
from service.inputs import points_to_base64

REPO = Path(__file__).resolve().parent.parent
EXAMPLE = REPO / "examples" / "chair-without-legs.json"
BODY_KINDS = ("json", "base64")


@dataclass(frozen=True)
class BenchQuery:
    """The points and k of the benchmark's request.

    Shapes:
        points: (n_points, 3) float32, canonical frame.
    """

    points: np.ndarray
    k: int
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


def held_out_queries(catalog: Catalog, count: int, n_points: int = 1000, seed: int = 0) -> list[np.ndarray]:
    """Partial assemblies of held-out shapes: each a test-split shape with one random part left out.

    Points come from the catalog's stored part samples (placed with their translations),
    resampled to ``n_points``; shapes are drawn without replacement (seeded).

    Shapes:
        returns ``count`` arrays of (n_points, 3) float32 (fewer if the catalog has fewer shapes).
    """
    rng = np.random.default_rng(seed)
    rows_of: dict[str, list[int]] = {}
    for i, rec in enumerate(catalog.records):
        if rec.get("split", "test") == "test":
            rows_of.setdefault(rec["shape_id"], []).append(i)
    shapes = sorted(s for s, rows in rows_of.items() if len(rows) >= 2)
    if not shapes:  # a catalog without a test split: any multi-part shape
        rows_of = {}
        for i, rec in enumerate(catalog.records):
            rows_of.setdefault(rec["shape_id"], []).append(i)
        shapes = sorted(s for s, rows in rows_of.items() if len(rows) >= 2)
    picked = rng.permutation(len(shapes))[:count]
    out = []
    for j in picked:
        rows = rows_of[shapes[j]]
        drop = rows[int(rng.integers(len(rows)))]
        pts = np.concatenate([catalog.part_points(i) + catalog.translations[i] for i in rows if i != drop])
        out.append(resample_points(pts, n_points, int(rng.integers(2**31))).astype(np.float32))
    return out
