"""Overload: a bounded gate on inference requests (503 + Retry-After) and a deadline (504)."""

from __future__ import annotations

import asyncio
import threading
import time
from functools import partial
from pathlib import Path
from typing import Any

import anyio
import httpx
import orjson
import pytest
from fastapi.testclient import TestClient
from service_testkit import AssemblyQuery, make_settings
from starlette.types import Receive, Scope, Send

from service.api.app import create_app
from service.api.middleware import body_bound
from service.api.overload import (
    ClientErrorBudget,
    ErrorBudgetMiddleware,
    InferenceGate,
    OverloadMiddleware,
    ReceptionBudget,
)


def test_gate_admits_queues_and_refuses() -> None:
    async def run() -> None:
        gate = InferenceGate(max_inflight=2, max_queue=1)
        assert gate.try_enter() is None and gate.try_enter() is None
        waiter = gate.try_enter()
        assert waiter is not None and gate.waiting == 1
        with pytest.raises(OverflowError):
            gate.try_enter()
        gate.leave(0.5)  # the slot passes to the waiter: still two running
        assert waiter.done() and gate.inflight == 2 and gate.waiting == 0
        gate.leave()
        gate.leave()
        assert gate.inflight == 0
        # A waiter that gives up after being handed a slot passes it on (no slot is lost).
        assert gate.try_enter() is None and gate.try_enter() is None
        late = gate.try_enter()
        assert late is not None
        gate.leave()
        gate.abandon(late)
        assert gate.inflight == 1
        assert 1 <= gate.retry_after() <= 60

    asyncio.run(run())


def _slow_app(seconds: float, in_thread: bool = False) -> Any:
    """An ASGI app that works ``seconds`` (asleep, or in a worker thread like a sync route)."""
    async def app(scope: Scope, receive: Receive, send: Send) -> None:
        if in_thread:
            await anyio.to_thread.run_sync(time.sleep, seconds)
        else:
            await asyncio.sleep(seconds)
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"done"})
    return app


def _run(middleware: OverloadMiddleware, requests: list[tuple[str, float]]) -> list[httpx.Response]:
    """Send requests (method, start delay) concurrently through the middleware."""
    async def main() -> list[httpx.Response]:
        transport = httpx.ASGITransport(app=middleware)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            async def one(method: str, delay: float) -> httpx.Response:
                await asyncio.sleep(delay)
                return await client.request(method, "/work")
            return list(await asyncio.gather(*(one(m, d) for m, d in requests)))
    return asyncio.run(main())


def test_past_the_queue_requests_get_503_with_retry_after() -> None:
    mw = OverloadMiddleware(_slow_app(0.3), max_inflight=1, max_queue=1, timeout=10)
    answers = _run(mw, [("POST", 0), ("POST", 0.05), ("POST", 0.1), ("GET", 0.1)])
    assert [a.status_code for a in answers] == [200, 200, 503, 200], "GETs are not gated"
    refused = answers[2]
    assert refused.json()["error"]["code"] == "overloaded"
    assert 1 <= int(refused.headers["retry-after"]) <= 60
    assert mw.gate.inflight == 0 and mw.gate.waiting == 0


def test_catalog_writes_do_not_take_query_slots() -> None:
    mw = OverloadMiddleware(_slow_app(0.3), max_inflight=1, max_queue=0, timeout=10, max_inflight_writes=1)

    async def main() -> list[int]:
        transport = httpx.ASGITransport(app=mw)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            answers = await asyncio.gather(client.post("/parts"), client.post("/suggest"),
                                           client.delete("/parts/a/0"))
            return [a.status_code for a in answers]

    # The write and the query each have their slot; the second write finds the write gate full.
    assert asyncio.run(main()) == [200, 200, 503]


def test_a_request_past_its_deadline_gets_504_and_its_slot_waits_for_the_thread() -> None:
    # The work blocks in its thread until released: the answers below come while it still runs.
    release, started = threading.Event(), threading.Event()

    def work() -> None:
        started.set()
        assert release.wait(60), "the test never released the work"

    async def app(scope: Scope, receive: Receive, send: Send) -> None:
        await anyio.to_thread.run_sync(work)
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"done"})

    mw = OverloadMiddleware(app, max_inflight=1, max_queue=4, timeout=0.2)

    async def main() -> None:
        transport = httpx.ASGITransport(app=mw)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            first, second = await asyncio.gather(client.post("/work"), client.post("/work"))
            assert not release.is_set() and started.is_set(), "the 504 must not wait for the work"
            assert first.status_code == 504 and first.json()["error"]["code"] == "deadline_exceeded"
            # The second waited for the slot, which the still-running thread holds: 503 at its deadline.
            assert second.status_code == 503 and "retry-after" in second.headers
            assert mw.gate.inflight == 1, "the thread still computes: its slot is still taken"
            release.set()
            for _ in range(6000):  # the slot comes back when the thread ends
                if mw.gate.inflight == 0:
                    break
                await asyncio.sleep(0.01)
            assert mw.gate.inflight == 0

    asyncio.run(main())


def test_real_app_deadline_and_gate(artifacts: Path, query: AssemblyQuery) -> None:
    body = {"points": query.points.tolist(), "k": 3}
    with TestClient(create_app(make_settings(artifacts, request_timeout=1e-6, verify_checksums=False))) as c:
        answer = c.post("/suggest", json=body)
        assert answer.status_code == 504 and answer.json()["error"]["code"] == "deadline_exceeded"
        metrics = c.app.state.metrics.render().decode()  # type: ignore[attr-defined]
        assert 'complementme_overload_rejections_total{reason="deadline"}' in metrics
    with TestClient(create_app(make_settings(artifacts, max_inflight=1, max_queue=0,
                                             verify_checksums=False))) as c:
        assert c.post("/suggest", json=body).status_code == 200  # one at a time is fine
        assert "complementme_inflight_requests 0.0" in c.get("/metrics").text


def _reading_app(reads: list[str], seconds: float = 0.0) -> Any:
    """An app that reads its whole body (recording its path per chunk), works ``seconds``
    (asleep), then answers 200."""
    async def app(scope: Scope, receive: Receive, send: Send) -> None:
        while True:
            message = await receive()
            reads.append(scope["path"])
            if not message.get("more_body", False):
                break
        await asyncio.sleep(seconds)
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"done"})
    return app


def test_a_full_gate_refuses_before_reading_and_slow_bodies_hold_no_slot() -> None:
    """A request whose body is still arriving holds no slot; one arriving at a full gate is
    refused without a byte of its body read."""
    reads: list[str] = []
    mw = OverloadMiddleware(_reading_app(reads, 0.3), max_inflight=1, max_queue=0, timeout=10)

    async def main() -> list[int]:
        transport = httpx.ASGITransport(app=mw)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            release = asyncio.Event()

            async def slow_body() -> Any:
                yield b"{"
                await release.wait()
                yield b"}"

            slow = asyncio.ensure_future(client.post("/slow", content=slow_body()))
            await asyncio.sleep(0.05)
            assert mw.gate.inflight == 0, "a body still arriving holds no slot"
            fast = asyncio.ensure_future(client.post("/fast", content=b"{}"))
            await asyncio.sleep(0.05)
            assert mw.gate.inflight == 1 and mw.gate.full()
            refused = await client.post("/refused", content=b"{}")
            release.set()
            answers = [await fast, refused, await slow]
            return [a.status_code for a in answers]

    statuses = asyncio.run(main())
    assert statuses[:2] == [200, 503]
    assert statuses[2] in (200, 503)  # its body came in while the fast one still ran
    assert "/refused" not in reads, "the refused request's body was never read"


# ------------------------------------------------------------------ bodies being received


def test_reception_budget_lets_a_body_larger_than_itself_in_alone() -> None:
    budget = ReceptionBudget(1000)
    assert budget.take(600) and budget.take(400)
    assert not budget.take(1), "full: nothing more, however small"
    budget.give(600)
    assert budget.take(601) is False and budget.take(600)
    budget.give(400)
    budget.give(600)
    assert budget.held == 0 and budget.bodies == 0
    assert budget.take(5000), "alone, a body over the whole budget may still be sent"
    assert not budget.take(1)


def test_reception_budget_gives_each_client_a_share() -> None:
    budget = ReceptionBudget(1000, per_client=600)
    assert budget.take(500, "a") and budget.refusal(200, "a") == "client"
    assert budget.take(400, "b"), "another client is not touched by a's share"
    assert budget.refusal(200, "c") == "all" and budget.held_by("a") == 500
    budget.give(500, "a")
    assert budget.held_by("a") == 0 and budget.take(600, "a")
    budget.give(600, "a")
    budget.give(400, "b")
    assert (budget.held, budget.bodies, budget.held_by("b")) == (0, 0, 0)
    assert budget.take(900, "a"), "alone, a body over the client's share may still be sent"


def test_bodies_being_received_are_bounded_by_their_bytes() -> None:
    """A request whose body would take the bodies in reception past the budget is refused 503
    before a byte is read; one that fits goes on; a chunked body reserves its path's limit."""
    reads: list[str] = []
    mw = OverloadMiddleware(_reading_app(reads), max_inflight=8, max_queue=8, timeout=10,
                            max_receiving_bytes=1000,
                            body_bound=partial(body_bound, max_body_bytes=600, max_upload_bytes=5000))
    reception = mw.reception
    assert reception is not None

    async def main() -> None:
        transport = httpx.ASGITransport(app=mw)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            release = asyncio.Event()

            async def slow_body() -> Any:
                yield b"x" * 250
                await release.wait()
                yield b"x" * 250

            async def chunked() -> Any:
                yield b"{}"

            slow = asyncio.ensure_future(client.post("/slow", content=slow_body(),
                                                     headers={"content-length": "500"}))
            await asyncio.sleep(0.05)
            assert (reception.held, reception.bodies) == (500, 1), "reserved by its Content-Length"
            big = await client.post("/big", content=b"x" * 600)
            assert big.status_code == 503 and big.json()["error"]["code"] == "overloaded"
            assert "being received" in big.json()["error"]["message"] and "retry-after" in big.headers
            assert (await client.post("/small", content=b"x" * 300)).status_code == 200, "it fits"
            refused = await client.post("/chunked", content=chunked())
            assert refused.status_code == 503, "no length: it reserves its limit, 600"
            release.set()
            assert (await slow).status_code == 200
            assert (reception.held, reception.bodies) == (0, 0)
            # Alone, a chunked upload whose limit (5000) is over the whole budget goes in.
            assert (await client.post("/suggest/mesh", content=chunked())).status_code == 200

    asyncio.run(main())
    assert "/big" not in reads and "/chunked" not in reads, "refused bodies are never read"
    assert mw.metrics.rejections.labels("receiving_full")._value.get() == 2


def test_a_client_with_slow_bodies_cannot_take_the_others_reception() -> None:
    """Past its share, a client's next body is refused 429 before it is read; another client's
    body still goes in."""
    reads: list[str] = []
    mw = OverloadMiddleware(_reading_app(reads), max_inflight=8, max_queue=8, timeout=10,
                            max_receiving_bytes=1000, max_receiving_bytes_per_client=700,
                            body_bound=partial(body_bound, max_body_bytes=600, max_upload_bytes=600))
    reception = mw.reception
    assert reception is not None

    async def main() -> None:
        hostile = httpx.AsyncClient(transport=httpx.ASGITransport(app=mw, client=("10.0.0.1", 1)),
                                    base_url="http://test")
        other = httpx.AsyncClient(transport=httpx.ASGITransport(app=mw, client=("10.0.0.2", 1)),
                                  base_url="http://test")
        async with hostile, other:
            release = asyncio.Event()

            async def slow_body() -> Any:
                yield b"x"
                await release.wait()
                yield b"x"

            slow = [asyncio.ensure_future(hostile.post(f"/slow{i}", content=slow_body(),
                                                       headers={"content-length": "2"})) for i in range(2)]
            chunked = asyncio.ensure_future(hostile.post("/chunked", content=slow_body()))
            await asyncio.sleep(0.05)
            assert reception.held_by("10.0.0.1") == 604, "two of 2 bytes, and a chunked one: its limit"
            refused = await hostile.post("/more", content=b"x" * 100)
            assert refused.status_code == 429 and refused.json()["error"]["code"] == "too_many_bodies"
            assert "retry-after" in refused.headers and "10.0.0.1" in refused.json()["error"]["message"]
            assert (await other.post("/other", content=b"x" * 300)).status_code == 200
            release.set()
            assert [(await r).status_code for r in (*slow, chunked)] == [200, 200, 200]
            assert (reception.held, reception.bodies) == (0, 0)

    asyncio.run(main())
    assert "/more" not in reads and "/other" in reads
    assert mw.metrics.rejections.labels("receiving_client_full")._value.get() == 1


def test_a_body_cut_at_its_deadline_gives_its_reservation_back() -> None:
    mw = OverloadMiddleware(_reading_app([]), max_inflight=1, max_queue=1, timeout=0.2,
                            max_receiving_bytes=1000, body_bound=lambda scope: 700)
    reception = mw.reception
    assert reception is not None

    async def main() -> int:
        transport = httpx.ASGITransport(app=mw)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            async def stalled() -> Any:
                yield b"x"
                await asyncio.sleep(5)
                yield b"x"

            answer = await client.post("/stalled", content=stalled())
            return answer.status_code

    assert asyncio.run(main()) == 408
    assert (reception.held, reception.bodies) == (0, 0)


def test_the_real_app_bounds_bodies_in_reception(artifacts: Path, query: AssemblyQuery) -> None:
    """The app's reception budget is the setting: while a slow body holds it, a query whose
    body would pass it is refused 503; alone, the same query is answered."""
    settings = make_settings(artifacts, max_receiving_bytes=4096, verify_checksums=False)
    body = orjson.dumps({"points": query.points[:64].tolist(), "k": 3})
    assert len(body) > 2048
    with TestClient(create_app(settings)) as c:
        async def main() -> int:
            transport = httpx.ASGITransport(app=c.app)
            async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
                release = asyncio.Event()

                async def slow_body() -> Any:
                    yield b"{"
                    await release.wait()
                    yield b" " * 2047 + b"}"

                # It holds its 2049 bytes while they arrive (and is then refused: no points).
                slow = asyncio.ensure_future(client.post("/suggest", content=slow_body(), headers={
                    "content-length": "2049", "content-type": "application/json"}))
                await asyncio.sleep(0.05)
                refused = await client.post("/suggest", content=body,
                                            headers={"content-type": "application/json"})
                release.set()
                assert (await slow).status_code == 422
                return refused.status_code

        assert asyncio.run(main()) == 503
        alone = c.post("/suggest", content=body, headers={"content-type": "application/json"})
        assert alone.status_code == 200
        assert "complementme_receiving_body_bytes 0.0" in c.get("/metrics").text


# ------------------------------------------------------------------ per-client error budget


class _Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_error_budget_refills_and_tracks_each_client_apart() -> None:
    clock = _Clock()
    budget = ClientErrorBudget(rate=2.0, burst=3, max_clients=2, clock=clock)
    assert budget.wait("a") == 0 and len(budget) == 0, "a client without errors is not even remembered"
    for _ in range(3):
        budget.charge("a")
    assert budget.wait("a") == pytest.approx(0.5), "empty: one token comes back in 1 / rate seconds"
    assert budget.wait("b") == 0, "another client is not touched"
    budget.charge("a")  # a request already running when the bucket emptied: a debt
    assert budget.wait("a") == pytest.approx(1.0)
    clock.now += 1.0
    assert budget.wait("a") == 0
    # Past max_clients, clients whose bucket is full again are forgotten first, then the oldest.
    budget.charge("b")
    clock.now += 10
    budget.charge("a")
    budget.charge("c")
    assert len(budget) == 2 and budget.wait("c") == 0
    for _ in range(3):
        budget.charge("c")
    budget.charge("d")  # neither a nor c is full: a's last error is the oldest
    assert len(budget) == 2 and budget.wait("c") > 0


def _error_app(status: int, reads: list[str]) -> Any:
    """An app that reads the whole body, then answers ``status``."""
    async def app(scope: Scope, receive: Receive, send: Send) -> None:
        while (await receive()).get("more_body", False):
            pass
        reads.append(scope["path"])
        await send({"type": "http.response.start", "status": status, "headers": []})
        await send({"type": "http.response.body", "body": b"no"})
    return app


def test_a_client_past_its_error_budget_is_refused_before_its_body_is_read() -> None:
    reads: list[str] = []
    mw = ErrorBudgetMiddleware(_error_app(422, reads), rate=0.01, burst=3)

    async def main() -> tuple[list[httpx.Response], httpx.Response, httpx.Response, httpx.Response]:
        attacker = httpx.ASGITransport(app=mw, client=("10.0.0.1", 5000))
        other = httpx.ASGITransport(app=mw, client=("10.0.0.2", 5000))
        async with (httpx.AsyncClient(transport=attacker, base_url="http://test") as bad,
                    httpx.AsyncClient(transport=other, base_url="http://test") as good):
            errors = [await bad.post(f"/suggest/{i}", content=b"{}") for i in range(5)]
            return errors, await bad.get("/healthz"), await good.post("/suggest/other", content=b"{}"), \
                await bad.post("/suggest/after")

    errors, probe, other, after = asyncio.run(main())
    assert [a.status_code for a in errors] == [422, 422, 422, 429, 429]
    refused = errors[3].json()["error"]
    assert refused["code"] == "too_many_errors" and "COMPLEMENTME_CLIENT_ERROR_BURST" in refused["message"]
    assert "10.0.0.1" in refused["message"] and int(errors[3].headers["retry-after"]) >= 1
    assert reads[:3] == ["/suggest/0", "/suggest/1", "/suggest/2"] and "/suggest/3" not in reads, (
        "a refused request's body is not read")
    assert probe.status_code == 422, "the probes are never refused (this app answers 422 to all)"
    assert other.status_code == 422, "another client still reaches the app"
    assert after.status_code == 429
    assert mw.budget.wait("10.0.0.1") > 0 and mw.budget.wait("10.0.0.2") == 0


def test_real_app_refuses_a_client_with_too_many_errors(artifacts: Path, query: AssemblyQuery) -> None:
    settings = make_settings(artifacts, verify_checksums=False, client_error_burst=2, client_error_rate=0.01,
                             overload_refusal_delay=0)
    app = create_app(settings)
    good = {"points": query.points.tolist(), "k": 3}
    ok = TestClient(app, client=("10.0.0.2", 5000))  # the lifespan runs once, in ``bad``'s block
    with TestClient(app, client=("10.0.0.1", 5000)) as bad:
        answers = [bad.post("/suggest", content=b"{not json", headers={"content-type": "application/json"})
                   for _ in range(3)]
        codes = [a.json()["error"]["code"] for a in answers]
        assert codes == ["invalid_json", "invalid_json", "too_many_errors"], "the third was not parsed"
        refused = bad.post("/suggest", json=good)
        assert refused.status_code == 429 and refused.json()["error"]["code"] == "too_many_errors"
        assert bad.get("/healthz").status_code == 200
        assert ok.post("/suggest", json=good).status_code == 200
        metrics = ok.get("/metrics").text
    assert 'complementme_overload_rejections_total{reason="too_many_errors"} 2.0' in metrics
