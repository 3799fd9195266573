"""Suggestions and placement: ``POST /suggest``, ``/suggest/mesh``, ``/suggest/batch``, ``/place``.

The suggestion handlers are ``async``: they decode the request on the event loop (a mesh or a
whole batch of items in the threadpool), hand the queries to the micro-batcher
(``Served.suggest``, through ``service.api.batching``), whose worker runs them through the
engine together with other requests' queries, and render the answer. ``/place`` is a plain
``def`` run in the threadpool.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool

from service.api.batched_route import BatchedRoute
from service.api.batching import Ticket
from service.api.deps import (
    DeadlineDep,
    MetricsDep,
    ServedDep,
    SettingsDep,
    TicketDep,
    UploadsDep,
)
from service.api.errors import service_error_body, validation_error
from service.api.mesh_upload import MESH_UPLOAD_ERRORS, MeshUpload, mesh_upload_dependency, with_raw_bodies
from service.api.openapi_extras import BODY_TOO_LARGE
from service.api.render import render_place, render_suggest
from service.api.responses import OrjsonResponse
from service.api.schemas import (
    BatchRequest,
    BatchResponse,
    ErrorResponse,
    PlaceRequest,
    PlaceResponse,
    SuggestOptionsIn,
    SuggestRequest,
    SuggestResponse,
)
from service.api.served import Served
from service.errors import InputError, ServiceError
from service.suggest.engine import SuggestionEngine, SuggestOptions
from service.suggest.frame_fit import chosen_frame, fit_queries, fit_requested, up_axes_for
from service.suggest.region import Region

# Stands for any region in a cost estimate (the cost does not depend on where the region is).
_ANY_REGION = Region.ball(np.zeros(3), 1.0)

router = APIRouter(tags=["suggest"])
batched = APIRouter(tags=["suggest"], route_class=BatchedRoute)  # the routes that go through the batcher

# The suggestion routes refuse a request whose estimated CPU time is over the budget before any
# work starts (SuggestionEngine.check_budget), with the body limit's status.
_OVER_BUDGET = ("Or over_budget: the request's estimated CPU time is over "
                "COMPLEMENTME_MAX_REQUEST_COST_MS.")
_POINT_ERRORS: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorResponse, "description": "An excluded or placed part (or shape) is unknown."},
    422: {"model": ErrorResponse, "description": (
        "Empty input, too few or too many points, NaN or infinite values, wrong shape, "
        "non-numeric values, bad base64, k out of range, unknown category, a bad region "
        "(invalid_region).")},
}
_SUGGEST_ERRORS: dict[int | str, dict[str, Any]] = {
    **_POINT_ERRORS, 413: {"model": ErrorResponse, "description": f"{BODY_TOO_LARGE} {_OVER_BUDGET}"}}

# The form's examples; the raw-body media types are added (service.api.mesh_upload).
_MESH_EXAMPLE: dict[str, Any] = with_raw_bodies({"requestBody": {"content": {
    "multipart/form-data": {"examples": {
    "obj": {"summary": "An OBJ file, five suggestions for chairs",
            "value": {"file": "(chair_without_legs.obj)", "options": '{"k": 5, "category": "chair"}'}},
    "z-up": {"summary": "A z-up mesh in millimetres, answered in its own frame",
             "value": {"file": "(scan.ply)", "options": '{"frame": {"center": [0, 0, 450], '
                       '"radius": 600, "up_axis": "z"}}'}},
}}}}})


@batched.post("/suggest", response_model=SuggestResponse, responses=_SUGGEST_ERRORS,
              summary="Suggest complementary parts for a partial assembly given as points")
async def post_suggest(body: SuggestRequest, served: ServedDep, settings: SettingsDep, ticket: TicketDep,
                       deadline: DeadlineDep) -> OrjsonResponse:
    points = body.to_points(settings.max_points)
    options = body.to_options()
    served.check(len(points), options)
    if body.fit_frame:
        options = await fitted(served, points, options, body.frame is not None, ticket, deadline)
    result = await served.suggest(points, options, ticket, deadline)
    return OrjsonResponse(render_suggest(result, served.model_version, bool(body.fit_frame)))


async def fitted(served: Served, points: np.ndarray, options: SuggestOptions, framed: bool,
                 ticket: Ticket | None, deadline: float | None) -> SuggestOptions:
    """The options with the frame estimated from the partial (``service.suggest.frame_fit``): every
    hypothesis one query of the request's batch. ``framed``: the caller gave a frame, whose up
    axis is kept."""
    up_axes = up_axes_for(options.frame if framed else None)
    frames, queries = fit_queries(served.engine, served.settings, points, options, up_axes)
    if not frames:
        raise InputError("frame_unfit", "the points have no extent: no frame can be fitted to them")
    answers = await served.suggest_many(queries, ticket, deadline)
    fit = chosen_frame(served.settings, frames, answers)
    return replace(options, frame=fit.frame)


_suggest_upload = mesh_upload_dependency(
    "The mesh: OBJ, PLY, STL, OFF, GLB or self-contained glTF",
    "Suggestion options as JSON (the options of /suggest).", '{"k": 5, "category": "chair"}')


@batched.post("/suggest/mesh", response_model=SuggestResponse, summary=(
    "Suggest complementary parts for a partial assembly uploaded as a mesh"), openapi_extra=_MESH_EXAMPLE,
    responses={
    **MESH_UPLOAD_ERRORS,
    413: {"model": ErrorResponse, "description": f"{MESH_UPLOAD_ERRORS[413]['description']} {_OVER_BUDGET}"},
    422: {"model": ErrorResponse, "description": (
        "Corrupt, empty or zero-area mesh; bad options; a repeated form field or query parameter "
        "(duplicate_field); options in the query string of a form upload (conflicting_fields).")},
})
async def post_suggest_mesh(
    served: ServedDep, uploads: UploadsDep, settings: SettingsDep, ticket: TicketDep, deadline: DeadlineDep,
    upload: Annotated[MeshUpload, Depends(_suggest_upload)],
) -> OrjsonResponse:
    """The mesh comes as a multipart form, or as the request body (``service.api.mesh_upload``);
    its surface is sampled area-weighted (seeded) to the model's point count (``query_points``:
    enough for every network)."""
    opts = upload.parse_options(SuggestOptionsIn)
    options_out = opts.to_options()
    n_points = served.engine.artifacts.query_points
    served.check(n_points, options_out)
    points, _ = await run_in_threadpool(uploads.sample, upload.data, upload.format, n=n_points,
                                        name=upload.name, deadline=deadline)
    del upload  # the upload's bytes are not needed while the query waits for its batch
    fit = fit_requested(opts.fit_frame, opts.frame is not None, True, settings)
    if fit:
        options_out = await fitted(served, points, options_out, opts.frame is not None, ticket, deadline)
    result = await served.suggest(points, options_out, ticket, deadline)
    return OrjsonResponse(render_suggest(result, served.model_version, fit))


@batched.post("/suggest/batch", response_model=BatchResponse, responses=_SUGGEST_ERRORS,
              summary="Suggest for many partial assemblies at once (batched inference)")
async def post_suggest_batch(body: BatchRequest, served: ServedDep, settings: SettingsDep, ticket: TicketDep,
                             deadline: DeadlineDep) -> OrjsonResponse:
    """Each item is validated on its own: a bad item gets an error entry, the others are answered."""
    items = body.checked_items(settings.limits)
    engine = served.engine
    engine.check_budget(sum(_estimated_cost(engine, raw) for raw in items), len(items))
    results, valid, queries = await run_in_threadpool(_decode_items, items, engine, settings.max_points)
    answers = await served.suggest_many(queries, ticket, deadline) if queries else []
    for i, answer in zip(valid, answers, strict=True):
        if isinstance(answer, ServiceError):
            results[i] = {"index": i, "ok": False, "error": service_error_body(answer)["error"]}
        else:
            results[i] = {"index": i, "ok": True, "result": render_suggest(answer, served.model_version)}
    return OrjsonResponse({"model_version": served.model_version, "results": results})


def _estimated_cost(engine: SuggestionEngine, raw: Any) -> float:
    """A batch item's estimated cost from its raw JSON, before anything is decoded.

    Malformed fields count as their defaults (the item fails validation on its own later), and
    ``k`` is clamped to its range (an item out of range fails alone with ``k_out_of_range``).
    """
    if not isinstance(raw, dict):
        return engine.query_cost(0, SuggestOptions())
    points, b64, k, refine = (raw.get(f) for f in ("points", "points_base64", "k", "refine_contact"))
    n = len(points) if isinstance(points, list) else len(b64) * 3 // 4 // 12 if isinstance(b64, str) else 0
    k = min(max(k, 1), engine.config.max_k) if isinstance(k, int) and not isinstance(k, bool) else None
    refine = refine if isinstance(refine, bool) else None
    region = _ANY_REGION if isinstance(raw.get("region"), dict) else None
    return engine.query_cost(n, SuggestOptions(k=k, refine_contact=refine, region=region))


def _decode_items(items: list[Any], engine: SuggestionEngine, max_points: int
                  ) -> tuple[list[dict[str, Any] | None], list[int], list[tuple[np.ndarray, SuggestOptions]]]:
    """Validate batch items one by one: error entries for the bad, (points, options) for the rest."""
    results: list[dict[str, Any] | None] = [None] * len(items)
    valid, queries = [], []
    for i, raw in enumerate(items):
        try:
            req = SuggestRequest.model_validate(raw)
            if req.fit_frame:
                raise InputError("fit_frame_unsupported", "fit_frame is not available in /suggest/batch "
                                 "(each item would cost a batch of its own); use /suggest or /suggest/mesh")
            points, options = req.to_points(max_points), req.to_options()
            engine.check_query(len(points), options)  # bad options fail here, before the batch
            queries.append((points, options))
            valid.append(i)
        except ValidationError as exc:
            results[i] = {"index": i, "ok": False, "error": validation_error(exc)[1]["error"]}
        except ServiceError as exc:
            results[i] = {"index": i, "ok": False, "error": service_error_body(exc)["error"]}
    return results, valid, queries


@router.post("/place", response_model=PlaceResponse, responses=_POINT_ERRORS,
             summary="Place chosen catalog parts next to a partial assembly")
def post_place(body: PlaceRequest, served: ServedDep, settings: SettingsDep,
               metrics: MetricsDep) -> OrjsonResponse:
    points = body.to_points(settings.max_points)
    result = served.place(points, body.part_ids, body.frame.to_frame() if body.frame else None,
                          refine_contact=body.refine_contact, fit_scale=body.fit_scale)
    metrics.observe_engine(result.timings, 1, [])
    return OrjsonResponse(render_place(result, served.model_version))


router.include_router(batched)  # after its routes: include_router copies them
