"""The golden values of the shipped model: its graphs' outputs and its answers on fixed inputs.

``tests/service/test_golden.py`` compares the artifact folder under test with the file this
module writes for its model version. Refactors must leave them unchanged; a new model is pinned
again, on purpose, when it ships:

    python tests/service/golden_testkit.py          # exported/ -> tests/golden/<model_version>.json
    python tests/service/golden_testkit.py FOLDER

Inputs are seeded and built here, so the values say what the graphs compute, not what a test
happened to sample. Catalog queries come from the catalog itself (tests/service/service_testkit).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
from service_testkit import assembly_query, make_settings, multi_part_shapes

GOLDEN_DIR = Path(__file__).resolve().parents[1] / "golden"
# Shapes (with one part left out) whose answers are pinned, and the clouds fed to each graph.
QUERIES = 3
CLOUDS = 3
TOP = 10


def golden_path(model_version: str) -> Path:
    return GOLDEN_DIR / f"{model_version}.json"


def fixed_clouds(n_points: int) -> np.ndarray:
    """Seeded clouds in the canonical frame: a box's surface at three sizes.

    Shapes:
        return: (CLOUDS, n_points, 3) float32.
    """
    rng = np.random.default_rng(20261202)
    clouds = []
    for size in (0.3, 0.6, 0.9):
        p = rng.uniform(-size / 2, size / 2, size=(n_points, 3))
        face = rng.integers(0, 3, size=n_points)
        p[np.arange(n_points), face] = np.sign(p[np.arange(n_points), face]) * size / 2
        clouds.append(p)
    return np.asarray(clouds, dtype=np.float32)


def graph_values(networks: Any, n_points: int) -> dict[str, Any]:
    """What each served graph gives for the fixed clouds (query = part = the same cloud)."""
    clouds = fixed_clouds(n_points)
    mixture = networks.mixture(clouds)
    qf, pf = networks.query_features(clouds), networks.part_features(clouds)
    translation, scale = networks.place_and_fit(qf, pf)
    return {"embedding": networks.embed(clouds), "weights": mixture.weights, "means": mixture.means,
            "sigmas": mixture.sigmas, "translation": translation, "scale": scale}


def answer_values(client: Any, catalog: Any, n_points: int) -> list[dict[str, Any]]:
    """The /suggest top ids and scores of fixed catalog queries (category given), through the app."""
    answers = []
    for shape in multi_part_shapes(catalog, QUERIES):
        last = [r["part_id"] for r in catalog.records if r["shape_id"] == shape][-1]
        q = assembly_query(catalog, shape, last, n_points)
        category = catalog.records[catalog.lookup(last)]["category"]
        body = {"points": q.points.tolist(), "k": TOP, "category": category}
        resp = client.post("/suggest", json=body)
        assert resp.status_code == 200, resp.text
        got = resp.json()["suggestions"]
        answers.append({"shape": shape, "missing": last, "category": category,
                        "part_ids": [s["part_id"] for s in got], "scores": [s["score"] for s in got]})
    return answers


def pin(folder: Path) -> Path:
    from fastapi.testclient import TestClient

    from service.api.app import create_app

    with TestClient(create_app(make_settings(folder))) as client:
        engine = client.app.state.served.engine  # type: ignore[attr-defined]
        arts = engine.artifacts
        graphs = graph_values(arts.networks, arts.n_points)
        values = {k: np.asarray(v).round(6).tolist() for k, v in graphs.items()}
        record = {"model_version": arts.model_version, "graphs": values,
                  "answers": answer_values(client, engine.catalog, arts.n_points)}
    path = golden_path(record["model_version"])
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=1) + "\n")
    return path


if __name__ == "__main__":
    print(pin(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("exported")))
