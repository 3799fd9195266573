"""The framework peers answer the benchmark request like the service: same top-10, same placements.

The peer's pipeline is checked in process first (against the engine, alone and inside a batch of
other queries), then each framework peer is started on loopback from its own venv (created by
``ensure_venv`` when missing; .ci/run creates it beforehand) and asked over HTTP.
"""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import numpy as np
import pytest

from bench.framework.pipeline import PeerConfig, PeerModel, RequestError, parse_request
from bench.framework.venv import FRAMEWORKS, ensure_venv, requirements
from bench.framework_bench import compare_answers, framework_peer, peer_config
from bench.query import EXAMPLE, BenchQuery, load_query
from service.settings import Settings
from service.suggest.engine import SuggestionEngine, SuggestOptions


@pytest.fixture(scope="module")
def settings() -> Settings:
    return Settings(verify_checksums=False)


@pytest.fixture(scope="module")
def query() -> BenchQuery:
    return load_query(EXAMPLE, n_points=1000, k=10)


@pytest.fixture(scope="module")
def ours(settings: Settings, query: BenchQuery) -> dict[str, list[dict[str, object]]]:
    """The service engine's answer to the benchmark request (the default /suggest), as JSON."""
    from bench.engine_bench import load_engine

    engine: SuggestionEngine = load_engine(settings)
    result = engine.suggest(np.asarray(json.loads(query.body("json"))["points"]), SuggestOptions(k=query.k))
    return {"suggestions": [{"part_id": s.part_id, "translation": s.translation.tolist()}
                            for s in result.suggestions]}


@pytest.fixture(scope="module")
def model(settings: Settings) -> PeerModel:
    return PeerModel(peer_config(settings, "litserve", workers=1))


def test_pipeline_answers_like_the_engine_alone_and_in_a_batch(model: PeerModel, query: BenchQuery,
                                                                ours: dict) -> None:
    cfg = model.cfg
    request = parse_request(json.loads(query.body("json")), cfg)
    alone = model.suggest_batch([request])[0]
    assert compare_answers({"suggestions": alone}, ours)["match"]
    other = parse_request({"points": (query.points[::-1] * 0.8).tolist(), "k": 3}, cfg)
    batch = model.suggest_batch([other, request, other])
    assert [len(a) for a in batch] == [3, 10, 3]
    assert compare_answers({"suggestions": batch[1]}, ours)["match"]


def test_a_category_filter_keeps_the_search_in_the_category(model: PeerModel) -> None:
    cat = model.catalog
    means = cat.embeddings[:16].reshape(2, 8, -1)  # (B, K, D): two queries of 8 means each
    code = int(cat.category_of[100])
    filtered, unfiltered = model._search(means, [code, None], k=10)
    assert len(filtered) and (cat.category_of[filtered] == code).all()
    assert set(range(8, 16)) <= set(unfiltered.tolist())  # each mean is a part: it finds itself


@pytest.mark.parametrize("body, message", [
    ({"k": 10}, '"points"'),
    ({"points": [[0, 0]] * 20}, "shape (N, 3)"),
    ({"points": [[0, 0, 0]] * 3}, "between 16 and"),
    ({"points": [[0, 0, 0]] * 20, "k": 0}, "k must be"),
    ({"points": [[0, 0, float("nan")]] * 20}, "finite"),
])
def test_bad_requests_are_refused_with_what_is_wrong(settings: Settings, body: dict, message: str) -> None:
    with pytest.raises(RequestError, match=message.replace("(", r"\(").replace(")", r"\)")):
        parse_request(body, peer_config(settings, "bentoml", workers=1))


def test_compare_answers_needs_the_same_parts_in_order_and_close_placements() -> None:
    a = {"suggestions": [{"part_id": "x", "translation": [0, 0, 0]},
                         {"part_id": "y", "translation": [1, 0, 0]}]}
    assert compare_answers(a, a)["match"]
    swapped = {"suggestions": a["suggestions"][::-1]}
    assert not compare_answers(swapped, a)["match"]
    moved = {"suggestions": [a["suggestions"][0], {"part_id": "y", "translation": [1, 0.01, 0]}]}
    result = compare_answers(moved, a)
    assert result["same_ids"] and not result["match"] and result["max_translation_gap"] == pytest.approx(0.01)


def test_peer_requirements_pin_the_numeric_packages_as_the_project_lock() -> None:
    lock = (Path(__file__).resolve().parents[2] / "docker" / "constraints.txt").read_text()
    reqs = requirements()
    for pinned in reqs:
        name = pinned.split("==")[0]
        if name not in FRAMEWORKS:
            assert f"\n{pinned}\n" in f"\n{lock}\n", pinned
    assert {r.split("==")[0] for r in reqs} >= set(FRAMEWORKS)


@pytest.fixture(scope="module")
def peer_venv() -> Path:
    return ensure_venv()


@pytest.mark.slow
@pytest.mark.parametrize("framework", sorted(FRAMEWORKS))
def test_framework_peer_serves_the_same_top10_over_http(framework: str, peer_venv: Path, settings: Settings,
                                                         query: BenchQuery, ours: dict,
                                                         tmp_path: Path) -> None:
    cfg: PeerConfig = peer_config(settings, framework, workers=1)
    with framework_peer(framework, cfg, tmp_path, start_timeout=240) as server:
        url = server.url
        r = httpx.post(url + "/suggest", content=query.body("json"),
                       headers={"Content-Type": "application/json"}, timeout=60)
        assert r.status_code == 200, r.text
        result = compare_answers(r.json(), ours)
        assert result["match"], result
        bad = httpx.post(url + "/suggest", json={"points": [[0, 0, 0]] * 3, "k": 10}, timeout=60)
        assert 400 <= bad.status_code < 500 and "between 16 and" in bad.text, (bad.status_code, bad.text)
