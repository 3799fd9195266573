"""Catalog reads: ``GET /parts``, ``/parts/{id}``, ``/parts/{id}/mesh``, ``/parts/{id}/points``.

Part ids contain a slash ("chair-0007/2"), so routes take them with the ``path`` converter and
use them verbatim: ``/parts/chair-0007/2/mesh``. A client may also percent-encode the slash
(``chair-0007%2F2``), which decodes to the same id. The mesh and points routes are declared
before the record route so that their suffixes are not swallowed into the id.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
import trimesh
from fastapi import APIRouter, Path, Query
from starlette.responses import Response

from service.api.deps import ServedDep, SettingsDep
from service.api.render import render_part
from service.api.responses import OrjsonResponse
from service.api.schemas import CategoryOut, ErrorResponse, PartOut, PartPointsOut, PartsPage
from service.errors import InputError
from service.geometry.inputs import points_to_base64

router = APIRouter(tags=["parts"])

PartId = Annotated[str, Path(description="Catalog part id; its slash is kept (or sent as %2F).",
                             examples=["chair-0007/2"])]

MESH_MEDIA_TYPES = {"glb": "model/gltf-binary", "obj": "model/obj", "ply": "application/x-ply"}
_NOT_FOUND: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorResponse, "description": "Unknown part id."}}


@router.get("/parts", response_model=PartsPage, summary="List catalog parts, paged",
            responses={404: {"model": ErrorResponse, "description": "No part comes from shape_id."},
                       422: {"model": ErrorResponse, "description": "Unknown category or bad paging."}})
def list_parts(
    served: ServedDep, settings: SettingsDep,
    category: str | None = Query(None, description="Only parts of this category.", examples=["chair"]),
    shape_id: str | None = Query(None, description="Only parts of this source shape.",
                                 examples=["chair-0007"]),
    q: str | None = Query(None, max_length=100, examples=["chair-0007/"], description=(
        "Only parts whose id or name (an added part's) contains this text (case-insensitive): "
        "the page's part search. Labels are not searched: the service never reads them.")),
    # Bounded so that the page can echo it: JSON numbers past 64 bits answered 500 (orjson).
    offset: int = Query(0, ge=0, le=2**63 - 1, description="Parts to skip.", examples=[0]),
    limit: int = Query(50, ge=1, le=2**63 - 1, examples=[50],
                       description="Parts per page (at most COMPLEMENTME_MAX_PAGE_SIZE)."),
) -> OrjsonResponse:
    if limit > settings.max_page_size:
        raise InputError("limit_out_of_range",
                         f"limit must be at most {settings.max_page_size}, found {limit}")
    cat = served.catalog  # one snapshot for the whole answer
    mask = np.ones(len(cat), dtype=bool)
    if category is not None:
        mask &= cat.category_of == cat.category_codes([category])[0]
    if shape_id is not None:
        mask &= cat.shape_of == cat.shape_code(shape_id)
    rows = np.flatnonzero(mask)
    if q and q.strip():
        rows = rows[[_matches(cat.records[i], q.strip().lower()) for i in rows.tolist()]]
    page = rows[offset:offset + limit].tolist()
    return OrjsonResponse({"total": len(rows), "offset": offset, "limit": limit,
                           "items": [render_part(cat, i) for i in page]})


# The part id and an added part's name only: labels of the data are for measuring, and the
# service never reads them (not even to find parts).
_SEARCHED_FIELDS = ("part_id", "name")


def _matches(record: dict[str, Any], text: str) -> bool:
    """Whether a part's id or name contains ``text`` (lower case)."""
    return any(text in str(record.get(key) or "").lower() for key in _SEARCHED_FIELDS)


@router.get("/categories", response_model=list[CategoryOut], summary="Categories in the catalog",
            responses={200: {"content": {"application/json": {"example": [
                {"name": "airplane", "parts": 771}, {"name": "chair", "parts": 889}]}}}})
def list_categories(served: ServedDep) -> OrjsonResponse:
    cat = served.catalog
    counts = np.bincount(cat.category_of, minlength=len(cat.categories))
    return OrjsonResponse([{"name": n, "parts": int(c)} for n, c in zip(cat.categories, counts, strict=True)])


@router.get("/parts/{part_id:path}/mesh", summary="A part's mesh (GLB, OBJ or PLY), centred",
            response_class=Response, responses={
    **_NOT_FOUND,
    200: {"content": {"model/gltf-binary": {"example": "(binary glTF 2.0)"},
                      "model/obj": {"example": "v 0.04 -0.46 0.0\nv -0.04 -0.46 0.0\n...\nf 1 2 3\n"},
                      "application/x-ply": {"example": "(binary little-endian PLY)"}},
          "description": "The mesh, centred at its bounding-box centre, in canonical units. "
                         "Place it at a suggestion's translation (times the frame's scale and rotation)."}})
def get_part_mesh(
    part_id: PartId, served: ServedDep,
    format: Literal["glb", "obj", "ply"] = Query("glb", description="Mesh file format.", examples=["obj"]),
) -> Response:
    cat = served.catalog
    vertices, faces = cat.mesh(cat.lookup(part_id))
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    data = mesh.export(file_type=format)
    body = data.encode("utf-8") if isinstance(data, str) else bytes(data)
    filename = part_id.replace("/", "_") + "." + format
    return Response(body, media_type=MESH_MEDIA_TYPES[format],
                    headers={"Content-Disposition": f'inline; filename="{filename}"'})


@router.get("/parts/{part_id:path}/points", response_model=PartPointsOut, responses=_NOT_FOUND,
            summary="A part's point samples, centred")
def get_part_points(
    part_id: PartId, served: ServedDep,
    encoding: Literal["json", "base64"] = Query("json", description=(
        "Points as a JSON list or base64 float32."), examples=["base64"]),
) -> OrjsonResponse:
    cat = served.catalog
    pts = cat.part_points(cat.lookup(part_id))
    body: dict[str, Any] = {"part_id": part_id, "n_points": len(pts)}
    if encoding == "base64":
        body["points_base64"] = points_to_base64(pts)
    else:
        body["points"] = pts
    return OrjsonResponse(body)


@router.get("/parts/{part_id:path}", response_model=PartOut, responses=_NOT_FOUND,
            summary="One catalog part's record")
def get_part(part_id: PartId, served: ServedDep) -> OrjsonResponse:
    cat = served.catalog
    return OrjsonResponse(render_part(cat, cat.lookup(part_id)))
