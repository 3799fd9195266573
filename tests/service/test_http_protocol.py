"""Requests that uvicorn's HTTP parser refuses get the JSON error body (issue 16, finding 10).

A real uvicorn server with the protocol ``complementme serve`` uses (``HTTP_PROTOCOL``), in a
thread of the test on a loopback port, behind a trivial app: a parser error never reaches the
app, so the app does not matter here.
"""

from __future__ import annotations

import socket
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager

import orjson
import pytest
from starlette.types import Receive, Scope, Send

from service.serve.cli import HTTP_PROTOCOL


async def _hello(scope: Scope, receive: Receive, send: Send) -> None:
    assert scope["type"] == "http"
    await send({"type": "http.response.start", "status": 200,
                "headers": [(b"content-type", b"text/plain"), (b"content-length", b"5")]})
    await send({"type": "http.response.body", "body": b"hello"})


@pytest.fixture(scope="module")
def port(serve_in_thread: Callable[..., AbstractContextManager[int]]) -> Iterator[int]:
    with serve_in_thread(_hello, start_timeout=60, http=HTTP_PROTOCOL, log_level="error",
                         lifespan="off") as port:
        yield port


def _exchange(port: int, raw: bytes) -> tuple[int, dict[str, str], bytes]:
    """Send ``raw``, read until the server closes; status, headers and body."""
    with socket.create_connection(("127.0.0.1", port), timeout=30) as sock:
        sock.sendall(raw)
        data = b""
        while chunk := sock.recv(65536):
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode("latin-1").split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, _, v in (ln.partition(":") for ln in lines[1:])}
    return int(lines[0].split()[1]), headers, body


@pytest.mark.parametrize("raw", [
    b"GET / HTTP/1.1\r\nHost: x\r\nno colon here\r\n\r\n",
    b"G\x00T / HTTP/1.1\r\nHost: x\r\n\r\n",
    b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03" + b"\x00" * 40,  # a TLS hello on the plain port
    b"POST / HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\n\r\nzz\r\n",
    b"GET / HTTP/1.1\r\nHost: x\r\nContent-Length: 1\r\nContent-Length: 2\r\n\r\nab",
    b"GET /" + b"a" * 100_000 + b" HTTP/1.1\r\nHost: x\r\n\r\n",  # past the parser's URL limit
], ids=["header", "method", "tls", "chunk", "lengths", "long-url"])
def test_a_request_the_parser_refuses_gets_the_json_error_body(port: int, raw: bytes) -> None:
    status, headers, body = _exchange(port, raw)
    assert status == 400 and headers["content-type"] == "application/json", (status, headers, body)
    assert headers["connection"] == "close" and int(headers["content-length"]) == len(body)
    error = orjson.loads(body)["error"]
    assert error["code"] == "bad_http" and "not valid HTTP/1.1" in error["message"], error


def test_a_valid_request_still_reaches_the_app(port: int) -> None:
    status, _, body = _exchange(port, b"GET / HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
    assert (status, body) == (200, b"hello")
