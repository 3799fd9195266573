"""Automatic assembly and export: ``POST /assemble``, ``/assemble/mesh`` and ``/export``.

Handlers are plain ``def`` (threadpool), like the suggestion routes; the work is in
``service.modeling.assembly`` and ``service.modeling.export_mesh``.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends
from starlette.concurrency import run_in_threadpool
from starlette.responses import Response

from service.api.deps import DeadlineDep, ServedDep, SettingsDep, UploadsDep
from service.api.mesh_upload import MESH_UPLOAD_ERRORS, MeshUpload, mesh_upload_dependency, with_raw_bodies
from service.api.render_modeling import render_assemble
from service.api.responses import OrjsonResponse
from service.api.schemas import ErrorResponse
from service.api.schemas_modeling import AssembleOptionsIn, AssembleRequest, AssembleResponse, ExportRequest
from service.api.served import Served
from service.artifacts.catalog import Catalog
from service.errors import InputError
from service.geometry.frames import Frame
from service.modeling.assembly import AssembleOptions, Start
from service.modeling.export_mesh import MEDIA_TYPES, export_assembly
from service.suggest.engine import SuggestionEngine, SuggestOptions
from service.suggest.frame_fit import fit_requested, up_axes_for
from service.suggest.snapshot import CatalogSnapshot

router = APIRouter(tags=["modeling"])

_ERRORS: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorResponse, "description": "The start part (or an excluded shape) is unknown."},
    422: {"model": ErrorResponse, "description": (
        "No start or two of them, bad points, max_parts or branching out of range, unknown "
        "category or style, bad mode weights.")},
}


# The form's examples; the raw-body media types are added (service.api.mesh_upload).
_MESH_EXAMPLE: dict[str, Any] = with_raw_bodies({"requestBody": {"content": {
    "multipart/form-data": {"examples": {
    "obj": {"summary": "A chair seat as OBJ, six parts added",
            "value": {"file": "(seat.obj)", "options": '{"max_parts": 6, "category": "chair"}'}},
    "z-up": {"summary": "A z-up scan in millimetres, answered in its own frame",
             "value": {"file": "(scan.ply)", "options": '{"frame": {"center": [0, 0, 450], '
                       '"radius": 600, "up_axis": "z"}}'}},
}}}}})


def start_of(body: AssembleRequest, engine: SuggestionEngine, catalog: Catalog, max_points: int,
             frame: Frame) -> Start:
    """The request's start in the canonical frame: one part, or placed parts and/or points."""
    if body.part_id is not None:
        return Start(kind="part", part_index=catalog.lookup(body.part_id))
    rows = tuple(catalog.lookup(p.part_id) for p in body.parts or [])
    trans = np.array([p.translation for p in body.parts or []], dtype=np.float64).reshape(-1, 3)
    if len(trans):
        trans = frame.to_canonical(trans).astype(np.float64)
    cloud = body.points is not None or body.points_base64 is not None
    points = engine.canonical(body.to_points(max_points), frame) if cloud else np.zeros((0, 3), np.float32)
    return Start(kind="parts" if rows else "points", points=points, parts=rows, part_translations=trans)


def fitted_frame(served: Served, points: np.ndarray, options: AssembleOptions, framed: bool,
                 snapshot: CatalogSnapshot) -> Frame:
    """The complete object's frame estimated from start points (``service.suggest.frame_fit``)."""
    fit = served.fit_frame(points, SuggestOptions(categories=options.categories, styles=options.styles,
                                                  frame=options.frame),
                           up_axes_for(options.frame if framed else None), snapshot)
    if not fit.hypotheses:
        raise InputError("frame_unfit", "the start points have no extent: no frame can be fitted to them")
    return fit.frame


@router.post("/assemble", response_model=AssembleResponse, responses=_ERRORS,
             summary="Grow a shape automatically from a start part or points")
def post_assemble(body: AssembleRequest, served: ServedDep, settings: SettingsDep) -> OrjsonResponse:
    snapshot = served.snapshot  # one catalog for the start's rows, the assembly and the answer
    options = body.to_options()
    cloud = body.points is not None or body.points_base64 is not None
    fit = fit_requested(body.fit_frame, body.frame is not None, False, settings) and cloud
    if fit:
        options = replace(options, frame=fitted_frame(served, body.to_points(settings.max_points), options,
                                                      body.frame is not None, snapshot))
    start = start_of(body, served.engine, snapshot.catalog, settings.max_points, options.frame)
    result = served.assemble(start, options, snapshot)
    answer = render_assemble(result, snapshot.catalog, served.model_version, options.strategy, fit)
    return OrjsonResponse(answer)


_assemble_upload = mesh_upload_dependency(
    "The start mesh: OBJ, PLY, STL, OFF, GLB or self-contained glTF",
    "Assembly options as JSON (the options of /assemble).", '{"max_parts": 6, "category": "chair"}')


@router.post("/assemble/mesh", response_model=AssembleResponse, summary=(
    "Grow a shape automatically from an uploaded mesh"), openapi_extra=_MESH_EXAMPLE, responses={
    **MESH_UPLOAD_ERRORS,
    422: {"model": ErrorResponse, "description": (
        "Corrupt, empty or zero-area mesh; bad options; a repeated form field or query parameter "
        "(duplicate_field); options in the query string of a form upload (conflicting_fields).")},
})
async def post_assemble_mesh(
    served: ServedDep, settings: SettingsDep, uploads: UploadsDep, deadline: DeadlineDep,
    upload: Annotated[MeshUpload, Depends(_assemble_upload)],
) -> OrjsonResponse:
    """The mesh comes as a multipart form, or as the request body (``service.api.mesh_upload``);
    its surface is sampled area-weighted (seeded), and its area weighs it in the queries."""
    opts = upload.parse_options(AssembleOptionsIn)
    n = max(served.engine.artifacts.query_points, settings.contact_part_samples)
    points, area = await run_in_threadpool(uploads.sample, upload.data, upload.format, n=n, name=upload.name,
                                           deadline=deadline)
    del upload
    snapshot = served.snapshot  # one catalog for the assembly and the answer
    assemble_options = opts.to_options()
    fit = fit_requested(opts.fit_frame, opts.frame is not None, True, settings)
    if fit:
        assemble_options = replace(assemble_options, frame=await run_in_threadpool(
            fitted_frame, served, points, assemble_options, opts.frame is not None, snapshot))
    frame = assemble_options.frame
    start = Start(kind="mesh", points=served.engine.canonical(points, frame), area=area / frame.radius ** 2)
    result = await run_in_threadpool(served.assemble, start, assemble_options, snapshot)
    return OrjsonResponse(render_assemble(result, snapshot.catalog, served.model_version, opts.strategy, fit))


@router.post("/export", response_class=Response, summary="Placed parts as one GLB or OBJ file", responses={
    200: {"content": {"model/gltf-binary": {"example": "(binary glTF 2.0, one node per part)"},
                      "model/obj": {"example": "o 0_chair-0007_0\nv 0.45 -0.03 -0.38\n...\nf 1 2 3\n"}},
          "description": "The assembly, one node (GLB) or object (OBJ) per part, as an attachment."},
    404: {"model": ErrorResponse, "description": "A part id is unknown."},
    422: {"model": ErrorResponse, "description": (
        "No parts, more than COMPLEMENTME_MAX_EXPORT_PARTS, or bad translation, scale or frame.")},
})
def post_export(body: ExportRequest, served: ServedDep, settings: SettingsDep) -> Response:
    frame = body.frame.to_frame() if body.frame else None
    data = export_assembly(served.catalog, body.to_items(), body.format, frame,
                           max_parts=settings.max_export_parts)
    return Response(data, media_type=MEDIA_TYPES[body.format],
                    headers={"Content-Disposition": f'attachment; filename="assembly.{body.format}"'})
