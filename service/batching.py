"""Dynamic micro-batching: concurrent suggestion requests run together through one engine call.

Under load, many requests want the same few milliseconds of ONNX Runtime and FAISS. Run each in
its own threadpool thread and they contend for the two cores (and FAISS's OpenMP teams, and
the GIL between the numpy calls); run them together and one ``engine.suggest_batch`` call does
one g run, one h_query run, one FAISS search of all their means (which takes FAISS's BLAS path
past ``faiss_blas_threshold`` queries) and one h_head run.

``MicroBatcher`` owns a queue and ``workers`` threads (one by default) that alone call the
engine. Requests ``submit`` their queries from the event loop and await the answer:

* a worker takes every job queued (up to ``max_size`` queries) and runs them at once;
* it waits for more only while a request has *announced* itself (its body is being read or
  parsed, see ``arriving``) and at most ``max_wait`` seconds after the oldest job was queued,
  so a lone request never waits, and no request waits longer than the bound for company;
* while a batch runs, new jobs queue up: the next batch takes them all, so batches grow with
  the load by themselves;
* each query's outcome is its own: the engine returns a ``ServiceError`` per bad query, and
  only that query's request fails with it (an unexpected exception fails the jobs of its batch);
* a job whose request gave up (cancelled: client gone, or cut at twice its deadline) is
  skipped, and so is one still queued at its deadline (``DeadlineError``, 504);
* ``close`` refuses new jobs (503 ``shutting_down``), runs those already queued and joins the
  workers.

Metrics: queries per engine call and seconds each job waited in the queue.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

from service.errors import DeadlineError, NotReadyError, ServiceError

log = logging.getLogger(__name__)

Q = TypeVar("Q")  # one query
R = TypeVar("R")  # its answer

RunBatch = Callable[[list[Q]], Sequence[R | ServiceError]]


@dataclass
class BatchStats:
    """Callbacks for the batcher's metrics (no-ops by default)."""

    batch: Callable[[int], None] = lambda size: None            # queries per engine call
    wait: Callable[[float], None] = lambda seconds: None        # a job's seconds in the queue
    ran: Callable[[Any, int], None] = lambda answers, size: None  # answers of one engine call


@dataclass
class Ticket:
    """One announced request (see ``MicroBatcher.arriving``)."""

    done: bool = False


@dataclass
class _Job(Generic[Q, R]):
    """Queries of one request, the future its handler awaits and when it was queued."""

    queries: list[Q]
    future: asyncio.Future[list[R | ServiceError]]
    loop: asyncio.AbstractEventLoop
    deadline: float | None = None   # time.monotonic() past which nobody wants the answer
    queued: float = field(default_factory=time.monotonic)


class MicroBatcher(Generic[Q, R]):
    """Queue concurrent queries and run them in batches on a fixed number of worker threads.

    Args:
        run_batch: runs a list of queries, returning one answer or ``ServiceError`` per query in
            order (``SuggestionEngine.suggest_batch``).
        max_size: most queries per call (a single job larger than this runs alone, whole).
        max_wait: longest wait, in seconds after the oldest queued job, for announced requests.
        workers: threads calling ``run_batch``.
        stats: metric callbacks.
    """

    def __init__(self, run_batch: RunBatch[Q, R], *, max_size: int, max_wait: float, workers: int = 1,
                 stats: BatchStats | None = None, name: str = "batcher"):
        if max_size < 1 or workers < 1 or max_wait < 0:
            raise ValueError(f"max_size and workers must be at least 1 and max_wait at least 0, found "
                             f"{max_size}, {workers}, {max_wait}")
        self.run_batch = run_batch
        self.max_size = max_size
        self.max_wait = max_wait
        self.stats = stats or BatchStats()
        self._jobs: deque[_Job[Q, R]] = deque()
        self._cond = threading.Condition()
        self._arriving = 0
        self._closing = False
        self._threads = [threading.Thread(target=self._work, name=f"{name}-{i}", daemon=True)
                         for i in range(workers)]
        for t in self._threads:
            t.start()

    # ---------------------------------------------------------------- event-loop side
    @contextmanager
    def arriving(self) -> Iterator[Ticket]:
        """Announce a request that will submit soon (while its body is read and parsed).

        A worker holding a partial batch waits (within ``max_wait``) only while some request
        is announced: with nobody on the way, it runs at once. Pass the ticket to ``submit``:
        the announcement ends when the job is queued (or when the block ends, whichever is first).
        """
        ticket = Ticket()
        with self._cond:
            self._arriving += 1
        try:
            yield ticket
        finally:
            with self._cond:
                self._retire(ticket)

    def _retire(self, ticket: Ticket | None) -> None:
        """End an announcement (lock held)."""
        if ticket is not None and not ticket.done:
            ticket.done = True
            self._arriving -= 1
            self._cond.notify_all()

    async def submit(self, query: Q, ticket: Ticket | None = None, deadline: float | None = None) -> R:
        """Run one query in the next batch; its ``ServiceError`` is raised here."""
        answer = (await self.submit_many([query], ticket, deadline))[0]
        if isinstance(answer, ServiceError):
            raise answer
        return answer

    async def submit_many(self, queries: list[Q], ticket: Ticket | None = None,
                          deadline: float | None = None) -> list[R | ServiceError]:
        """Run several queries (one request's) in the same batch; one answer or error each.

        A job still queued at its ``deadline`` (``time.monotonic()``) is not run: it fails with
        ``DeadlineError`` (the overload middleware has answered 504 by then).
        """
        loop = asyncio.get_running_loop()
        job: _Job[Q, R] = _Job(list(queries), loop.create_future(), loop, deadline)
        with self._cond:
            self._retire(ticket)
            if self._closing:
                raise NotReadyError("shutting_down", "the service is shutting down; retry on another "
                                    "instance or after it restarts")
            self._jobs.append(job)
            self._cond.notify_all()
        try:
            return await asyncio.shield(job.future)
        except asyncio.CancelledError:
            job.future.cancel()  # the worker skips it if it has not started it yet
            raise

    @property
    def queued(self) -> int:
        """Queries waiting for a worker."""
        with self._cond:
            return sum(len(j.queries) for j in self._jobs)

    @property
    def closing(self) -> bool:
        """Whether ``close`` was called (new jobs are refused)."""
        return self._closing

    def close(self, timeout: float = 30.0) -> None:
        """Refuse new jobs, let the workers finish the queued ones, and join them."""
        with self._cond:
            self._closing = True
            self._cond.notify_all()
        deadline = time.monotonic() + timeout
        for t in self._threads:
            t.join(max(0.0, deadline - time.monotonic()))
            if t.is_alive():
                log.warning("batch worker %s still running after %.0f s at shutdown", t.name, timeout)

    # ---------------------------------------------------------------- worker side
    def _take(self, batch: list[_Job[Q, R]], size: int) -> int:
        """Move queued jobs into ``batch`` while they fit (the first always does); lock held."""
        while self._jobs:
            job = self._jobs[0]
            if job.future.cancelled():
                self._jobs.popleft()
                continue
            if batch and size + len(job.queries) > self.max_size:
                break
            batch.append(self._jobs.popleft())
            size += len(job.queries)
        return size

    def _next_batch(self) -> list[_Job[Q, R]] | None:
        """Block for the next batch; None when closing and nothing is left."""
        with self._cond:
            batch: list[_Job[Q, R]] = []
            size = 0
            while not batch:
                while not self._jobs and not self._closing:
                    self._cond.wait()
                if not self._jobs:
                    return None  # closing, drained
                size = self._take(batch, size)
            deadline = batch[0].queued + self.max_wait
            while size < self.max_size and self._arriving > 0 and not self._closing:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._cond.wait(remaining)
                size = self._take(batch, size)
            return batch

    def _work(self) -> None:
        while True:
            batch = self._next_batch()
            if batch is None:
                return
            self._run(batch)

    def _run(self, batch: list[_Job[Q, R]]) -> None:
        start = time.monotonic()
        live = []
        for job in batch:
            if job.deadline is not None and start > job.deadline:
                _resolve(job, DeadlineError("deadline_exceeded", "the request's deadline passed while "
                                            "it waited for the engine"))
            elif not job.future.cancelled():
                live.append(job)
        if not live:
            return
        for job in live:
            self.stats.wait(start - job.queued)
        queries = [q for job in live for q in job.queries]
        self.stats.batch(len(queries))
        try:
            answers = list(self.run_batch(queries))
            if len(answers) != len(queries):
                raise RuntimeError(f"run_batch returned {len(answers)} answers for {len(queries)} queries")
        except Exception as exc:  # a bug, not bad input: every request of the batch gets a 500
            log.exception("batch of %d queries failed", len(queries))
            for job in live:
                _resolve(job, exc)
            return
        try:
            self.stats.ran(answers, len(queries))
        except Exception:  # metrics must never fail a request
            log.exception("batch metrics failed")
        start_row = 0
        for job in live:
            n = len(job.queries)
            _resolve(job, answers[start_row:start_row + n])
            start_row += n


def _resolve(job: _Job[Any, Any], outcome: Any) -> None:
    """Hand a job's answers (or exception) to its event loop; dropped if the request gave up."""
    def settle() -> None:
        if job.future.done():
            return
        if isinstance(outcome, BaseException):
            job.future.set_exception(outcome)
        else:
            job.future.set_result(outcome)

    with suppress(RuntimeError):  # the loop is closed: nobody waits any more
        job.loop.call_soon_threadsafe(settle)
