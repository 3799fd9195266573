"""``HEAD`` answers like ``GET`` without the body (RFC 9110, 9.3.2).

FastAPI registers only the methods a route declares, so ``HEAD /healthz`` answered 405, which
breaks load-balancer probes and ``curl -I``. Pure ASGI: the request runs as a ``GET``, its status
and headers (``Content-Length`` included) go out, its body does not.
"""

from __future__ import annotations

from starlette.types import ASGIApp, Message, Receive, Scope, Send


class HeadAsGetMiddleware:
    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "HEAD":
            await self.app(scope, receive, send)
            return

        async def send_without_body(message: Message) -> None:
            if message["type"] == "http.response.body":
                message = {**message, "body": b""}
            await send(message)

        await self.app({**scope, "method": "GET"}, receive, send_without_body)
