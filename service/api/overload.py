"""Bounded work under load: a gate on inference requests, and a deadline on every request.

Latency must not grow without bound when more requests arrive than the CPU can serve. Every
request that runs inference (each POST and DELETE) passes a gate: at most ``max_inflight`` run at
once and at most ``max_queue`` wait for a slot; past that the service answers 503
``overloaded`` with a ``Retry-After`` estimated from recent latencies. Reads (GET) are not gated.

A request takes its place in the gate only once its body is in (when the app receives the body's
last chunk; a request without a body, and every DELETE, at once): a client that sends its body
slowly holds no slot and keeps no other request waiting (it holds only its body's reservation,
below; the body's own limits bound it: ``body_read_timeout`` without a byte, 408; the deadline
below, 408 while still reading). A
request that finds the gate full when it arrives is refused at once, before a byte of its body
is read or parsed, so that shedding under overload costs next to nothing.

Bodies being received are bounded too, by their bytes: ``max_receiving_bytes`` a process. A
gated request with a body reserves what its body can bring (its Content-Length, or its path's
limit when chunked: ``service.api.middleware.body_bound``) from its arrival until the body is in
(or the request ends); one that finds the reservation over the budget is refused 503 at once,
before a byte is read, like a full gate. Without it, only the proxy's connection limit bounded
how many bodies were held in memory (a JSON body whole, an upload's file part up to
``upload_memory_bytes``, then on disk) while they arrived: HAProxy's ``maxconn`` of 4096 times
8 MB. A body larger than the whole budget is let in when no other is being received, so every
body within the limits can be sent.

One client (its address, as for the error budget below) may hold at most
``max_receiving_bytes_per_client`` of it: a client that opens many slow uploads (each chunked one
reserves its whole limit, 32 MB) would otherwise hold the whole budget, and every other client's
bodies would be refused until its deadlines cut them. Past its share a client's new body is
refused 429 ``too_many_bodies`` (not charged to its error budget), before a byte is read; a
single body larger than the share is let in when the client has none on its way.

Catalog writes (``POST /parts``, ``DELETE /parts/...``) have a gate of their own
(``max_inflight_writes``): they wait for each other on the database, and must not take the slots
of suggestion queries while they do. ``POST /suggest`` has one too (``max_inflight_suggest``,
many slots): its requests mostly wait in the micro-batcher's queue (``service.api.batching``), whose
workers bound the CPU they use, and a batch can only grow as large as the requests let in.

Every request also has a deadline (``request_timeout``, queueing included). A request still
reading its body at its deadline gets 408 ``body_timeout``, one still waiting for a slot 503;
one running gets 504 ``deadline_exceeded`` at once, and its late answer is dropped. The work it
started is not interrupted (the micro-batcher stops a request's queries between its chunks and
before each one's contact refinement; see ``service.api.batching``): ONNX Runtime and FAISS cannot
stop halfway, and asyncio's cancellation does not reach a worker thread (it
only abandons it). So the request runs to its end and keeps its slot until then: the gate counts
the CPU really in use. A request still running after a second ``request_timeout`` (stuck on
something asynchronous, which a thread never is) is cancelled.

Fairness between clients: a flood of cheap invalid requests must not starve valid clients. A
``/suggest`` whose options fail its checks is answered 422 from the event loop in well under a
millisecond, so two clients sending one after another at full speed got 1,166 answers a second
and took the event loop (and the interpreter the micro-batcher's thread needs) from everyone
else: the normal clients beside them fell from 195 to 11.8 requests a second (p99 5.8 s).
``ErrorBudgetMiddleware`` gives each client (its address) a budget of error answers: a token
bucket of ``client_error_burst`` answers refilled at ``client_error_rate`` a second, one token
taken by every 4xx it gets (except the 429 below, and a client that left mid-body). A client
whose bucket is empty is refused 429 ``too_many_errors`` with ``Retry-After`` before its body is
read or parsed, after the same ``refusal_delay`` as an overload refusal, so that a client that
retries at once comes back a few times a second per connection. Other clients are not touched.
The address is the one uvicorn puts in the scope: the peer's, or ``X-Forwarded-For``'s from a
proxy in uvicorn's ``--forwarded-allow-ips`` (by default 127.0.0.1 and ::1); behind a proxy that sends
none, every client shares the proxy's budget. The probes (``/healthz``, ``/readyz``,
``/metrics``) are never refused. At most ``MAX_TRACKED_CLIENTS`` clients owing tokens are
remembered; past that, those with a full bucket are forgotten first, then the oldest.

Pure ASGI, like the other middleware: a few function calls per request.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable, Mapping
from typing import Any

import orjson
from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.metrics import Metrics
from service.errors import error_body

GATED_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
# Never refused for a client's errors: orchestrators probe from addresses shared with others.
PROBE_PATHS = frozenset({"/healthz", "/readyz", "/metrics"})
# Clients whose error budget is remembered (an entry is two floats: about 200 bytes with the key).
MAX_TRACKED_CLIENTS = 10_000
# The status of a refusal for too many errors: not itself an error the client is charged for.
TOO_MANY_ERRORS = 429


def client_key(scope: Scope) -> str:
    """The client a request is counted against: its address as uvicorn puts it in the scope (the
    peer's, or ``X-Forwarded-For``'s from a trusted proxy)."""
    client = scope.get("client")
    return client[0] if client else "unknown"


class InferenceGate:
    """At most ``max_inflight`` holders at once, at most ``max_queue`` waiting (asyncio, one loop)."""

    def __init__(self, max_inflight: int, max_queue: int):
        self.max_inflight = max_inflight
        self.max_queue = max_queue
        self.inflight = 0
        self.waiting = 0
        self._waiters: list[asyncio.Future[None]] = []
        # Exponentially weighted mean of gated request durations, for Retry-After.
        self.mean_seconds = 0.05

    def full(self) -> bool:
        """Whether a request arriving now would be refused (every slot taken, the queue full)."""
        return self.inflight >= self.max_inflight and len(self._waiters) >= self.max_queue

    def try_enter(self) -> asyncio.Future[None] | None:
        """Take a slot now (None), or a future that resolves when one is handed over.

        Raises:
            OverflowError: when the queue is full.
        """
        if self.inflight < self.max_inflight and not self._waiters:
            self.inflight += 1
            return None
        if len(self._waiters) >= self.max_queue:
            raise OverflowError
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._waiters.append(fut)
        self.waiting = len(self._waiters)
        return fut

    def abandon(self, fut: asyncio.Future[None]) -> None:
        """A waiter gave up (deadline); if it had just been handed a slot, pass the slot on."""
        if fut in self._waiters:
            self._waiters.remove(fut)
            self.waiting = len(self._waiters)
        elif fut.done() and not fut.cancelled():
            self.leave()

    def leave(self, seconds: float | None = None) -> None:
        """Release a slot: hand it to the oldest waiter, or free it."""
        if seconds is not None:
            self.mean_seconds += 0.1 * (seconds - self.mean_seconds)
        while self._waiters:
            fut = self._waiters.pop(0)
            self.waiting = len(self._waiters)
            if not fut.done():
                fut.set_result(None)  # the slot moves to this waiter; inflight is unchanged
                return
        self.inflight -= 1

    def retry_after(self) -> int:
        """Seconds a refused client should wait: the queue's expected drain time, 1-60."""
        drain = self.mean_seconds * (self.waiting + self.inflight + 1) / self.max_inflight
        return int(min(60, max(1, math.ceil(drain))))


class ReceptionBudget:
    """Bytes of request bodies being received at once: at most ``max_bytes`` in all, and at most
    ``per_client`` for one client key (asyncio, one loop: no locking).

    A body larger than a bound is let in when nothing else holds that bound (the whole budget, or
    the client's share), so every body within the request limits can be sent.
    """

    def __init__(self, max_bytes: int, per_client: int | None = None):
        assert max_bytes > 0, f"max_bytes must be positive, found {max_bytes}"
        self.max_bytes = max_bytes
        self.per_client = per_client  # None: no share per client
        self.held = 0
        self.bodies = 0
        self._by_client: dict[str, int] = {}  # clients holding bytes now (the entry goes at 0)

    def held_by(self, key: str) -> int:
        return self._by_client.get(key, 0)

    def refusal(self, nbytes: int, key: str) -> str | None:
        """Why ``nbytes`` more for ``key`` would pass a bound: ``"client"``, ``"all"``, or None."""
        mine = self._by_client.get(key, 0)
        if self.per_client is not None and mine and mine + nbytes > self.per_client:
            return "client"
        if self.bodies and self.held + nbytes > self.max_bytes:
            return "all"
        return None

    def take(self, nbytes: int, key: str = "") -> bool:
        """Reserve ``nbytes`` for ``key``'s body about to be received; False when that would pass
        a bound (``refusal`` says which)."""
        if self.refusal(nbytes, key) is not None:
            return False
        self.held += nbytes
        self.bodies += 1
        self._by_client[key] = self._by_client.get(key, 0) + nbytes
        return True

    def give(self, nbytes: int, key: str = "") -> None:
        """A body reserved with ``take`` is in (or its request ended)."""
        self.held -= nbytes
        self.bodies -= 1
        left = self._by_client.pop(key, 0) - nbytes
        if left > 0:
            self._by_client[key] = left


class ClientErrorBudget:
    """Token buckets of error answers, one per client key (asyncio, one loop: no locking).

    A client starts with ``burst`` tokens; ``charge`` takes one per error answer, and tokens come
    back at ``rate`` a second, up to ``burst``. Requests that were already running when the bucket
    emptied are charged too, into a debt of at most ``burst``: the server did their work.
    """

    def __init__(self, rate: float, burst: int, max_clients: int = MAX_TRACKED_CLIENTS,
                 clock: Callable[[], float] = time.monotonic):
        assert rate > 0 and burst > 0, f"rate and burst must be positive, found {rate}, {burst}"
        self.rate, self.burst, self.max_clients, self.clock = rate, burst, max_clients, clock
        self._buckets: dict[str, tuple[float, float]] = {}  # key -> (tokens, when counted)

    def __len__(self) -> int:
        return len(self._buckets)

    def _tokens(self, key: str, now: float) -> float:
        tokens, then = self._buckets.get(key, (self.burst, now))
        return min(float(self.burst), tokens + (now - then) * self.rate)

    def wait(self, key: str) -> float:
        """Seconds until ``key`` may send again: 0 when it has a token."""
        if key not in self._buckets:  # the common case: a client without errors
            return 0.0
        tokens = self._tokens(key, self.clock())
        return 0.0 if tokens >= 1 else (1 - tokens) / self.rate

    def charge(self, key: str) -> None:
        """One error answer for ``key``."""
        now = self.clock()
        tokens = max(-float(self.burst), self._tokens(key, now) - 1)
        self._buckets.pop(key, None)  # re-inserted last: the dict's order is the order of last errors
        if len(self._buckets) >= self.max_clients:
            self._forget(now)
        self._buckets[key] = (tokens, now)

    def _forget(self, now: float) -> None:
        """Drop clients whose bucket is full again; if none is, the one whose last error is oldest."""
        full = [k for k in self._buckets if self._tokens(k, now) >= self.burst]
        for key in full:
            del self._buckets[key]
        if not full:
            del self._buckets[next(iter(self._buckets))]


class ErrorBudgetMiddleware:
    """Refuse clients past their budget of error answers with 429 (see the module doc)."""

    def __init__(self, app: ASGIApp, rate: float, burst: int, refusal_delay: float = 0.0,
                 metrics: Metrics | None = None):
        self.app = app
        self.budget = ClientErrorBudget(rate, burst)
        self.refusal_delay = refusal_delay
        self.metrics = metrics or Metrics()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["path"] in PROBE_PATHS:
            await self.app(scope, receive, send)
            return
        key = client_key(scope)
        wait = self.budget.wait(key)
        if wait > 0:  # refused before a byte of the body is read
            self.metrics.rejections.labels("too_many_errors").inc()
            await asyncio.sleep(self.refusal_delay)  # as an overload refusal, and for the same reason
            retry = max(1, math.ceil(wait))
            budget = self.budget
            await _send_error(send, TOO_MANY_ERRORS, "too_many_errors", (
                f"this client ({key}) had more error answers than this server accepts (at most "
                f"{budget.burst} at once, {budget.rate:g} a second: COMPLEMENTME_CLIENT_ERROR_BURST, "
                f"COMPLEMENTME_CLIENT_ERROR_RATE); fix the requests, and retry in {retry} s"),
                [(b"retry-after", str(retry).encode())])
            return
        status = 0

        async def watching_send(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, watching_send)
        finally:
            if (400 <= status < 500 and status != TOO_MANY_ERRORS
                    and not scope.get("state", {}).get("client_gone")):
                self.budget.charge(key)


class OverloadMiddleware:
    """Gate inference requests and enforce the request deadline (see the module doc)."""

    def __init__(self, app: ASGIApp, max_inflight: int, max_queue: int, timeout: float,
                 max_inflight_writes: int = 2, metrics: Metrics | None = None,
                 max_inflight_suggest: int | None = None, refusal_delay: float = 0.0,
                 max_receiving_bytes: int | None = None, max_receiving_bytes_per_client: int | None = None,
                 body_bound: Callable[[Scope], int] | None = None):
        self.app = app
        # None: bodies being received are not bounded here (tests of the gate alone).
        self.reception = (ReceptionBudget(max_receiving_bytes, max_receiving_bytes_per_client)
                          if max_receiving_bytes else None)
        self.body_bound = body_bound or (lambda scope: 0)
        self.refusal_delay = refusal_delay
        self.gate = InferenceGate(max_inflight, max_queue)
        self.write_gate = InferenceGate(max_inflight_writes, max_queue)
        # None: /suggest shares the inference gate.
        self.suggest_gate = (InferenceGate(max_inflight_suggest, max_queue)
                             if max_inflight_suggest is not None else self.gate)
        self.timeout = timeout
        self.metrics = metrics or Metrics()
        self.rejected = self.metrics.rejections
        gates = {id(g): g for g in (self.gate, self.write_gate, self.suggest_gate)}.values()
        self.metrics.watch(self.metrics.inflight_requests, lambda: sum(g.inflight for g in gates))
        self.metrics.watch(self.metrics.queued_requests, lambda: sum(g.waiting for g in gates))
        reception = self.reception
        if reception is not None:
            self.metrics.watch(self.metrics.receiving_bytes, lambda: reception.held)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        deadline = time.monotonic() + self.timeout
        # Queues further in (the micro-batcher) drop work whose answer would be dropped anyway.
        scope.setdefault("state", {})["deadline"] = deadline
        admission: _Admission | None = None
        if scope["method"] in GATED_METHODS:
            gate = self._gate_of(scope)
            if gate.full():  # refused before a byte of the body is read
                self.rejected.labels("queue_full").inc()
                await self._overloaded(gate, send, self._why_full(gate))
                return
            admission = _Admission(gate)
            if scope["method"] == "DELETE" or not _has_body(scope):
                if not await self._enter(gate, deadline, send):
                    return
                admission.running()
            else:
                if not await self._reserve(admission, scope, send):
                    return
                receive = self._admitting(admission, receive)
        answered = started = False

        async def guarded_send(message: Message) -> None:
            nonlocal started
            if answered:  # after a 504, the late answer goes nowhere
                return
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        task = asyncio.ensure_future(self.app(scope, receive, guarded_send))
        if admission is not None:
            task.add_done_callback(admission.leave)
            task.add_done_callback(admission.body_in)
        try:
            done, _ = await asyncio.wait({task}, timeout=max(0.0, deadline - time.monotonic()))
        except asyncio.CancelledError:  # the server is shutting down or the client went away
            task.cancel()
            raise
        if task in done or started:  # an answer under way cannot become a 504: let it finish
            try:
                await task  # re-raises what the app raised
            except Overloaded as exc:  # raised from receive, and no exception handler answered it
                if started:
                    raise
                await _send_error(send, 503, exc.code, str(exc.detail), _header_list(exc.headers))
            return
        task.add_done_callback(_consume)
        answered = True
        if admission is not None and admission.state != "running":
            # Still reading its body, or queued for a slot: no work started, nothing to wait for.
            task.cancel()
            if admission.state == "reading":
                self.rejected.labels("body_deadline").inc()
                await _send_error(send, 408, "body_timeout", f"the request body was not in within "
                                  f"{self.timeout:g} s (COMPLEMENTME_REQUEST_TIMEOUT)")
            else:
                self.rejected.labels("queue_timeout").inc()
                await self._overloaded(admission.gate, send, f"no slot became free within {self.timeout:g} s")
            return
        loop = asyncio.get_running_loop()
        stuck = loop.call_later(self.timeout, task.cancel)
        task.add_done_callback(lambda _: stuck.cancel())
        self.rejected.labels("deadline").inc()
        await _send_error(send, 504, "deadline_exceeded", f"the request took longer than "
                          f"{self.timeout:g} s (COMPLEMENTME_REQUEST_TIMEOUT); its answer is dropped")

    def _admitting(self, admission: _Admission, receive: Receive) -> Receive:
        """``receive`` that takes the request's gate slot when the body's last chunk arrives."""
        async def admitting_receive() -> Message:
            message = await receive()
            if admission.state == "reading" and not (
                    message["type"] == "http.request" and message.get("more_body", False)):
                admission.body_in()
                if message["type"] == "http.request":
                    await self._admit(admission)
                else:  # the client left: the request ends with no work to gate
                    admission.state = "gone"
            return message
        return admitting_receive

    async def _admit(self, admission: _Admission) -> None:
        """Take a slot for a request whose body is in; ``Overloaded`` when the queue is full."""
        gate = admission.gate
        try:
            fut = gate.try_enter()
        except OverflowError:
            self.rejected.labels("queue_full").inc()
            why = self._why_full(gate)
            await asyncio.sleep(self.refusal_delay)  # as in ``_overloaded``
            raise Overloaded(gate, why) from None
        admission.state = "waiting"
        if fut is not None:
            try:
                await asyncio.shield(fut)
            except asyncio.CancelledError:  # the deadline (503, see __call__) or the server stopping
                gate.abandon(fut)
                raise
        admission.running()

    async def _reserve(self, admission: _Admission, scope: Scope, send: Send) -> bool:
        """Reserve the reception budget for the request's body; answer 503 and return False when
        the bodies being received already hold it."""
        reception = self.reception
        if reception is None:
            return True
        nbytes, key = self.body_bound(scope), client_key(scope)
        why = reception.refusal(nbytes, key)
        if why is None:
            reception.take(nbytes, key)
            admission.receiving(reception, nbytes, key)
            return True
        if why == "client":  # this client's own bodies hold its share: the others are not refused
            self.rejected.labels("receiving_client_full").inc()
            await asyncio.sleep(self.refusal_delay)  # as an overload refusal, and for the same reason
            await _send_error(send, TOO_MANY_ERRORS, "too_many_bodies", (
                f"this client ({key}) is still sending request bodies of {reception.held_by(key)} bytes, "
                f"and this one may bring {nbytes} more: one client may have at most "
                f"{reception.per_client} bytes of bodies on their way at once "
                "(COMPLEMENTME_MAX_RECEIVING_BYTES_PER_CLIENT); retry when they are in"),
                [(b"retry-after", b"1")])
            return False
        self.rejected.labels("receiving_full").inc()
        await self._overloaded(admission.gate, send, (
            f"{reception.bodies} request bodies of {reception.held} bytes are being received, and "
            f"this one may bring {nbytes} more: the most this server holds at once is "
            f"{reception.max_bytes} (COMPLEMENTME_MAX_RECEIVING_BYTES)"))
        return False

    @staticmethod
    def _why_full(gate: InferenceGate) -> str:
        return (f"{gate.inflight} requests are running and {gate.waiting} waiting, the most this server "
                "accepts")

    def _gate_of(self, scope: Scope) -> InferenceGate:
        if _is_catalog_write(scope):
            return self.write_gate
        if scope["method"] == "POST" and scope["path"] == "/suggest":
            return self.suggest_gate
        return self.gate

    async def _enter(self, gate: InferenceGate, deadline: float, send: Send) -> bool:
        """Take a gate slot for a request; answer 503 and return False when that is not possible."""
        try:
            fut = gate.try_enter()
        except OverflowError:
            self.rejected.labels("queue_full").inc()
            await self._overloaded(gate, send, self._why_full(gate))
            return False
        if fut is None:
            return True
        try:
            await asyncio.wait_for(asyncio.shield(fut), timeout=max(0.0, deadline - time.monotonic()))
            return True
        except asyncio.TimeoutError:
            gate.abandon(fut)
            self.rejected.labels("queue_timeout").inc()
            await self._overloaded(gate, send, f"no slot became free within {self.timeout:g} s")
            return False
        except asyncio.CancelledError:
            gate.abandon(fut)
            raise

    async def _overloaded(self, gate: InferenceGate, send: Send, why: str) -> None:
        # A refusal costs the event loop about what reading a small request does; clients that
        # retry at once (ignoring Retry-After) would make hundreds a second of them. Held a
        # while, at no CPU cost, each such client retries a few times a second at most.
        await asyncio.sleep(self.refusal_delay)
        retry = gate.retry_after()
        await _send_error(send, 503, "overloaded", f"the service is overloaded ({why}); retry in {retry} s",
                          [(b"retry-after", str(retry).encode())])


class Overloaded(HTTPException):
    """Raised from ``receive`` when a request whose body is in finds the gate's queue full: 503."""

    code = "overloaded"

    def __init__(self, gate: InferenceGate, why: str):
        retry = gate.retry_after()
        super().__init__(503, f"the service is overloaded ({why}); retry in {retry} s",
                         headers={"Retry-After": str(retry)})


class _Admission:
    """A gated request's way through the gate: ``reading`` its body, ``waiting`` for a slot,
    ``running`` (holding one) or ``gone`` (the client left before its body was in)."""

    def __init__(self, gate: InferenceGate):
        self.gate = gate
        self.state = "reading"
        self.entered: float | None = None
        self._reception: ReceptionBudget | None = None
        self._reserved = 0
        self._client = ""

    def receiving(self, reception: ReceptionBudget, nbytes: int, client: str) -> None:
        """The body's bytes are reserved in ``reception`` for ``client`` until ``body_in``."""
        self._reception, self._reserved, self._client = reception, nbytes, client

    def body_in(self, _: object = None) -> None:
        """The body is in, or the request ended without it: give its reservation back (once)."""
        if self._reception is not None:
            self._reception.give(self._reserved, self._client)
            self._reception = None

    def running(self) -> None:
        self.state = "running"
        self.entered = time.monotonic()

    def leave(self, _: object = None) -> None:
        """Give the slot back, if the request took one (the app's task is done)."""
        if self.entered is not None:
            self.gate.leave(time.monotonic() - self.entered)
            self.entered = None


def _has_body(scope: Scope) -> bool:
    """Whether the request announces a body (a non-zero Content-Length, or chunked)."""
    for name, value in scope["headers"]:
        if name == b"content-length":
            return value.strip() not in (b"0", b"")
        if name == b"transfer-encoding":
            return True
    return False


def _header_list(headers: Mapping[str, str] | None) -> list[tuple[bytes, bytes]]:
    return [(k.lower().encode("latin-1"), v.encode("latin-1")) for k, v in (headers or {}).items()]


def _is_catalog_write(scope: Scope) -> bool:
    path = scope["path"]
    return (scope["method"] == "POST" and path == "/parts") or (
        scope["method"] == "DELETE" and path.startswith("/parts/"))


def _consume(task: asyncio.Future[Any]) -> None:
    """Retrieve a cancelled request's outcome so asyncio does not log it as never retrieved."""
    if not task.cancelled():
        task.exception()


async def _send_error(send: Send, status: int, code: str, message: str,
                      headers: list[tuple[bytes, bytes]] | None = None) -> None:
    data = orjson.dumps(error_body(code, message))
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(data)).encode()), *(headers or [])]})
    await send({"type": "http.response.body", "body": data})
