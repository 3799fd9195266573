"""Pure ASGI middleware: request body limits, and metrics plus the model-version header.

Pure ASGI (not ``BaseHTTPMiddleware``) keeps the per-request cost to a few function calls and
lets the body limit act on the raw ``receive`` stream.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

import orjson
from starlette.datastructures import Headers
from starlette.exceptions import HTTPException
from starlette.middleware.cors import CORSMiddleware
from starlette.responses import Response
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.metrics import Metrics
from service.errors import error_body

# Mesh uploads get COMPLEMENTME_MAX_UPLOAD_BYTES; other bodies COMPLEMENTME_MAX_BODY_BYTES.
MESH_UPLOAD_PATHS = ("/suggest/mesh", "/assemble/mesh", "/parts")
# The status metrics count for a request whose client disconnected before its body was in.
CLIENT_GONE = 499


class BodyRefused(HTTPException):
    """Raised from ``receive`` when a body cannot be read; FastAPI's handlers answer it.

    ``code`` is the error body's code (``service.api.errors`` answers with it).
    """

    code = "bad_request"


class BodyTooLarge(BodyRefused):
    """A body past its limit: 413."""

    code = "payload_too_large"

    def __init__(self, limit: int, length: int | None = None):
        size = f"of {length} bytes " if length is not None else ""
        super().__init__(413, f"request body {size}exceeds the limit of {limit} bytes")


class BodyTimeout(BodyRefused):
    """A body that stopped arriving (or is shorter than its Content-Length): 408."""

    code = "body_timeout"

    def __init__(self, seconds: float):
        super().__init__(408, f"no byte of the request body arrived for {seconds:g} s "
                         "(COMPLEMENTME_BODY_READ_TIMEOUT); is the body shorter than its Content-Length?")


class BodyLimitMiddleware:
    """Refuse bodies over the limit (by Content-Length before reading any byte, and while
    reading) and bodies that stop arriving (``body_read_timeout`` seconds without a byte).

    The refusal is raised from the first ``receive`` call rather than answered here, so the
    request is routed first and metrics see its route. Mesh uploads get their own limit. A
    client that disconnects before its body is in is marked in the scope's state
    (``client_gone``), so that metrics do not count the 400 its request ends with.
    """

    def __init__(self, app: ASGIApp, max_body_bytes: int, max_upload_bytes: int,
                 body_read_timeout: float = 10.0):
        self.app = app
        self.max_body_bytes = max_body_bytes
        self.max_upload_bytes = max_upload_bytes
        self.body_read_timeout = body_read_timeout

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS"):
            await self.app(scope, receive, send)
            return
        limit = body_limit(scope, self.max_body_bytes, self.max_upload_bytes)
        declared = _content_length(scope)
        seen = 0
        reading = True  # until the last body chunk: later receives wait for a disconnect, unbounded
        started = False

        async def limited_receive() -> Message:
            nonlocal seen, reading
            if declared is not None and declared > limit:
                raise BodyTooLarge(limit, declared)
            if not reading:
                return await receive()
            try:
                async with asyncio.timeout(self.body_read_timeout):  # no task per call, unlike wait_for
                    message = await receive()
            except TimeoutError:
                raise BodyTimeout(self.body_read_timeout) from None
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    raise BodyTooLarge(limit)
                reading = bool(message.get("more_body", False))
            elif message["type"] == "http.disconnect":
                scope.setdefault("state", {})["client_gone"] = True
                reading = False
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except BodyRefused as exc:  # only when no exception handler answered it
            if started:
                raise
            data = orjson.dumps(error_body(exc.code, str(exc.detail)))
            await send({"type": "http.response.start", "status": exc.status_code,
                        "headers": [(b"content-type", b"application/json"),
                                    (b"content-length", str(len(data)).encode())]})
            await send({"type": "http.response.body", "body": data})


def body_limit(scope: Scope, max_body_bytes: int, max_upload_bytes: int) -> int:
    """The most bytes this request's body may bring: mesh uploads get their own limit."""
    return max_upload_bytes if scope["path"] in MESH_UPLOAD_PATHS else max_body_bytes


def body_bound(scope: Scope, max_body_bytes: int, max_upload_bytes: int) -> int:
    """The bytes a request's body can bring before ``BodyLimitMiddleware`` refuses it: its
    Content-Length, or its path's limit when it declares none (chunked) or more than the limit."""
    limit = body_limit(scope, max_body_bytes, max_upload_bytes)
    declared = _content_length(scope)
    return limit if declared is None or declared < 0 else min(declared, limit)


def _content_length(scope: Scope) -> int | None:
    for name, value in scope["headers"]:
        if name == b"content-length":
            try:
                return int(value)
            except ValueError:
                return None
    return None


class MetricsMiddleware:
    """Count and time every request by route template and status; add ``X-Model-Version``."""

    def __init__(self, app: ASGIApp, metrics: Metrics, model_version: Callable[[], str | None]):
        self.app = app
        self.metrics = metrics
        self.model_version = model_version

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500

        async def send_with_header(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
                version = self.model_version()
                if version is not None:
                    message["headers"] = [*message.get("headers", []),
                                          (b"x-model-version", version.encode("latin-1", "replace"))]
            await send(message)

        try:
            await self.app(scope, receive, send_with_header)
        finally:
            # Route templates, not raw paths: part ids must not explode the label set.
            route = getattr(scope.get("route"), "path", None) or "unmatched"
            if scope.get("state", {}).get("client_gone"):
                # The client left before its body was in: not a bad request of its own (the 400
                # its request ends with goes nowhere). 499, as nginx logs it.
                status = CLIENT_GONE
            self.metrics.observe_request(scope["method"], route, status, time.perf_counter() - start)


class JsonCorsMiddleware(CORSMiddleware):
    """Starlette's CORS middleware with the service's JSON error body for a refused preflight.

    Starlette answers a preflight it refuses with a plain-text 400 ("Disallowed CORS origin");
    every other error of the service is ``{"error": {"code", "message"}}``, so this one is too
    (code ``cors_refused``). Allowed preflights and simple requests are unchanged.
    """

    def preflight_response(self, request_headers: Headers) -> Response:
        response = super().preflight_response(request_headers)
        if response.status_code != 400:
            return response
        message = bytes(response.body).decode("utf-8", "replace")
        dropped = ("content-length", "content-type")
        headers = {k: v for k, v in response.headers.items() if k.lower() not in dropped}
        return Response(orjson.dumps(error_body("cors_refused", message)), status_code=400, headers=headers,
                        media_type="application/json")
