"""Golden tests: the served model computes exactly what was pinned when it shipped.

Behaviour must not change under refactors: the graphs' outputs on fixed clouds, and the /suggest
answers (ids in order, scores) of fixed catalog queries, match ``tests/golden/<model_version>.json``
(made by ``python tests/service/golden_testkit.py`` when a model ships).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient
from golden_testkit import answer_values, golden_path, graph_values

from service.artifacts.catalog import Catalog
from service.suggest.engine import SuggestionEngine

# Float32 graphs on another CPU (AVX2 against AVX-512 kernels) differ in the last bits.
ATOL = 1e-4


@pytest.fixture(scope="module")
def golden(engine: SuggestionEngine) -> dict:
    path = golden_path(engine.artifacts.model_version)
    assert path.is_file(), (f"no golden values for model {engine.artifacts.model_version}: pin a shipped "
                            f"model with `python tests/service/golden_testkit.py` ({path})")
    return json.loads(path.read_text())


def test_graph_outputs_match_the_pinned_values(engine: SuggestionEngine, golden: dict) -> None:
    got = graph_values(engine.artifacts.networks, engine.artifacts.n_points)
    assert set(got) == set(golden["graphs"])
    for name, want in golden["graphs"].items():
        np.testing.assert_allclose(np.asarray(got[name]), np.asarray(want), atol=ATOL, rtol=1e-4,
                                   err_msg=f"graph output {name}")


def test_suggest_answers_match_the_pinned_ones(client: TestClient, catalog: Catalog, engine: SuggestionEngine,
                                              golden: dict) -> None:
    got = answer_values(client, catalog, engine.artifacts.n_points)
    assert len(got) == len(golden["answers"])
    for answer, want in zip(got, golden["answers"], strict=True):
        assert answer["part_ids"] == want["part_ids"], answer["shape"]
        np.testing.assert_allclose(answer["scores"], want["scores"], atol=1e-3, rtol=1e-4)
