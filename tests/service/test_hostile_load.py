"""Hostile load (issue 16, findings 1, 2, 4 and the small ones of the request path).

A heavy request does not hold the suggestion routes, one client's bad options fail only its own
requests, slow bodies hold no slot, a body shorter than its Content-Length is refused promptly
and a client that leaves mid-body is not counted as a bad request. The live tests run the real
service in its own process (``catalog_testkit.LiveServer``) and talk to it over loopback sockets.
"""

from __future__ import annotations

import asyncio
import logging
import re
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx
import orjson
import pytest
from catalog_testkit import LiveServer
from fastapi.testclient import TestClient
from load_testkit import closed_loop, http_request, probe, read_response, slow_clients
from service_testkit import AssemblyQuery, make_settings

from service.api.app import create_app
from service.errors import InputError
from service.geometry.inputs import points_to_base64
from service.settings import Settings
from service.suggest.engine import SuggestionEngine, SuggestOptions
from service.suggest.preferences import Preferences

pytestmark = pytest.mark.slow

# The live server's settings: big enough for the heavy requests below, quick to give up on a
# stalled body.
LIVE = {"max_k": 100, "max_batch_items": 64, "max_body_bytes": 4 * 1024 * 1024,
        "max_request_cost_ms": 1_000_000, "body_read_timeout": 2.0, "warmup": "true"}


@pytest.fixture(scope="module")
def live(artifacts: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    server = LiveServer(artifacts, tmp_path_factory.mktemp("live") / "data", **LIVE).start()
    try:
        yield server
    finally:
        server.stop()


def _suggest(query: AssemblyQuery, **options: Any) -> dict[str, Any]:
    return {"points_base64": points_to_base64(query.points), **options}


def _request(path: str, body: dict[str, Any]) -> bytes:
    return http_request("POST", path, orjson.dumps(body))


# ------------------------------------------------------------------ finding 1: one heavy request


def test_the_heavy_batch_of_the_issue_is_refused_before_any_work(artifacts: Path,
                                                                 query: AssemblyQuery) -> None:
    """64 items of 1,500 points, k 100, refined: about 2.5 s of CPU by the estimate (the budget is 2 s);
    413 at once."""
    settings = make_settings(artifacts, verify_checksums=False, warmup=False, max_batch_items=64, max_k=100,
                             max_body_bytes=4 * 1024 * 1024)
    points = points_to_base64(query.points[:1500] if len(query.points) >= 1500 else query.points)
    body = {"items": [{"points_base64": points, "k": 100, "refine_contact": True}] * 64}
    with TestClient(create_app(settings)) as client:
        answer = client.post("/suggest/batch", json=body)
        assert answer.status_code == 413, answer.text
        error = answer.json()["error"]
        assert error["code"] == "over_budget"
        assert "2000 ms" in error["message"] and "COMPLEMENTME_MAX_REQUEST_COST_MS" in error["message"]
        # Refused before any work: the engine never ran (no warm-up here, no batch since).
        metrics = client.get("/metrics").text
        assert re.search(r"^complementme_batch_size_count 0\.0$", metrics, re.M), \
            [line for line in metrics.splitlines() if line.startswith("complementme_batch_size")]
        # A single query over the budget is refused the same way; within it, answered.
        # k = 10 refined: about 4 + 10 x 0.35 ms by the estimate; plain: about 4 ms.
        small = make_settings(artifacts, verify_checksums=False, warmup=False, max_request_cost_ms=6.0)
    with TestClient(create_app(small)) as client:
        over = client.post("/suggest", json=_suggest(query, k=10, refine_contact=True))
        assert over.status_code == 413 and over.json()["error"]["code"] == "over_budget"
        assert client.post("/suggest", json=_suggest(query, k=10)).status_code == 200


def test_a_heavy_batch_does_not_delay_a_concurrent_suggest(live: LiveServer, query: AssemblyQuery) -> None:
    """A /suggest/batch of 64 refined k = 100 queries (seconds of CPU even on a fast host: 16 of
    k = 50 once took several, but ran out before the three probes on an AVX-512 host once contact
    refinement got faster) runs in chunks: three /suggest sent meanwhile are answered while the
    batch still runs (each within about one chunk: printed)."""
    heavy = {"items": [_suggest(query, k=100, refine_contact=True)] * 64}
    with httpx.Client(base_url=live.url, timeout=120) as client, ThreadPoolExecutor(1) as pool:
        assert client.post("/suggest", json=_suggest(query, k=5)).status_code == 200  # warm
        started = time.monotonic()
        running = pool.submit(client.post, "/suggest/batch", json=heavy)
        time.sleep(0.5)  # the batch is in the batcher
        waits = []
        for _ in range(3):
            t = time.monotonic()
            answer = client.post("/suggest", json=_suggest(query, k=5))
            waits.append(time.monotonic() - t)
            assert answer.status_code == 200
        assert not running.done(), "the heavy batch finished too soon to show anything"
        batch = running.result()
        heavy_took = time.monotonic() - started
    assert batch.status_code == 200 and all(r["ok"] for r in batch.json()["results"])
    # Measured, not asserted (the ordering above is the behaviour: all three answered while the
    # batch still ran); docs/performance.md has the figures.
    print(f"\n/suggest took at most {max(waits):.2f} s beside a {heavy_took:.1f} s batch")


def test_a_flood_of_fitted_requests_leaves_plain_ones_their_turn(live: LiveServer,
                                                                 query: AssemblyQuery) -> None:
    """32 concurrent /suggest with fit_frame (90 mixture-only queries each, 2,880 in all) and,
    meanwhile, three plain /suggest: the plain ones are answered while the flood still runs,
    since frame fitting's queries wait in the micro-batcher's queue in chunks like any query."""
    fitted = _suggest(query, k=5, fit_frame=True)
    with httpx.Client(base_url=live.url, timeout=120) as client, ThreadPoolExecutor(32) as pool:
        warm = client.post("/suggest", json=fitted)
        assert warm.status_code == 200 and warm.json()["frame_fitted"] is True, warm.text
        flood = [pool.submit(client.post, "/suggest", json=fitted) for _ in range(32)]
        time.sleep(0.3)  # the flood is in the batcher
        for _ in range(3):
            assert client.post("/suggest", json=_suggest(query, k=5)).status_code == 200
        assert not all(f.done() for f in flood), "the flood finished too soon to show anything"
        answers = [f.result() for f in flood]
    assert all(a.status_code == 200 and a.json()["frame_fitted"] is True for a in answers)


# ------------------------------------------------------------------ finding 2: poisoned batches


def test_poisoning_clients_leave_every_normal_request_200(live: LiveServer, engine: SuggestionEngine,
                                                          query: AssemblyQuery) -> None:
    """2 clients with mode_weights all zero beside 8 normal ones: the normal ones all get 200.

    The poisoning clients send from another address: past their error budget
    (``client_error_burst``, then ``client_error_rate`` a second) they are refused with 429
    before their bodies are parsed, and the normal clients are not.
    """
    normal = _request("/suggest", _suggest(query, k=5))
    poison = _request("/suggest", _suggest(query, k=5, mode_weights=[0] * engine.artifacts.n_modes))

    async def main() -> tuple[Any, Any]:
        return await asyncio.gather(closed_loop(live.port, normal, 8, 4.0),
                                    closed_loop(live.port, poison, 2, 4.0, source="127.0.0.2"))

    good, bad = asyncio.run(main())
    assert good.statuses[200] >= 20 and set(good.statuses) == {200}, good.statuses
    assert set(bad.statuses) == {422, 429}, bad.statuses
    # Their 422s: the burst, then the refill; never the hundreds a second of a free-running client.
    burst, rate = Settings.model_fields["client_error_burst"].default, Settings.model_fields[
        "client_error_rate"].default
    assert bad.statuses[422] <= burst + rate * bad.seconds + 2, bad.statuses
    log = live.log.read_text()
    assert "Traceback" not in log and "all_modes_excluded" not in log, log[-2000:]


def test_a_poisoned_item_fails_alone_in_a_batch(client: TestClient, engine: SuggestionEngine,
                                                query: AssemblyQuery) -> None:
    only_one = [0] * engine.artifacts.n_modes
    only_one[1] = 1  # and that one excluded
    items = [_suggest(query, k=3), _suggest(query, k=3, mode_weights=[0] * engine.artifacts.n_modes),
             _suggest(query, k=3, exclude_modes=[1], mode_weights=only_one), _suggest(query, k=2)]
    answer = client.post("/suggest/batch", json={"items": items})
    assert answer.status_code == 200, answer.text
    results = answer.json()["results"]
    assert [r["ok"] for r in results] == [True, False, False, True]
    assert {results[1]["error"]["code"], results[2]["error"]["code"]} == {"all_modes_excluded"}
    assert len(results[3]["result"]["suggestions"]) == 2


def test_an_error_found_in_the_ranking_stays_with_its_query(engine: SuggestionEngine, query: AssemblyQuery,
                                                            caplog: pytest.LogCaptureFixture) -> None:
    """Preferences that fail only once g's weights are known (a fault injected in ``weights``)."""
    class Failing(Preferences):
        def weights(self, phi: Any) -> Any:
            raise InputError("all_modes_excluded", "injected")

    bad = SuggestOptions(k=3, preferences=Failing(mode_weights=(1.0,) * engine.artifacts.n_modes))
    with caplog.at_level(logging.ERROR):
        answers = engine.suggest_batch([(query.points, SuggestOptions(k=3)), (query.points, bad),
                                        (query.points, SuggestOptions(k=4))])
    assert isinstance(answers[1], InputError) and answers[1].code == "all_modes_excluded"
    assert [len(a.suggestions) for a in (answers[0], answers[2])] == [3, 4]  # type: ignore[union-attr]
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


# ------------------------------------------------------------------ finding 4: slow clients


def test_fifty_slow_clients_leave_normal_requests_served(live: LiveServer,
                                                                         query: AssemblyQuery) -> None:
    place = _request("/place", {"points_base64": points_to_base64(query.points), "part_ids": [query.kept[0]]})
    suggest = _request("/suggest", _suggest(query, k=5))
    batch = _request("/suggest/batch", {"items": [_suggest(query, k=3)] * 2})
    health = http_request("GET", "/healthz")

    async def main() -> dict[str, list[float]]:
        # 25 on /place (the general gate, 4 slots) and 25 on /suggest, one byte every 0.5 s.
        async with slow_clients(live.port, place, 25, 0.5), slow_clients(live.port, suggest, 25, 0.5):
            found = {}
            for name, request in (("place", place), ("suggest", suggest), ("batch", batch),
                                  ("healthz", health)):
                found[name] = await probe(live.port, request, every=0.05, seconds=0.6)
            return found

    found = asyncio.run(main())
    # Every probe answered 200 (``probe`` checks) while the 50 slow bodies still trickled in, and
    # each route answered several in turn: none waited for a slot a slow client held. How long
    # they took is printed, not asserted (the issue's 1 s: docs/performance.md).
    for name, seconds in found.items():
        assert len(seconds) >= 2, f"{name}: {len(seconds)} answer(s) beside 50 slow clients"
    print("\n" + ", ".join(f"{n} worst {max(v):.3f} s" for n, v in found.items()))


def test_a_body_shorter_than_its_content_length_gets_408_promptly(live: LiveServer) -> None:
    async def main() -> tuple[int, bytes, float]:
        reader, writer = await asyncio.open_connection("127.0.0.1", live.port)
        head = http_request("POST", "/place", b"x" * 1000).partition(b"\r\n\r\n")[0]
        t = time.monotonic()
        writer.write(head + b"\r\n\r\n" + b'{"points"')  # 9 of 1000 bytes, then nothing
        status, body, _ = await asyncio.wait_for(read_response(reader), 20)
        writer.close()
        return status, body, time.monotonic() - t

    status, body, took = asyncio.run(main())
    assert status == 408 and orjson.loads(body)["error"]["code"] == "body_timeout", body
    assert took < LIVE["body_read_timeout"] + 2.0, f"408 after {took:.1f} s"  # type: ignore[operator]


def test_a_client_gone_mid_body_is_not_counted_as_a_bad_request(live: LiveServer) -> None:
    def count(metrics: str, status: str) -> float:
        pattern = rf'complementme_http_requests_total{{method="POST",route="/place",status="{status}"}} (\S+)'
        return sum(float(m) for m in re.findall(pattern, metrics))

    before = httpx.get(live.url + "/metrics").text

    async def main() -> None:
        _, writer = await asyncio.open_connection("127.0.0.1", live.port)
        head = http_request("POST", "/place", b"x" * 1000).partition(b"\r\n\r\n")[0]
        writer.write(head + b"\r\n\r\n" + b'{"points": [')
        await writer.drain()
        await asyncio.sleep(0.2)
        writer.close()
        await asyncio.sleep(0.5)  # the server sees the disconnect

    asyncio.run(main())
    after = httpx.get(live.url + "/metrics").text
    assert count(after, "400") == count(before, "400"), "a client disconnect counted as a 400"
    assert count(after, "499") == count(before, "499") + 1
