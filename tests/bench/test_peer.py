"""The peer baseline answers one request correctly: the same model as the service, served plainly."""

from __future__ import annotations

import warnings
from collections.abc import Iterator

import numpy as np
import pytest

from bench.query import EXAMPLE, REPO, load_query
from service.suggest.mixture import mixture_log_likelihood

ARTIFACTS = REPO / "exported"

# Starlette asks for httpx2 for its TestClient; httpx still works (as in tests/service/conftest.py).
warnings.filterwarnings("ignore", message=".*httpx.*starlette.testclient.*")

from fastapi.testclient import TestClient  # noqa: E402

pytest.importorskip("torch")


def test_peer_mixture_likelihood_matches_the_service() -> None:
    from bench.peer.app import mixture_log_likelihood as peer_ll

    rng = np.random.default_rng(0)
    y, mu = rng.normal(size=(40, 6)), rng.normal(size=(3, 6))
    sigma, w = rng.uniform(0.05, 0.5, size=(3, 6)), np.array([0.2, 0.5, 0.3])
    expected = mixture_log_likelihood(y, w, mu, sigma)[0]
    np.testing.assert_allclose(peer_ll(y, w, mu, sigma), expected, rtol=1e-9)


@pytest.fixture(scope="module")
def peer_client() -> Iterator[TestClient]:
    if not (ARTIFACTS / "manifest.json").is_file():
        pytest.skip(f"the peer serves the shipped model: no artifact folder at {ARTIFACTS}")
    from bench.peer.app import app

    with TestClient(app) as client:
        yield client


def test_peer_answers_the_example_like_the_service(peer_client: TestClient) -> None:
    from bench.engine_bench import load_engine
    from service.settings import Settings
    from service.suggest.engine import SuggestOptions

    q = load_query(EXAMPLE)
    r = peer_client.post("/suggest", content=q.body("json", k=5),
                         headers={"Content-Type": "application/json"})
    assert r.status_code == 200, r.text
    sug = r.json()["suggestions"]
    assert [s["rank"] for s in sug] == [1, 2, 3, 4, 5]
    assert len({s["part_id"] for s in sug}) == 5
    assert all(np.isfinite(s["translation"]).all() and len(s["translation"]) == 3 for s in sug)
    assert [s["score"] for s in sug] == sorted((s["score"] for s in sug), reverse=True)
    # The peer ranks by the mixture likelihood alone (the paper's ranking): compare with the
    # engine ranking the same way (no fit key, no complement check).
    engine = load_engine(Settings(artifacts=ARTIFACTS, verify_checksums=False, rank_scale_weight=0.0,
                                  rank_move_weight=0.0, suggest_complement_check=False))
    ours = engine.suggest(q.points, SuggestOptions(k=5, refine_contact=False))
    assert sug[0]["part_id"] == ours.suggestions[0].part_id
    assert sug[0]["score"] == pytest.approx(ours.suggestions[0].score, rel=1e-3)
    # Placement from the full h on the part's stored samples is close to the service's cached features.
    assert np.abs(np.array(sug[0]["translation"]) - ours.suggestions[0].translation).max() < 0.1
    bad = peer_client.post("/suggest", json={"points": [[0, 0, 0]] * 3})
    assert bad.status_code == 422
