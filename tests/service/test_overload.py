"""Overload: a bounded gate on inference requests (503 + Retry-After) and a deadline (504)."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import anyio
import httpx
import pytest
from fastapi.testclient import TestClient
from service_testkit import AssemblyQuery, make_settings
from starlette.types import Receive, Scope, Send

from service.api import create_app
from service.overload import InferenceGate, OverloadMiddleware


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
    mw = OverloadMiddleware(_slow_app(1.0, in_thread=True), max_inflight=1, max_queue=4, timeout=0.2)

    async def main() -> None:
        transport = httpx.ASGITransport(app=mw)
        async with httpx.AsyncClient(transport=transport, base_url="http://test") as client:
            t = time.monotonic()
            first, second = await asyncio.gather(client.post("/work"), client.post("/work"))
            assert time.monotonic() - t < 0.9, "the 504 must not wait for the work to finish"
            assert first.status_code == 504 and first.json()["error"]["code"] == "deadline_exceeded"
            # The second waited for the slot, which the still-running thread holds: 503 at its deadline.
            assert second.status_code == 503 and "retry-after" in second.headers
            assert mw.gate.inflight == 1, "the thread still computes: its slot is still taken"
            await asyncio.sleep(1.2)
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


def test_a_full_gate_refuses_before_reading_and_slow_bodies_hold_no_slot() -> None:
    """A request whose body is still arriving holds no slot; one arriving at a full gate is
    refused without a byte of its body read."""
    reads: list[str] = []

    async def app(scope: Scope, receive: Receive, send: Send) -> None:
        while True:
            message = await receive()
            reads.append(scope["path"])
            if not message.get("more_body", False):
                break
        await asyncio.sleep(0.3)
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"done"})

    mw = OverloadMiddleware(app, max_inflight=1, max_queue=0, timeout=10)

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
