"""Typed dependencies of the routes: the loaded engine, its micro-batcher, the settings, the metrics.

They are ``async`` on purpose: sync dependencies would each cost a threadpool hop per request.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from fastapi import Depends, Request

from service.api.batching import MicroBatcher
from service.api.metrics import Metrics
from service.errors import InputError, NotReadyError
from service.geometry.inputs import MeshUploads
from service.settings import Settings
from service.suggest.engine import SuggestionEngine, SuggestOptions, SuggestResult

# The micro-batcher of suggestion queries: (points, options) in, SuggestResult out.
SuggestBatcher = MicroBatcher[tuple[np.ndarray, SuggestOptions], SuggestResult]


async def get_engine(request: Request) -> SuggestionEngine:
    engine = getattr(request.app.state, "engine", None)
    if engine is None:
        raise NotReadyError("not_ready", "the artifacts are not loaded yet")
    return engine


async def get_batcher(request: Request) -> SuggestBatcher:
    batcher = getattr(request.app.state, "batcher", None)
    if batcher is None:
        raise NotReadyError("not_ready", "the artifacts are not loaded yet")
    return batcher


async def get_app_settings(request: Request) -> Settings:
    return request.app.state.settings


async def get_metrics(request: Request) -> Metrics:
    return request.app.state.metrics


async def get_uploads(request: Request) -> MeshUploads:
    return request.app.state.uploads


async def unique_form_fields(request: Request) -> None:
    """Refuse a multipart form that repeats a field: which copy counts would be a guess.

    FastAPI's ``File``/``Form`` parameters silently take the last copy; the form is parsed (and
    cached by Starlette) before dependencies run, so this costs a pass over its field names.
    """
    form = await request.form()
    seen: set[str] = set()
    for key, _ in form.multi_items():
        if key in seen:
            raise InputError("duplicate_field", f"form field {key!r} is given more than once")
        seen.add(key)


BatcherDep = Annotated[SuggestBatcher, Depends(get_batcher)]
EngineDep = Annotated[SuggestionEngine, Depends(get_engine)]
SettingsDep = Annotated[Settings, Depends(get_app_settings)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
UploadsDep = Annotated[MeshUploads, Depends(get_uploads)]
