"""Typed dependencies of the routes: what is served, the settings, the metrics, the uploads, and
the request's batch announcement and deadline.

They are ``async`` on purpose: sync dependencies would each cost a threadpool hop per request.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, FastAPI, Request

from service.api.batching import Ticket
from service.api.metrics import Metrics
from service.api.served import Served
from service.errors import NotReadyError
from service.geometry.inputs import MeshUploads
from service.settings import Settings


def served_of(app: FastAPI) -> Served | None:
    """What ``app`` serves: set by its lifespan once the artifacts are loaded and warm, else None."""
    return getattr(app.state, "served", None)


async def get_served(request: Request) -> Served:
    served = served_of(request.app)
    if served is None:
        raise NotReadyError("not_ready", "the artifacts are not loaded yet")
    return served


async def get_app_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


async def get_uploads(request: Request) -> MeshUploads:
    return request.app.state.uploads


async def get_ticket(request: Request) -> Ticket | None:
    """The announcement ``BatchedRoute`` made for this request to the batcher, if any."""
    return getattr(request.state, "batch_ticket", None)


async def get_deadline(request: Request) -> float | None:
    """The request's deadline (``time.monotonic()``) set by the overload middleware, if any."""
    return getattr(request.state, "deadline", None)


ServedDep = Annotated[Served, Depends(get_served)]
SettingsDep = Annotated[Settings, Depends(get_app_settings)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
UploadsDep = Annotated[MeshUploads, Depends(get_uploads)]
TicketDep = Annotated[Ticket | None, Depends(get_ticket)]
DeadlineDep = Annotated[float | None, Depends(get_deadline)]
