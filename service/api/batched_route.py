"""The route class of the suggestion routes: orjson bodies, and an announcement to the batcher.

Two things happen before FastAPI reads and validates a suggestion request's body:

* the request is announced to the micro-batcher (``MicroBatcher.arriving``), so that a worker
  holding a partial batch knows another query is on its way and may wait for it (within
  ``batch_max_wait_ms``); the handler gets the ticket (``service.api.deps.TicketDep``) and passes
  it to ``submit``, which ends the announcement when the query is queued;
* the body is parsed with orjson (1000 points as a JSON list: about 0.1 ms against 0.5 ms for the
  standard library). A body orjson refuses is parsed again by the standard library, which also
  reads the ``NaN`` and ``Infinity`` literals careless clients send (answered 422
  ``non_finite_points``, not 400) and raises the ``JSONDecodeError`` FastAPI turns into 400.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Coroutine
from typing import Any

import orjson
from fastapi import Request, Response
from fastapi.routing import APIRoute

from service.api.deps import served_of


class OrjsonRequest(Request):
    """A request whose ``json()`` parses with orjson (standard library as the fallback)."""

    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            body = await self.body()
            try:
                self._json = orjson.loads(body)
            except orjson.JSONDecodeError:
                self._json = json.loads(body)
        return self._json


class BatchedRoute(APIRoute):
    """Suggestion routes: orjson request bodies and a batcher announcement (see the module doc)."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()

        async def announced(request: Request) -> Response:
            request = OrjsonRequest(request.scope, request.receive)
            served = served_of(request.app)
            if served is None:
                return await handler(request)
            with served.batcher.arriving() as ticket:
                request.state.batch_ticket = ticket
                return await handler(request)

        return announced

