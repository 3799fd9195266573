"""One listening socket in the supervisor, which deals the connections out to the workers in turn.

Why not let the kernel spread connections: with a ``SO_REUSEPORT`` socket per worker it picks a
worker by a hash of the client's address, so 32 keep-alive connections landed 21 / 11 or 22 / 10
on two workers as often as 16 / 16. The busier worker's queue then sets the tail: at 650 req/s
p99 was 113 ms with an 11 / 21 split and 70 ms with 16 / 16. (uvicorn's shared socket is worse:
the worker that wakes first takes a whole burst.) Node's cluster module hands connections out
from its primary process for the same reason.

Here the supervisor accepts every connection and passes its file descriptor to the next ready
worker in turn (round robin). Only the accept passes through the supervisor; the requests go
straight to the worker. Round robin rather than "fewest open connections": a client that
reconnects (wrk between two runs, a batch job between two passes) opens its new connections
before the workers have seen the old ones close, and counts that lag by a few milliseconds sent
a whole burst to one worker (23 / 9).

One channel per worker, an ``AF_UNIX`` ``SOCK_SEQPACKET`` pair, one message per event:

* supervisor to worker: ``c`` with one descriptor attached (``SCM_RIGHTS``): a new connection;
* worker to supervisor: ``r`` ready (start-up finished), ``a`` one connection taken, ``s``
  stopping (hand it nothing more). End of file: the worker is gone, or, seen from the worker,
  the supervisor is (the worker then stops).

A worker whose event loop is busy or stuck does not take what it is handed; past
``max_pending`` connections not yet taken it is skipped, and when every worker is, new
connections wait in the listen backlog instead of piling up on a worker that cannot serve them.

``ConnectionBalancer`` is the supervisor's side, ``HandedServer`` (a ``uvicorn.Server``) the
worker's.
"""

from __future__ import annotations

import asyncio
import logging
import selectors
import socket
import sys
from bisect import bisect_left
from contextlib import suppress
from dataclasses import dataclass

import uvicorn
from uvicorn.server import STARTUP_FAILURE

log = logging.getLogger(__name__)

NEW_CONNECTION = b"c"
READY = b"r"
TAKEN = b"a"
STOPPING = b"s"
_ACCEPTS_PER_WAKE = 64  # accepts in a row before the channels are read again
_RECEIVE_BYTES = 64  # one message is one byte; a larger buffer only guards against surprises


def channel_pair() -> tuple[socket.socket, socket.socket]:
    """(supervisor end, worker end) of a new channel; the supervisor's end does not block."""
    ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    ours.setblocking(False)
    return ours, theirs


@dataclass(eq=False)
class _Worker:
    """The supervisor's view of one worker: its channel and whether it takes connections."""

    slot: int
    channel: socket.socket
    ready: bool = False
    pending: int = 0  # connections handed and not yet taken

    def takes(self, max_pending: int) -> bool:
        return self.ready and self.pending < max_pending


class ConnectionBalancer:
    """Accept on ``listener`` and hand the connections to the ready workers in turn.

    Runs in the supervisor's thread: ``poll`` does the work of one wait (call it in a loop).
    The listener is only watched while some worker is ready and has fewer than ``max_pending``
    connections it has not taken yet; until then connections wait in its backlog.
    """

    def __init__(self, listener: socket.socket, max_pending: int = 64):
        if max_pending < 1:
            raise ValueError(f"max_pending must be at least 1, found {max_pending}")
        self.listener = listener
        self.max_pending = max_pending
        listener.setblocking(False)
        self._selector = selectors.DefaultSelector()
        self._workers: dict[int, _Worker] = {}
        self._listening = False
        self._accepting = True  # False once stop_accepting was called
        self._turn = 0  # slot of the worker whose turn is next

    def add(self, slot: int, channel: socket.socket) -> None:
        """Watch the supervisor's end of a new worker's channel (replacing the slot's old one)."""
        self.remove(slot)
        worker = _Worker(slot, channel)
        self._workers[slot] = worker
        self._selector.register(channel, selectors.EVENT_READ, worker)

    def remove(self, slot: int) -> None:
        """Forget a worker (it died or is being replaced) and close its channel."""
        worker = self._workers.pop(slot, None)
        if worker is not None:
            self._selector.unregister(worker.channel)
            worker.channel.close()
            self._update_listening()

    def poll(self, timeout: float) -> None:
        """Wait up to ``timeout`` seconds, then read worker messages and hand out new connections."""
        events = self._selector.select(timeout)
        # Readiness first, so that a worker that just became ready or is stopping counts below.
        for key, _ in events:
            if key.data is not None:
                self._read(key.data)
        if any(key.data is None for key, _ in events):
            self._accept()

    def stop_accepting(self) -> None:
        """Stop watching the listener for good (before it is closed); the channels stay open."""
        self._accepting = False
        self._update_listening()

    def close(self) -> None:
        """Stop accepting and close every channel (workers still running see end of file)."""
        self.stop_accepting()
        for slot in list(self._workers):
            self.remove(slot)
        self._selector.close()

    def _read(self, worker: _Worker) -> None:
        while True:
            try:
                message = worker.channel.recv(_RECEIVE_BYTES)
            except BlockingIOError:
                break
            except OSError:
                message = b""
            if not message:  # the worker exited: the supervisor's loop restarts it
                self.remove(worker.slot)
                return
            if message == TAKEN:
                worker.pending = max(0, worker.pending - 1)
            elif message == READY:
                worker.ready = True
            elif message == STOPPING:
                worker.ready = False
        self._update_listening()

    def _accept(self) -> None:
        for _ in range(_ACCEPTS_PER_WAKE):
            if not self._listening:  # no worker takes more: the rest wait in the backlog
                return
            try:
                conn, _ = self.listener.accept()
            except BlockingIOError:
                return
            except OSError as exc:  # out of descriptors, say: the connection waits in the backlog
                log.warning("supervisor: accept failed: %s", exc)
                return
            with conn:
                if not self._hand(conn):
                    return

    def _hand(self, conn: socket.socket) -> bool:
        """Pass ``conn`` to the next ready worker in turn; a worker that cannot take it is skipped."""
        slots = sorted(self._workers)
        first = bisect_left(slots, self._turn)
        for slot in slots[first:] + slots[:first]:
            worker = self._workers[slot]
            if not worker.takes(self.max_pending):
                continue
            try:
                socket.send_fds(worker.channel, [NEW_CONNECTION], [conn.fileno()])
            except BlockingIOError:  # its channel is full: it is far behind, try the next one
                continue
            except OSError:  # it is gone; its end of file will remove it
                worker.ready = False
                continue
            worker.pending += 1
            self._turn = worker.slot + 1
            if not worker.takes(self.max_pending):
                self._update_listening()
            return True
        log.warning("supervisor: no worker could take a connection from %s; closing it", _peer(conn))
        self._update_listening()
        return False

    def _update_listening(self) -> None:
        """Watch the listener exactly while some worker takes connections (until ``stop_accepting``)."""
        want = self._accepting and any(w.takes(self.max_pending) for w in self._workers.values())
        if want and not self._listening:
            self._selector.register(self.listener, selectors.EVENT_READ, None)
        elif not want and self._listening:
            self._selector.unregister(self.listener)
        self._listening = want


def _peer(conn: socket.socket) -> str:
    try:
        return str(conn.getpeername())
    except OSError:
        return "a client"


class HandedServer(uvicorn.Server):
    """A uvicorn server that listens on no socket: it serves the connections its channel brings.

    Start-up runs the app's lifespan as uvicorn does, then says ``ready``; at shutdown the
    server says ``stopping`` and stops reading. End of file on the channel (the supervisor is
    gone) makes the server stop gracefully.
    """

    def __init__(self, config: uvicorn.Config, channel: socket.socket):
        super().__init__(config)
        self.channel = channel
        self._connecting: set[asyncio.Task[None]] = set()

    async def startup(self, sockets: list[socket.socket] | None = None) -> None:
        await self.lifespan.startup()
        if self.lifespan.should_exit:
            sys.exit(STARTUP_FAILURE)  # as uvicorn's own start-up does
        loop = asyncio.get_running_loop()
        self.channel.setblocking(False)
        loop.add_reader(self.channel.fileno(), self._receive, loop)
        # uvicorn's shutdown calls close() and wait_closed() on its servers: that is all it needs.
        self.servers = [_ChannelListener(self, loop)]  # type: ignore[list-item]
        self.started = True
        self._send(READY)
        log.info("worker: serving connections handed over by the supervisor")

    def _protocol(self) -> asyncio.Protocol:
        protocol_class = self.config.http_protocol_class
        return protocol_class(config=self.config, server_state=self.server_state,  # type: ignore[call-arg]
                              app_state=self.lifespan.state)

    def _receive(self, loop: asyncio.AbstractEventLoop) -> None:
        while True:
            try:
                message, fds, _, _ = socket.recv_fds(self.channel, _RECEIVE_BYTES, 16)
            except BlockingIOError:
                return
            except OSError:
                message, fds = b"", []
            if not message and not fds:
                log.warning("worker: the supervisor is gone; stopping")
                loop.remove_reader(self.channel.fileno())
                self.should_exit = True
                return
            for fd in fds:
                self._send(TAKEN)
                task = loop.create_task(self._serve_connection(loop, socket.socket(fileno=fd)))
                self._connecting.add(task)
                task.add_done_callback(self._connecting.discard)

    async def _serve_connection(self, loop: asyncio.AbstractEventLoop, conn: socket.socket) -> None:
        conn.setblocking(False)
        try:
            await loop.connect_accepted_socket(self._protocol, conn)
        except OSError as exc:  # the client left before the worker took the connection
            log.debug("worker: a handed connection failed: %s", exc)
            conn.close()

    def _send(self, message: bytes) -> None:
        with suppress(OSError):  # the supervisor is gone: nobody to tell
            self.channel.send(message)

    async def connections_set_up(self) -> None:
        """Wait until every handed connection received so far is set up (or failed)."""
        if self._connecting:
            await asyncio.wait(list(self._connecting))

    def stop_receiving(self, loop: asyncio.AbstractEventLoop) -> None:
        """Stop reading the channel and tell the supervisor to hand this worker nothing more."""
        if self.channel.fileno() >= 0:
            loop.remove_reader(self.channel.fileno())
            self._send(STOPPING)


class _ChannelListener:
    """What uvicorn's shutdown closes and waits for in place of a listening server: the channel's
    reader, and the handed connections still being set up."""

    def __init__(self, server: HandedServer, loop: asyncio.AbstractEventLoop):
        self.server, self.loop = server, loop

    def close(self) -> None:
        self.server.stop_receiving(self.loop)

    async def wait_closed(self) -> None:
        await self.server.connections_set_up()

