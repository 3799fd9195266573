"""The supervisor's connection balancer, in process: real sockets, workers played by the test.

Each "worker" is the worker end of a channel: it says ready (or stopping) and receives the
descriptors of the connections the balancer hands it.
"""

from __future__ import annotations

import socket
from collections.abc import Iterator

import pytest

from service.serve.balancer import READY, STOPPING, TAKEN, ConnectionBalancer, channel_pair


class Rig:
    """A listening socket on loopback, its balancer, and the worker ends of its channels."""

    def __init__(self, max_pending: int = 64) -> None:
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.balancer = ConnectionBalancer(self.listener, max_pending=max_pending)
        self.workers: dict[int, socket.socket] = {}
        self.clients: list[socket.socket] = []

    def add_worker(self, slot: int, ready: bool = True) -> socket.socket:
        ours, theirs = channel_pair()
        theirs.settimeout(5)
        self.balancer.add(slot, ours)
        self.workers[slot] = theirs
        if ready:
            theirs.send(READY)
        return theirs

    def add_ready_workers(self, count: int) -> None:
        """Workers 0 .. count-1, each ready, with the balancer having read that they are."""
        for slot in range(count):
            self.add_worker(slot)
        self.settle()

    def connect(self, count: int) -> None:
        for _ in range(count):
            self.clients.append(socket.create_connection(("127.0.0.1", self.port), timeout=5))

    def settle(self, rounds: int = 20) -> None:
        """Let the balancer read its channels and accept what is waiting."""
        for _ in range(rounds):
            self.balancer.poll(0.01)

    def received(self, slot: int) -> list[socket.socket]:
        """Connections handed to one worker so far (each as a socket of the worker's own)."""
        channel = self.workers[slot]
        channel.setblocking(False)
        got = []
        try:
            while True:
                message, fds, _, _ = socket.recv_fds(channel, 16, 4)
                if not message:
                    break
                assert message == b"c" and len(fds) == 1
                got.append(socket.socket(fileno=fds[0]))
        except BlockingIOError:
            pass
        channel.settimeout(5)
        return got

    def close(self) -> None:
        self.balancer.close()
        self.listener.close()
        for s in [*self.clients, *self.workers.values()]:
            s.close()


@pytest.fixture
def rig() -> Iterator[Rig]:
    r = Rig()
    try:
        yield r
    finally:
        r.close()


def test_connections_are_dealt_to_the_workers_in_turn(rig: Rig) -> None:
    rig.add_ready_workers(3)
    rig.connect(9)
    rig.settle()
    handed = {slot: rig.received(slot) for slot in range(3)}
    assert [len(handed[s]) for s in range(3)] == [3, 3, 3]
    # A handed descriptor is the client's connection itself: bytes flow both ways.
    server_side = handed[0][0]
    peers = {c.getsockname(): c for c in rig.clients}
    client = peers[server_side.getpeername()]
    client.sendall(b"ping")
    assert server_side.recv(4) == b"ping"
    server_side.sendall(b"pong")
    assert client.recv(4) == b"pong"


def test_nothing_is_accepted_until_a_worker_is_ready(rig: Rig) -> None:
    rig.add_worker(0, ready=False)
    rig.connect(2)
    rig.settle()
    assert rig.received(0) == []  # the connections wait in the listen backlog
    rig.workers[0].send(READY)
    rig.settle()
    assert len(rig.received(0)) == 2


def test_a_stopping_worker_gets_no_more_connections(rig: Rig) -> None:
    rig.add_ready_workers(2)
    rig.workers[1].send(STOPPING)
    rig.connect(4)
    rig.settle()
    assert len(rig.received(0)) == 4
    assert rig.received(1) == []


def test_a_worker_that_exits_is_dropped_and_the_others_take_its_share(rig: Rig) -> None:
    rig.add_ready_workers(2)
    rig.workers[1].close()  # the worker process died: its end of the channel closed
    rig.settle()
    rig.connect(4)
    rig.settle()
    assert len(rig.received(0)) == 4


def test_a_replacement_worker_takes_its_turn_again(rig: Rig) -> None:
    rig.add_ready_workers(2)
    rig.workers[1].close()
    rig.settle()
    rig.add_worker(1)  # the supervisor started another process in the slot
    rig.connect(4)
    rig.settle()
    assert [len(rig.received(0)), len(rig.received(1))] == [2, 2]


def test_after_stop_accepting_connections_wait_even_for_a_ready_worker(rig: Rig) -> None:
    rig.add_worker(0)
    rig.settle()
    rig.balancer.stop_accepting()
    rig.workers[0].send(READY)  # a late message must not start accepting again
    rig.connect(1)
    rig.settle()
    assert rig.received(0) == []


def test_a_worker_that_does_not_take_its_connections_is_skipped() -> None:
    rig = Rig(max_pending=2)
    try:
        rig.add_ready_workers(2)
        rig.connect(2)
        rig.settle()
        assert [len(rig.received(0)), len(rig.received(1))] == [1, 1]
        rig.workers[0].send(TAKEN)  # worker 0 takes its connection; worker 1 is stuck
        rig.connect(3)
        rig.settle()
        # Worker 1 gets one more (its second pending), then only worker 0 is dealt to.
        assert [len(rig.received(0)), len(rig.received(1))] == [2, 1]
        # Both past the limit now: the next connection waits in the backlog, it is not dropped ...
        rig.connect(1)
        rig.settle()
        assert [len(rig.received(0)), len(rig.received(1))] == [0, 0]
        # ... and is handed out once a worker catches up.
        rig.workers[1].send(TAKEN)
        rig.settle()
        assert [len(rig.received(0)), len(rig.received(1))] == [0, 1]
    finally:
        rig.close()
