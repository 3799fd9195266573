"""A small load generator on raw loopback sockets, for the hostile-load tests and the soak.

asyncio streams with hand-written HTTP/1.1 (keep-alive, Content-Length bodies): a client in the
test process cheap enough that 128 connections leave the CPU to the server under test. Closed
loop: each connection sends its next request as soon as the previous answer is in, so a 503 is
retried at once (the clients of finding 8). A client may send from another loopback address
(``source``, e.g. 127.0.0.2: all of 127.0.0.0/8 is loopback), which the server sees as another
client, as it would hostile clients elsewhere on a network.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import multiprocessing
import socket
import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np


def http_request(method: str, path: str, body: bytes = b"", content_type: str = "application/json",
                 extra: str = "") -> bytes:
    """The bytes of one HTTP/1.1 request to 127.0.0.1."""
    head = (f"{method} {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: {content_type}\r\n"
            f"Content-Length: {len(body)}\r\n{extra}\r\n")
    return head.encode() + body


async def read_response(reader: asyncio.StreamReader) -> tuple[int, bytes, bool]:
    """Status, body and whether the server keeps the connection open."""
    head = await reader.readuntil(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    status = int(lines[0].split()[1])
    headers = {k.strip().lower(): v.strip() for k, _, v in (ln.partition(":") for ln in lines[1:] if ln)}
    body = await reader.readexactly(int(headers.get("content-length", "0")))
    return status, body, headers.get("connection", "").lower() != "close"


@dataclass
class LoadResult:
    """Answers of a closed-loop run: statuses, latencies (seconds) of the 200s, duration."""

    statuses: Counter[int] = field(default_factory=Counter)
    latencies: list[float] = field(default_factory=list)
    seconds: float = 0.0
    errors: int = 0  # connections reset or closed mid-answer

    @property
    def goodput(self) -> float:
        """200 answers per second."""
        return self.statuses[200] / self.seconds if self.seconds else 0.0

    def p(self, q: float) -> float:
        return float(np.percentile(self.latencies, q)) if self.latencies else float("nan")


LOCAL = "127.0.0.1"


async def _connect(port: int, source: str) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    return await asyncio.open_connection("127.0.0.1", port, local_addr=(source, 0))


async def closed_loop(port: int, request: bytes, concurrency: int, seconds: float,
                      source: str = LOCAL) -> LoadResult:
    """``concurrency`` connections from ``source`` sending ``request`` back to back for ``seconds``."""
    out = LoadResult()
    stop = time.monotonic() + seconds

    async def connection() -> None:
        reader = writer = None
        while time.monotonic() < stop:
            try:
                if writer is None:
                    reader, writer = await _connect(port, source)
                assert reader is not None
                t = time.monotonic()
                writer.write(request)
                status, _, keep = await read_response(reader)
                out.statuses[status] += 1
                if status == 200:
                    out.latencies.append(time.monotonic() - t)
                if not keep:
                    writer.close()
                    reader = writer = None
            except (OSError, asyncio.IncompleteReadError):
                out.errors += 1
                if writer is not None:
                    writer.close()
                reader = writer = None
                await asyncio.sleep(0.01)
        if writer is not None:
            writer.close()

    start = time.monotonic()
    await asyncio.gather(*(connection() for _ in range(concurrency)))
    out.seconds = time.monotonic() - start
    return out


async def probe(port: int, request: bytes, every: float, seconds: float) -> list[float]:
    """Latencies of one request sent every ``every`` seconds on its own keep-alive connection."""
    found: list[float] = []
    stop = time.monotonic() + seconds
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        while time.monotonic() < stop:
            t = time.monotonic()
            writer.write(request)
            status, body, _ = await read_response(reader)
            assert status == 200, body[:300]
            found.append(time.monotonic() - t)
            await asyncio.sleep(every)
    finally:
        writer.close()
    return found


def _probe_blocking(port: int, request: bytes, every: float, seconds: float) -> list[float]:
    """``probe`` with blocking sockets, for a process of its own (see ``probe_elsewhere``)."""
    found: list[float] = []
    stop = time.monotonic() + seconds
    with socket.create_connection(("127.0.0.1", port)) as sock:
        rest = b""
        while time.monotonic() < stop:
            t = time.monotonic()
            sock.sendall(request)
            while b"\r\n\r\n" not in rest:
                chunk = sock.recv(65536)
                assert chunk, "the server closed the probe's connection"
                rest += chunk
            head, _, rest = rest.partition(b"\r\n\r\n")
            assert head.split(b" ", 2)[1] == b"200", head[:300]
            length = next(int(line.split(b":", 1)[1]) for line in head.split(b"\r\n")
                          if line.lower().startswith(b"content-length:"))
            while len(rest) < length:
                chunk = sock.recv(65536)
                assert chunk, "the server closed the probe's connection"
                rest += chunk
            rest = rest[length:]
            found.append(time.monotonic() - t)
            time.sleep(every)
    return found


async def probe_elsewhere(port: int, request: bytes, every: float, seconds: float) -> list[float]:
    """``probe`` from a process of its own: the latencies are the server's, not those of the
    load generator's event loop (which, beside 128 connections, delays its own probe's reads by
    tens of milliseconds on a 2-core machine)."""
    ctx = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(1, mp_context=ctx) as pool:
        return await asyncio.get_running_loop().run_in_executor(
            pool, _probe_blocking, port, request, every, seconds)


@contextlib.asynccontextmanager
async def slow_clients(port: int, request: bytes, count: int, byte_every: float = 1.0, source: str = LOCAL):
    """``count`` connections from ``source`` that send ``request``'s head and then its body one
    byte at a time."""
    head, _, body = request.partition(b"\r\n\r\n")
    stop = asyncio.Event()

    async def trickle() -> None:
        _, writer = await _connect(port, source)
        try:
            writer.write(head + b"\r\n\r\n")
            for i in range(len(body)):
                writer.write(body[i:i + 1])
                await writer.drain()
                with contextlib.suppress(asyncio.TimeoutError):
                    await asyncio.wait_for(stop.wait(), byte_every)
                if stop.is_set():
                    return
        except OSError:
            return
        finally:
            writer.close()

    tasks = [asyncio.ensure_future(trickle()) for _ in range(count)]
    await asyncio.sleep(0.3)  # every connection open and its head sent
    try:
        yield
    finally:
        stop.set()
        await asyncio.gather(*tasks, return_exceptions=True)
