"""Pure ASGI middleware: request body limits, and metrics plus the model-version header.

Pure ASGI (not ``BaseHTTPMiddleware``) keeps the per-request cost to a few function calls and
lets the body limit act on the raw ``receive`` stream.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import orjson
from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.errors import error_body
from service.metrics import Metrics

# Mesh uploads get COMPLEMENTME_MAX_UPLOAD_BYTES; other bodies COMPLEMENTME_MAX_BODY_BYTES.
MESH_UPLOAD_PATHS = ("/suggest/mesh", "/assemble/mesh", "/parts")


class BodyTooLarge(HTTPException):
    """Raised from ``receive`` once a body passes its limit; FastAPI's handlers turn it into 413."""

    def __init__(self, limit: int, length: int | None = None):
        size = f"of {length} bytes " if length is not None else ""
        super().__init__(413, f"request body {size}exceeds the limit of {limit} bytes")


class BodyLimitMiddleware:
    """Refuse bodies over the limit: by Content-Length before reading any byte, and while reading.

    The refusal is raised from the first ``receive`` call rather than answered here, so the
    request is routed first and metrics see its route. Mesh uploads get their own limit.
    """

    def __init__(self, app: ASGIApp, max_body_bytes: int, max_upload_bytes: int):
        self.app = app
        self.max_body_bytes = max_body_bytes
        self.max_upload_bytes = max_upload_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS"):
            await self.app(scope, receive, send)
            return
        limit = self.max_upload_bytes if scope["path"] in MESH_UPLOAD_PATHS else self.max_body_bytes
        declared = _content_length(scope)
        seen = 0
        started = False

        async def limited_receive() -> Message:
            nonlocal seen
            if declared is not None and declared > limit:
                raise BodyTooLarge(limit, declared)
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > limit:
                    raise BodyTooLarge(limit)
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except BodyTooLarge as exc:  # only when no exception handler answered it
            if started:
                raise
            data = orjson.dumps(error_body("payload_too_large", str(exc.detail)))
            await send({"type": "http.response.start", "status": 413,
                        "headers": [(b"content-type", b"application/json"),
                                    (b"content-length", str(len(data)).encode())]})
            await send({"type": "http.response.body", "body": data})


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
            self.metrics.observe_request(scope["method"], route, status, time.perf_counter() - start)
