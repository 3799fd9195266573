"""Micro-batching: batched answers equal the engine's own, bad queries fail alone, shutdown drains.

The batcher runs the real engine; where a test needs to hold a batch while others queue, it
wraps ``engine.suggest_batch`` with a gate (an event), never a stand-in for the engine.
"""

from __future__ import annotations

import asyncio
import re
import threading
import time
from collections.abc import Awaitable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pytest
from fastapi.testclient import TestClient
from service_testkit import AssemblyQuery, assembly_query, make_settings, multi_part_shapes

from service.api.app import create_app
from service.api.batching import MicroBatcher
from service.errors import DeadlineError, InputError, NotReadyError, ServiceError
from service.geometry.inputs import points_to_base64
from service.suggest.engine import SuggestionEngine, SuggestOptions, SuggestResult

Query = tuple[np.ndarray, SuggestOptions]
T = TypeVar("T")


@pytest.fixture(scope="module")
def queries(engine: SuggestionEngine) -> list[AssemblyQuery]:
    cat = engine.catalog
    out = []
    for shape in multi_part_shapes(cat, 6):
        parts = [r["part_id"] for r in cat.records if r["shape_id"] == shape]
        out.append(assembly_query(cat, shape, parts[-1], engine.artifacts.n_points, seed=2))
    return out


def _same(a: SuggestResult, b: SuggestResult) -> None:
    assert [s.part_id for s in a.suggestions] == [s.part_id for s in b.suggestions]
    np.testing.assert_allclose([s.score for s in a.suggestions], [s.score for s in b.suggestions], rtol=1e-5)
    for x, y in zip(a.suggestions, b.suggestions, strict=True):
        np.testing.assert_allclose(x.translation, y.translation, atol=1e-5)


class Gated:
    """``engine.suggest_batch`` that records batch sizes and can hold the next call until released."""

    def __init__(self, engine: SuggestionEngine):
        self.engine = engine
        self.sizes: list[int] = []
        self.ks: list[list[int | None]] = []  # each call's queries' k
        self.hold = threading.Event()
        self.hold.set()
        self.entered = threading.Event()

    def __call__(self, items: list[Query], deadlines: list[float | None]
                 ) -> Sequence[SuggestResult | ServiceError]:
        self.sizes.append(len(items))
        self.ks.append([options.k for _, options in items])
        self.entered.set()
        assert self.hold.wait(60), "the test never released the batch"
        return self.engine.suggest_batch(items, deadlines)

    async def holding(self, submission: Awaitable[T]) -> asyncio.Future[T]:
        """Start ``submission`` with the batch held; return once the worker is inside its engine call
        (a batch of its own), so that what is submitted next queues until ``hold.set()``."""
        self.hold.clear()
        job = asyncio.ensure_future(submission)
        await asyncio.to_thread(self.entered.wait, 60)
        return job


def test_queries_queued_during_a_batch_run_together_and_equal_the_engine(
        engine: SuggestionEngine, queries: list[AssemblyQuery]) -> None:
    run = Gated(engine)
    batcher: MicroBatcher[Query, SuggestResult] = MicroBatcher(run, max_size=32, max_wait=0.0)
    opts = [SuggestOptions(k=5), SuggestOptions(k=3, categories=(engine.catalog.categories[0],)),
            SuggestOptions(k=7, collapse_duplicates=False)]
    items = [(q.points, opts[i % len(opts)]) for i, q in enumerate(queries)]

    async def main() -> list[SuggestResult]:
        first = await run.holding(batcher.submit(items[0]))  # the worker now holds a batch of one
        rest = [asyncio.ensure_future(batcher.submit(it)) for it in items[1:]]
        await asyncio.sleep(0)  # let them all queue
        run.hold.set()
        return list(await asyncio.gather(first, *rest))

    try:
        answers = asyncio.run(main())
    finally:
        batcher.close()
    assert run.sizes == [1, len(items) - 1], "everything queued meanwhile runs as one batch"
    for (points, options), answer in zip(items, answers, strict=True):
        _same(answer, engine.suggest(points, options))


def test_a_bad_query_fails_only_its_own_request(engine: SuggestionEngine, query: AssemblyQuery) -> None:
    run = Gated(engine)
    batcher: MicroBatcher[Query, SuggestResult] = MicroBatcher(run, max_size=32, max_wait=0.0)

    async def main() -> list[Any]:
        warm = await run.holding(batcher.submit((query.points, SuggestOptions(k=2))))
        jobs = [batcher.submit((query.points, SuggestOptions(k=4))),
                batcher.submit((query.points[:3], SuggestOptions())),                 # too few points
                batcher.submit((query.points, SuggestOptions(categories=("spaceship",)))),
                batcher.submit_many([(query.points, SuggestOptions(k=1)),
                                     (query.points, SuggestOptions(k=0))])]
        pending = [asyncio.ensure_future(j) for j in jobs]
        await asyncio.sleep(0)
        run.hold.set()
        return list(await asyncio.gather(warm, *pending, return_exceptions=True))

    try:
        warm, good, few, unknown, many = asyncio.run(main())
    finally:
        batcher.close()
    assert run.sizes == [1, 5]
    assert isinstance(warm, SuggestResult) and isinstance(good, SuggestResult) and len(good.suggestions) == 4
    assert isinstance(few, InputError) and few.code == "too_few_points"
    assert isinstance(unknown, ServiceError) and unknown.code == "unknown_category"
    assert isinstance(many[0], SuggestResult) and len(many[0].suggestions) == 1
    assert isinstance(many[1], InputError) and many[1].code == "k_out_of_range"


def test_an_unexpected_failure_fails_its_batch_and_the_worker_goes_on(engine: SuggestionEngine,
                                                                       query: AssemblyQuery) -> None:
    calls: list[int] = []

    def flaky(items: list[Query], deadlines: list[float | None]) -> Sequence[SuggestResult | ServiceError]:
        calls.append(len(items))
        if len(calls) == 1:
            raise RuntimeError("engine bug")
        return engine.suggest_batch(items, deadlines)

    batcher: MicroBatcher[Query, SuggestResult] = MicroBatcher(flaky, max_size=4, max_wait=0.0)

    async def main() -> tuple[Any, Any]:
        first = await asyncio.gather(batcher.submit((query.points, SuggestOptions(k=2))),
                                     return_exceptions=True)
        second = await batcher.submit((query.points, SuggestOptions(k=2)))
        return first[0], second

    try:
        failed, answered = asyncio.run(main())
    finally:
        batcher.close()
    assert isinstance(failed, RuntimeError) and "engine bug" in str(failed)
    assert isinstance(answered, SuggestResult) and len(answered.suggestions) == 2


def test_a_lone_request_does_not_wait_for_company(engine: SuggestionEngine, query: AssemblyQuery) -> None:
    """With an hour's max_wait and nobody announced, a single query still runs at once."""
    run = Gated(engine)
    batcher: MicroBatcher[Query, SuggestResult] = MicroBatcher(run, max_size=32, max_wait=3600.0)

    async def main() -> SuggestResult:
        return await asyncio.wait_for(batcher.submit((query.points, SuggestOptions(k=3))), timeout=120)

    try:
        result = asyncio.run(main())
    finally:
        batcher.close()
    assert run.sizes == [1] and len(result.suggestions) == 3


def test_an_announced_request_joins_the_batch(engine: SuggestionEngine, query: AssemblyQuery) -> None:
    """A worker holding a partial batch waits for an announced request (within max_wait)."""
    run = Gated(engine)
    batcher: MicroBatcher[Query, SuggestResult] = MicroBatcher(run, max_size=32, max_wait=3600.0)

    async def main() -> list[SuggestResult]:
        with batcher.arriving() as ticket:
            first = asyncio.ensure_future(batcher.submit((query.points, SuggestOptions(k=2))))
            await asyncio.sleep(0.05)  # the worker has the first query and waits for the announced one
            second = await batcher.submit((query.points, SuggestOptions(k=3)), ticket)
        return [await first, second]

    try:
        answers = asyncio.run(main())
    finally:
        batcher.close()
    assert run.sizes == [2]
    assert [len(a.suggestions) for a in answers] == [2, 3]


def test_a_cancelled_request_is_skipped(engine: SuggestionEngine, query: AssemblyQuery) -> None:
    run = Gated(engine)
    batcher: MicroBatcher[Query, SuggestResult] = MicroBatcher(run, max_size=32, max_wait=0.0)

    async def main() -> SuggestResult:
        first = await run.holding(batcher.submit((query.points, SuggestOptions(k=2))))
        gone = asyncio.ensure_future(batcher.submit((query.points, SuggestOptions(k=9))))
        kept = asyncio.ensure_future(batcher.submit((query.points, SuggestOptions(k=4))))
        await asyncio.sleep(0)
        gone.cancel()
        await asyncio.sleep(0)
        run.hold.set()
        await first
        return await kept

    try:
        kept = asyncio.run(main())
    finally:
        batcher.close()
    assert run.sizes == [1, 1] and len(kept.suggestions) == 4


def test_a_job_past_its_deadline_is_not_run(engine: SuggestionEngine, query: AssemblyQuery) -> None:
    run = Gated(engine)
    batcher: MicroBatcher[Query, SuggestResult] = MicroBatcher(run, max_size=32, max_wait=0.0)

    async def main() -> list[Any]:
        first = await run.holding(batcher.submit((query.points, SuggestOptions(k=2))))
        past = time.monotonic() - 1.0  # already expired when the worker gets to it
        late = asyncio.ensure_future(batcher.submit((query.points, SuggestOptions(k=3)), deadline=past))
        fine = asyncio.ensure_future(batcher.submit((query.points, SuggestOptions(k=4)),
                                                    deadline=time.monotonic() + 3600))
        await asyncio.sleep(0)
        run.hold.set()
        return list(await asyncio.gather(first, late, fine, return_exceptions=True))

    try:
        first, late, fine = asyncio.run(main())
        assert isinstance(first, SuggestResult)
    finally:
        batcher.close()
    assert run.sizes == [1, 1], "the expired job never reached the engine"
    assert isinstance(late, DeadlineError) and late.status == 504
    assert isinstance(fine, SuggestResult) and len(fine.suggestions) == 4


def test_close_answers_what_is_queued_and_refuses_the_rest(engine: SuggestionEngine,
                                                           query: AssemblyQuery) -> None:
    run = Gated(engine)
    batcher: MicroBatcher[Query, SuggestResult] = MicroBatcher(run, max_size=2, max_wait=0.0)

    async def main() -> tuple[list[Any], Any]:
        run.hold.clear()
        jobs = [asyncio.ensure_future(batcher.submit((query.points, SuggestOptions(k=k))))
                for k in (1, 2, 3, 4)]
        await asyncio.to_thread(run.entered.wait, 60)
        closing = asyncio.ensure_future(asyncio.to_thread(batcher.close, 60))
        while not batcher.closing:
            await asyncio.sleep(0.01)
        late = await asyncio.gather(batcher.submit((query.points, SuggestOptions(k=5))),
                                    return_exceptions=True)
        run.hold.set()
        answers = await asyncio.gather(*jobs)
        await closing
        return list(answers), late[0]

    answers, late = asyncio.run(main())
    assert [len(a.suggestions) for a in answers] == [1, 2, 3, 4]
    assert sum(run.sizes) == 4 and max(run.sizes) <= 2
    assert isinstance(late, NotReadyError) and late.code == "shutting_down"


def test_bad_batcher_settings_are_refused(engine: SuggestionEngine) -> None:
    with pytest.raises(ValueError, match="max_size"):
        MicroBatcher(engine.suggest_batch, max_size=0, max_wait=0.0)


# ------------------------------------------------------------------ through HTTP


def _histogram(metrics: str, name: str) -> dict[str, float]:
    """Bucket upper bounds -> cumulative counts of an unlabelled histogram, plus its count."""
    out = {m.group(1): float(m.group(2))
           for m in re.finditer(rf'^{name}_bucket{{le="([^"]+)"}} (\S+)$', metrics, re.MULTILINE)}
    count = re.search(rf"^{name}_count (\S+)$", metrics, re.MULTILINE)
    out["count"] = float(count.group(1)) if count else 0.0
    return out


def test_concurrent_http_requests_are_batched_and_all_answered(artifacts: Path, engine: SuggestionEngine,
                                                               queries: list[AssemblyQuery]) -> None:
    settings = make_settings(artifacts, verify_checksums=False, warmup=False, batch_max_wait_ms=500.0)
    bodies: list[dict[str, Any]] = []
    for i in range(24):
        q = queries[i % len(queries)]
        points: dict[str, Any] = ({"points": q.points.tolist()} if i % 2 else
                                  {"points_base64": points_to_base64(q.points)})
        bodies.append({**points, "k": 3 + i % 5})
    bodies.append({"points": queries[0].points[:3].tolist()})  # too few points: 422 alone
    with TestClient(create_app(settings)) as client, ThreadPoolExecutor(len(bodies)) as pool:
        answers = list(pool.map(lambda b: client.post("/suggest", json=b), bodies))
        metrics = client.get("/metrics").text
    assert answers[-1].status_code == 422 and answers[-1].json()["error"]["code"] == "too_few_points"
    for i, (body, answer) in enumerate(zip(bodies[:-1], answers[:-1], strict=True)):
        assert answer.status_code == 200, answer.text
        q = queries[i % len(queries)]
        expected = engine.suggest(q.points, SuggestOptions(k=body["k"]))
        got = [s["part_id"] for s in answer.json()["suggestions"]]
        assert got == [s.part_id for s in expected.suggestions]
    sizes = _histogram(metrics, "complementme_batch_size")
    assert sizes["count"] >= 1
    assert sizes["1.0"] < sizes["count"], "some engine call ran more than one query"
    waits = _histogram(metrics, "complementme_batch_queue_wait_seconds")
    assert waits["count"] == len(bodies), "one queue wait per request (point limits are the engine's)"
    assert "complementme_batch_queued_queries 0.0" in metrics


def test_batch_route_and_mesh_route_go_through_the_batcher(client: TestClient, query: AssemblyQuery) -> None:
    before = _histogram(client.get("/metrics").text, "complementme_batch_queue_wait_seconds")["count"]
    items = [{"points_base64": points_to_base64(query.points), "k": 2}, {"points": query.points.tolist()}]
    assert client.post("/suggest/batch", json={"items": items}).status_code == 200
    after = _histogram(client.get("/metrics").text, "complementme_batch_queue_wait_seconds")["count"]
    assert after == before + 1, "one job for the whole /suggest/batch request"


def test_requests_after_shutdown_are_refused(artifacts: Path, query: AssemblyQuery) -> None:
    app = create_app(make_settings(artifacts, verify_checksums=False, warmup=False))
    body = {"points_base64": points_to_base64(query.points), "k": 2}
    with TestClient(app) as client:
        assert client.post("/suggest", json=body).status_code == 200
        batcher = app.state.served.batcher
    assert app.state.served is None
    with pytest.raises(NotReadyError):
        asyncio.run(batcher.submit((query.points, SuggestOptions(k=2))))
    with TestClient(app, raise_server_exceptions=False) as client:  # a restart gets a new batcher
        assert client.post("/suggest", json=body).status_code == 200


# ------------------------------------------------------------------ fairness and isolation


def test_a_large_job_runs_in_chunks_and_others_go_between(engine: SuggestionEngine,
                                                          query: AssemblyQuery) -> None:
    """max_cost 2 (each query costs 1): a job of 6 runs 2 at a time, and a job queued while its
    first chunk runs goes before its second."""
    run = Gated(engine)
    batcher: MicroBatcher[Query, SuggestResult] = MicroBatcher(run, max_size=32, max_wait=0.0, max_cost=2.0)
    large = [(query.points, SuggestOptions(k=k)) for k in range(1, 7)]

    async def main() -> tuple[list[Any], Any]:
        first = await run.holding(batcher.submit_many(large))
        small = asyncio.ensure_future(batcher.submit((query.points, SuggestOptions(k=9))))
        await asyncio.sleep(0)
        run.hold.set()
        return await first, await small

    try:
        answers, small = asyncio.run(main())
    finally:
        batcher.close()
    assert run.ks == [[1, 2], [9, 3], [4, 5], [6]], "the small job ran right after the first chunk"
    assert [len(a.suggestions) for a in answers] == [1, 2, 3, 4, 5, 6]
    assert len(small.suggestions) == 9


def test_a_deadline_stops_a_large_job_between_its_chunks(engine: SuggestionEngine,
                                                         query: AssemblyQuery) -> None:
    run = Gated(engine)
    batcher: MicroBatcher[Query, SuggestResult] = MicroBatcher(run, max_size=2, max_wait=0.0)

    async def main() -> Any:
        job = await run.holding(batcher.submit_many([(query.points, SuggestOptions(k=2))] * 6,
                                                    deadline=time.monotonic() + 0.3))
        await asyncio.sleep(0.4)  # past the deadline while the first chunk runs
        run.hold.set()
        return (await asyncio.gather(job, return_exceptions=True))[0]

    try:
        outcome = asyncio.run(main())
    finally:
        batcher.close()
    assert isinstance(outcome, DeadlineError)
    assert run.sizes == [2], "no chunk ran past the deadline"


def test_a_failing_request_fails_alone_when_its_batch_breaks(engine: SuggestionEngine,
                                                             query: AssemblyQuery) -> None:
    """An unexpected exception caused by one request's query: the batch runs again job by job."""
    hold = threading.Event()
    entered = threading.Event()

    def fragile(items: list[Query], deadlines: list[float | None]) -> Sequence[SuggestResult | ServiceError]:
        entered.set()
        assert hold.wait(60)
        if any(options.k == 13 for _, options in items):
            raise RuntimeError("engine bug on k = 13")
        return engine.suggest_batch(items, deadlines)

    batcher: MicroBatcher[Query, SuggestResult] = MicroBatcher(fragile, max_size=32, max_wait=0.0)

    async def main() -> list[Any]:
        warm = asyncio.ensure_future(batcher.submit((query.points, SuggestOptions(k=1))))
        await asyncio.to_thread(entered.wait, 60)
        jobs = [asyncio.ensure_future(batcher.submit((query.points, SuggestOptions(k=k))))
                for k in (2, 13, 3)]
        await asyncio.sleep(0)
        hold.set()
        return list(await asyncio.gather(warm, *jobs, return_exceptions=True))

    try:
        warm, two, bad, three = asyncio.run(main())
    finally:
        batcher.close()
    assert isinstance(bad, RuntimeError)
    assert [len(a.suggestions) for a in (warm, two, three)] == [1, 2, 3]
