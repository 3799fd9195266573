"""Fixtures shared by every test folder."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from typing import Any

import pytest
import uvicorn


@contextmanager
def _serve_in_thread(app: Any, start_timeout: float = 120.0, **config: Any) -> Iterator[int]:
    """``app`` served by a real uvicorn server on a free loopback port, in a daemon thread of this
    process (``config``: more ``uvicorn.Config`` options): the port once it has started; it is
    stopped (and its thread joined) when the block ends. Starting is bounded, not timed."""
    config = {"log_level": "warning", **config}
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=0, **config))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + start_timeout
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "the server did not start"
        time.sleep(0.05)
    try:
        yield server.servers[0].sockets[0].getsockname()[1]
    finally:
        server.should_exit = True
        thread.join(timeout=30)


@pytest.fixture(scope="session", autouse=True)
def _kernels_compiled() -> None:
    """The compiled kernels (contact refinement's search, the OBJ reader, the suggestion order's
    spread), compiled once before any test (about 30 s the first time on a fresh checkout, then
    loaded from numba's cache): so that a server a test starts does not spend its start-up bound
    compiling them."""
    from service.geometry import mesh_kernel
    from service.suggest import contact_kernel, spread_kernel

    contact_kernel.warm()
    mesh_kernel.warm()
    spread_kernel.warm()


@pytest.fixture(scope="session")
def serve_in_thread() -> Callable[..., AbstractContextManager[int]]:
    """``with serve_in_thread(app) as port: ...``"""
    return _serve_in_thread
