"""Dynamic micro-batching: concurrent suggestion requests run together through one engine call.

Under load, many requests want the same few milliseconds of ONNX Runtime and FAISS. Run each in
its own threadpool thread and they contend for the two cores (and FAISS's OpenMP teams, and
the GIL between the numpy calls); run them together and one ``engine.suggest_batch`` call does
one g run, one h_query run, one FAISS search of all their means (which takes FAISS's BLAS path
past ``faiss_blas_threshold`` queries) and one h_head run.

``MicroBatcher`` owns a queue and ``workers`` threads (one by default) that alone call the
engine. Requests ``submit`` their queries from the event loop and await the answer:

* a worker takes the jobs queued, in order, up to ``max_size`` queries and ``max_cost``
  (estimated milliseconds, ``cost`` of each query) and runs them at once; a job whose queries do
  not all fit gives the batch what fits, and its rest goes to the back of the queue once that
  batch has run, behind the requests that arrived meanwhile: one request of many (or costly)
  queries cannot hold the worker while others wait, they run between its chunks, each waiting
  for one of its chunks at most;
* it waits for more only while a request has *announced* itself (its body is being read or
  parsed, see ``arriving``) and at most ``max_wait`` seconds after the oldest job was queued,
  so a lone request never waits, and no request waits longer than the bound for company;
* while a batch runs, new jobs queue up: the next batch takes them all, so batches grow with
  the load by themselves;
* each query's outcome is its own: the engine returns a ``ServiceError`` per bad query, and
  only that query's request fails with it; an unexpected exception of a batch of several jobs
  runs each job again alone, so that only the job that causes it fails (and is logged);
* a job whose request gave up (cancelled: client gone, or cut at twice its deadline) is
  skipped, and so is one still queued at its deadline (``DeadlineError``, 504), including the
  chunks of a large job not yet run; ``run_batch`` gets each query's deadline too, to stop
  between its own steps;
* ``close`` refuses new jobs (503 ``shutting_down``), runs those already queued and joins the
  workers.

Metrics: queries per engine call and seconds each job waited in the queue.
"""

from __future__ import annotations

import asyncio
import logging
import math
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

# Queries and each one's deadline (time.monotonic(), None: none) -> one answer or error each.
RunBatch = Callable[[list[Q], list[float | None]], Sequence[R | ServiceError]]


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
    """Queries of one request, the future its handler awaits and when it was queued.

    A large job runs in chunks: ``taken`` queries have been handed to batches so far, and
    ``answers`` collects them until all ``len(queries)`` are in (``answered``).
    """

    queries: list[Q]
    future: asyncio.Future[list[R | ServiceError]]
    loop: asyncio.AbstractEventLoop
    deadline: float | None = None   # time.monotonic() past which nobody wants the answer
    costs: list[float] = field(default_factory=list)  # estimated milliseconds per query
    queued: float = field(default_factory=time.monotonic)
    taken: int = 0
    answered: int = 0
    answers: list[Any] = field(default_factory=list)
    finished: bool = False          # resolved (or failed) by a worker: skip its remaining chunks
    waited: bool = False            # its queue wait was recorded (at its first chunk)


@dataclass
class _Chunk(Generic[Q, R]):
    """Queries ``start:stop`` of one job, run in one batch."""

    job: _Job[Q, R]
    start: int
    stop: int


class MicroBatcher(Generic[Q, R]):
    """Queue concurrent queries and run them in batches on a fixed number of worker threads.

    Args:
        run_batch: runs a list of queries, returning one answer or ``ServiceError`` per query in
            order (``SuggestionEngine.suggest_batch``).
        max_size: most queries per call (a larger job runs in chunks).
        max_wait: longest wait, in seconds after the oldest queued job, for announced requests.
        max_cost: most estimated cost (the sum of ``cost`` of its queries) per call; a query
            costlier than this runs alone.
        cost: a query's estimated cost (default: 1 each).
        workers: threads calling ``run_batch``.
        stats: metric callbacks.
    """

    def __init__(self, run_batch: RunBatch[Q, R], *, max_size: int, max_wait: float, workers: int = 1,
                 stats: BatchStats | None = None, name: str = "batcher", max_cost: float = math.inf,
                 cost: Callable[[Q], float] | None = None):
        if max_size < 1 or workers < 1 or max_wait < 0 or not max_cost > 0:
            raise ValueError(f"max_size and workers must be at least 1, max_wait at least 0 and max_cost "
                             f"positive, found {max_size}, {workers}, {max_wait}, {max_cost}")
        self.run_batch = run_batch
        self.max_size = max_size
        self.max_wait = max_wait
        self.max_cost = max_cost
        self.cost = cost or (lambda query: 1.0)
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
        job: _Job[Q, R] = _Job(list(queries), loop.create_future(), loop, deadline,
                               [self.cost(q) for q in queries])
        job.answers = [None] * len(job.queries)
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
            return sum(len(j.queries) - j.taken for j in self._jobs)

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
    def _take(self, batch: list[_Chunk[Q, R]], size: int, cost: float) -> tuple[int, float]:
        """Move queued queries into ``batch`` while they fit (the first always does); lock held.

        A job that does not fit whole gives what fits; the rest goes to the back of the queue
        when this batch has run, behind the requests that arrived meanwhile.
        """
        while self._jobs:
            job = self._jobs[0]
            if job.future.cancelled() or job.finished:
                self._jobs.popleft()
                continue
            stop = job.taken
            while stop < len(job.queries) and size < self.max_size and (
                    cost + job.costs[stop] <= self.max_cost or (not batch and stop == job.taken)):
                cost += job.costs[stop]
                size += 1
                stop += 1
            if stop == job.taken:
                break  # the batch is full
            batch.append(_Chunk(job, job.taken, stop))
            job.taken = stop
            self._jobs.popleft()
            if stop < len(job.queries):
                break  # the rest is queued again once this chunk ran (``_requeue``)
        return size, cost

    def _full(self, size: int, cost: float) -> bool:
        return size >= self.max_size or cost >= self.max_cost

    def _next_batch(self) -> list[_Chunk[Q, R]] | None:
        """Block for the next batch; None when closing and nothing is left."""
        with self._cond:
            batch: list[_Chunk[Q, R]] = []
            size, cost = 0, 0.0
            while not batch:
                while not self._jobs and not self._closing:
                    self._cond.wait()
                if not self._jobs:
                    return None  # closing, drained
                size, cost = self._take(batch, size, cost)
            deadline = batch[0].job.queued + self.max_wait
            while not self._full(size, cost) and self._arriving > 0 and not self._closing:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                self._cond.wait(remaining)
                size, cost = self._take(batch, size, cost)
            return batch

    def _work(self) -> None:
        while True:
            batch = self._next_batch()
            if batch is None:
                return
            self._run(batch)

    def _run(self, batch: list[_Chunk[Q, R]]) -> None:
        try:
            self._run_chunks(batch)
        finally:
            self._requeue(batch)

    def _requeue(self, batch: list[_Chunk[Q, R]]) -> None:
        """Queue again the rest of the batch's unfinished large jobs."""
        with self._cond:
            for chunk in batch:
                job = chunk.job
                if chunk.stop == job.taken < len(job.queries) and not job.finished:
                    self._jobs.append(job)
                    self._cond.notify_all()

    def _run_chunks(self, batch: list[_Chunk[Q, R]]) -> None:
        start = time.monotonic()
        live = []
        for chunk in batch:
            job = chunk.job
            if job.finished or job.future.cancelled():
                continue
            if job.deadline is not None and start > job.deadline:
                self._fail(job, DeadlineError("deadline_exceeded", "the request's deadline passed "
                                              "while it waited for the engine"))
                continue
            live.append(chunk)
            if not job.waited:
                job.waited = True
                self.stats.wait(start - job.queued)
        if not live:
            return
        try:
            self._answer(live, self._call(live))
        except Exception as exc:  # a bug, not bad input (the engine returns those per query)
            if len(live) == 1:
                log.exception("batch of %d queries failed", live[0].stop - live[0].start)
                self._fail(live[0].job, exc)
                return
            # One request's queries may cause it: run each alone, so only that request fails.
            log.warning("batch of %d requests failed (%s: %s); running each alone", len(live),
                        type(exc).__name__, exc)
            for chunk in live:
                try:
                    self._answer([chunk], self._call([chunk]))
                except Exception as alone:
                    log.exception("a request's %d queries failed", chunk.stop - chunk.start)
                    self._fail(chunk.job, alone)

    def _call(self, chunks: list[_Chunk[Q, R]]) -> list[R | ServiceError]:
        """Run the chunks' queries in one engine call: one answer or error per query."""
        queries = [q for c in chunks for q in c.job.queries[c.start:c.stop]]
        deadlines = [c.job.deadline for c in chunks for _ in range(c.start, c.stop)]
        self.stats.batch(len(queries))
        answers = list(self.run_batch(queries, deadlines))
        if len(answers) != len(queries):
            raise RuntimeError(f"run_batch returned {len(answers)} answers for {len(queries)} queries")
        try:
            self.stats.ran(answers, len(queries))
        except Exception:  # metrics must never fail a request
            log.exception("batch metrics failed")
        return answers

    def _answer(self, chunks: list[_Chunk[Q, R]], answers: list[R | ServiceError]) -> None:
        """File each chunk's answers in its job; a job with all its answers is resolved."""
        row = 0
        for c in chunks:
            n = c.stop - c.start
            job = c.job
            with self._cond:
                job.answers[c.start:c.stop] = answers[row:row + n]
                job.answered += n
                complete = job.answered == len(job.queries) and not job.finished
                if complete:
                    job.finished = True
            row += n
            if complete:
                _resolve(job, job.answers)

    def _fail(self, job: _Job[Q, R], exc: BaseException) -> None:
        """Fail a job once; its chunks still queued are skipped."""
        with self._cond:
            if job.finished:
                return
            job.finished = True
        _resolve(job, exc)


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
