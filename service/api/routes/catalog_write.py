"""Catalog writes: ``POST /parts``, ``DELETE /parts/{id}``, and ``GET /catalog`` (its status).

Writes need the API key (``service.api.auth``) and a data folder. The upload's form is parsed by
the handler itself, after the key was checked, so an unauthenticated client cannot make the
server read a large body first. The heavy work (mesh checks, sampling, both networks, the
database transaction) runs in the threadpool.

An add answers 201 only when the part is stored, and stores nothing when it answers an error.
The request deadline is where this could break: the middleware answers 504 at the deadline
while the worker thread runs on. So ``POST /parts`` keeps its own, earlier deadline
(``write_commit_margin`` before the request's) and a ``CommitWindow`` decides once, under a
lock, between the thread's commit and the handler's 504: a thread that reaches the commit in
time commits and the handler waits for it (the rest, a rename and the snapshot swap, took a
median 27 ms and at most 40 ms over 60 adds, against the margin's 5 s); one that comes later
rolls back.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import threading
import time
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Header, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from starlette.datastructures import UploadFile
from starlette.responses import Response

from service.api.auth import WriterDep
from service.api.deps import DeadlineDep, SettingsDep, served_of
from service.api.mesh_upload import MESH_UPLOAD_ERRORS
from service.api.render import render_stored_part
from service.api.responses import OrjsonResponse
from service.api.routes.parts import PartId
from service.api.schemas import ErrorResponse, FrameIn, PartOut, Replication
from service.artifacts.catalog import part_links
from service.catalog_store.part_prep import prepare_part
from service.catalog_store.store import CommitRefusedError, NewPart, StoredPart
from service.catalog_store.writer import CATEGORY, SHAPE_ID, CatalogWriter
from service.errors import DeadlineError, InputError
from service.geometry.frames import Frame
from service.geometry.inputs import mesh_format
from service.settings import Settings

router = APIRouter(tags=["catalog"])

IdempotencyKey = Annotated[str | None, Header(alias="Idempotency-Key", description=(
    "A key unique to this add (a UUID): a retry with the same key and request answers the part the "
    "first one added instead of adding it again (postgres backend only)."),
    examples=["3f1c2a9e-7b1d-4c55-9d0e-1a2b3c4d5e6f"])]

_AUTH_ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorResponse, "description": "No API key, or a wrong one (with WWW-Authenticate)."},
    403: {"model": ErrorResponse, "description": (
        "Writes are disabled: no API key (writes_disabled) or no data folder (read_only) configured.")},
}


class PartUploadIn(BaseModel):
    """The form fields of ``POST /parts`` besides the file."""

    model_config = ConfigDict(extra="forbid")

    # The patterns are documented here and checked by the catalog writer, which answers 422
    # invalid_category / invalid_shape_id with a message a person can act on (a pattern checked
    # here would answer validation_error quoting the regex).
    category: str = Field(..., max_length=200, json_schema_extra={"pattern": CATEGORY.pattern}, description=(
        "The part's category (a new one is created if needed)."), examples=["chair"])
    shape_id: str | None = Field(
        default=None, max_length=200, json_schema_extra={"pattern": SHAPE_ID.pattern}, description=(
        "Groups parts of one source object (exclude_shapes acts on it); the part's id is "
        "<shape_id>/<n>. Default: a shape of its own, added-<n>."), examples=["my-chair-01"])
    name: str | None = Field(default=None, max_length=200, description="A free-text name.",
                             examples=["oak leg"])
    style: str | None = Field(default=None, max_length=200, description="Fine-grained style.",
                              examples=["windsor"])
    label: str | None = Field(default=None, max_length=200, description="Semantic label (leg, seat...).",
                              examples=["leg"])
    format: str | None = Field(default=None, max_length=8, description=(
        "Mesh format, when the file name has no extension."), examples=["obj"])
    frame: str | None = Field(default=None, max_length=1000, description=(
        "JSON frame of the complete object the part belongs to ({center, radius, up_axis}); the part is "
        "mapped to the canonical frame with it. Default: the mesh is already canonical."),
        examples=['{"center": [0, 0, 450], "radius": 600, "up_axis": "z"}'])

    def to_frame(self) -> Frame:
        if self.frame is None:
            return Frame()
        try:
            value = json.loads(self.frame)
        except json.JSONDecodeError as exc:
            raise InputError("invalid_frame", f"frame is not valid JSON ({exc})") from None
        try:
            return FrameIn.model_validate(value).to_frame()
        except ValidationError as exc:
            raise RequestValidationError([{**e, "loc": ("body", "frame", *e["loc"])}
                                          for e in exc.errors()]) from None


def _upload_schema() -> dict[str, Any]:
    schema = PartUploadIn.model_json_schema()
    props = {"file": {"type": "string", "format": "binary", "description": (
        "The part's mesh: OBJ, PLY, STL, OFF, GLB or self-contained glTF (no external references).")},
        **schema["properties"]}
    return {"type": "object", "properties": props, "required": ["file", "category"],
            "additionalProperties": False}


_UPLOAD_BODY: dict[str, Any] = {"requestBody": {"required": True, "content": {"multipart/form-data": {
    "schema": _upload_schema(),
    "examples": {"leg": {"summary": "A chair leg in the canonical frame",
                         "value": {"file": "(leg.obj)", "category": "chair", "label": "leg"}}},
}}}}


class CatalogStatus(BaseModel):
    model_config = ConfigDict(json_schema_extra={"examples": [{
        "writable": True, "backend": "sqlite", "shipped_parts": 7315, "added_parts": 12, "deleted_parts": 1,
        "parts": 7327, "sequence": 14, "database_sequence": 14, "index_sequence": 14,
        "index_rebuilt_at_start": False, "reembedded_at_start": 0, "left_out": [], "replication": None}]})

    writable: bool = Field(..., description="Whether this server accepts catalog writes at all.")
    backend: Literal["sqlite", "postgres"] | None = Field(..., description=(
        "Where added parts live (COMPLEMENTME_CATALOG_BACKEND); null for a read-only server."))
    shipped_parts: int
    added_parts: int = Field(..., description="Added parts served now.")
    deleted_parts: int | None = Field(..., description=(
        "Deleted parts (null while the database is unreachable)."))
    parts: int = Field(..., description="Parts served now (shipped + added).")
    sequence: int | None = Field(..., description="The last database change the served catalog includes.")
    database_sequence: int | None = Field(..., description="The database's last change.")
    index_sequence: int | None = Field(..., description=(
        "The change the index file in the data folder reflects."))
    index_rebuilt_at_start: bool
    reembedded_at_start: int = Field(..., description="Added parts re-embedded for a new model at start.")
    left_out: list[dict[str, str]] = Field(..., description=(
        "Added parts that could not be served (damaged geometry file, id clash), with the reason."))
    replication: Replication | None = Field(..., description="The postgres backend's replica state.")


async def _read_form(request: Request) -> tuple[UploadFile, PartUploadIn]:
    # Two files allowed here so that a repeated "file" is answered 422 duplicate_field below (with
    # max_files=1 Starlette refused it first with a plain 400).
    form = await request.form(max_files=2, max_fields=16)
    fields: dict[str, str] = {}
    upload: UploadFile | None = None
    for key, value in form.multi_items():
        if key in fields or (key == "file" and upload is not None):
            raise InputError("duplicate_field", f"form field {key!r} is given more than once")
        if isinstance(value, str):
            fields[key] = value
        elif key == "file":
            upload = value
        else:
            raise InputError("unexpected_file", f"form field {key!r} is a file; only 'file' may be one")
    if upload is None:
        raise InputError("missing_file", "send the part's mesh as the multipart form field 'file'")
    try:
        meta = PartUploadIn.model_validate(fields)
    except ValidationError as exc:
        raise RequestValidationError([{**e, "loc": ("body", *e["loc"])} for e in exc.errors()]) from None
    return upload, meta


@router.post("/parts", status_code=201, response_model=PartOut, summary="Add a part to the catalog",
             openapi_extra=_UPLOAD_BODY, responses={
    **_AUTH_ERRORS,
    409: {"model": ErrorResponse, "description": "shape_id belongs to the shipped catalog."},
    **MESH_UPLOAD_ERRORS,
    422: {"model": ErrorResponse, "description": "Missing file or category, bad fields, corrupt or "
          "empty mesh, external references, a part too large for the canonical frame."},
    503: {"model": ErrorResponse, "description": "The catalog database cannot be reached "
          "(database_unavailable, with Retry-After): nothing was stored."},
    507: {"model": ErrorResponse, "description": "The data folder holds COMPLEMENTME_MAX_ADDED_PARTS parts."},
})
async def post_part(request: Request, writer: WriterDep, settings: SettingsDep, deadline: DeadlineDep,
                    idempotency_key: IdempotencyKey = None) -> OrjsonResponse:
    """Upload one part's mesh: it is checked, centred, embedded and searchable by the next request.

    The mesh is in the canonical frame of the complete object it belongs to (unit radius, y up)
    unless `frame` says otherwise; its bounding-box centre becomes its `translation`. With an
    `Idempotency-Key` (postgres backend), a retry of the same request answers the part the first
    one added (header `Idempotent-Replayed: true`) instead of adding it twice.
    """
    upload, meta = await _read_form(request)
    fmt = mesh_format(upload.filename, meta.format)
    frame = meta.to_frame()
    data = await upload.read()
    if deadline is None:
        deadline = time.monotonic() + settings.request_timeout
    window = CommitWindow(deadline - min(settings.write_commit_margin, settings.request_timeout / 2))
    name = upload.filename or "upload"
    task = asyncio.ensure_future(
        run_in_threadpool(_add, writer, settings, data, fmt, name, frame, meta, window, idempotency_key))
    done, _ = await asyncio.wait({task}, timeout=max(0.0, window.close_at - time.monotonic()))
    if task not in done and window.expire():
        task.add_done_callback(_consume)  # the thread rolls back (or never starts its transaction)
        raise _not_stored(settings)
    try:
        stored, replayed = await task  # done, or committing: then its answer is the truth
    except CommitRefusedError:
        raise _not_stored(settings) from None
    headers = {"Location": part_links(stored.part_id)["part"]}
    if replayed:
        headers["Idempotent-Replayed"] = "true"
    return OrjsonResponse(render_stored_part(stored, writer.builder.n_points), status_code=201,
                          headers=headers)


class CommitWindow:
    """Decides once whether an add commits or its request gives up, never both (see module doc)."""

    def __init__(self, close_at: float):
        self.close_at = close_at
        self._lock = threading.Lock()
        self._state: str | None = None  # "commit" or "expired" once decided

    def may_commit(self) -> bool:
        """Asked by the writing thread just before its commit."""
        with self._lock:
            if self._state is None:
                self._state = "commit" if time.monotonic() < self.close_at else "expired"
            return self._state == "commit"

    def expire(self) -> bool:
        """Asked by the handler at ``close_at``: True if the add will not commit."""
        with self._lock:
            if self._state is None:
                self._state = "expired"
            return self._state == "expired"

    @property
    def expired(self) -> bool:
        return self._state == "expired"


def _not_stored(settings: Settings) -> DeadlineError:
    return DeadlineError("deadline_exceeded", "the part could not be stored within the request's deadline "
                         f"({settings.request_timeout:g} s, COMPLEMENTME_REQUEST_TIMEOUT, less "
                         "COMPLEMENTME_WRITE_COMMIT_MARGIN); nothing was stored: send it again")


def _consume(task: asyncio.Future[Any]) -> None:
    if not task.cancelled():
        task.exception()


def _add(writer: CatalogWriter, settings: Settings, data: bytes, fmt: str, name: str, frame: Frame,
         meta: PartUploadIn, window: CommitWindow, key: str | None) -> tuple[StoredPart, bool]:
    """The add in the threadpool: the stored part, and whether an earlier request stored it."""
    if window.expired:  # the handler already answered 504: do not start the work
        raise CommitRefusedError("the request's deadline passed before the add started")

    def prepare() -> NewPart:
        engine = writer.engine
        return prepare_part(data, fmt, name=name, frame=frame, networks=engine.networks,
                            n_points=engine.artifacts.n_points,
                            placement_points=engine.artifacts.placement_points,
                            preview_points=writer.builder.n_points,
                            seed=settings.seed, max_vertices=settings.max_mesh_vertices,
                            max_faces=settings.max_mesh_faces, max_nodes=settings.max_mesh_nodes,
                            max_nesting=settings.max_mesh_nesting, max_extent=settings.max_part_extent,
                            category=meta.category, part_name=meta.name, style=meta.style, label=meta.label,
                            model_version=engine.model_version)

    if key is None:
        return writer.add(prepare(), meta.shape_id, window.may_commit), False
    return writer.add_once(prepare, meta.shape_id, key, _request_sha256(data, fmt, meta), window.may_commit)


def _request_sha256(data: bytes, fmt: str, meta: PartUploadIn) -> str:
    """What makes two adds the same request: the mesh bytes, its format and every form field."""
    fields = json.dumps({"format": fmt, **meta.model_dump()}, sort_keys=True).encode()
    return hashlib.sha256(fields + b"\0" + data).hexdigest()


@router.delete("/parts/{part_id:path}", status_code=204, response_class=Response,
               summary="Remove an added part from the catalog", responses={
    **_AUTH_ERRORS,
    404: {"model": ErrorResponse, "description": "No such part."},
    409: {"model": ErrorResponse, "description": "The part ships with the artifacts (shipped_part)."},
    503: {"model": ErrorResponse, "description": "The catalog database cannot be reached "
          "(database_unavailable, with Retry-After): nothing was deleted."},
})
async def delete_part(part_id: PartId, writer: WriterDep) -> Response:
    """The part stops being suggested at once; shipped parts cannot be deleted (409)."""
    await run_in_threadpool(writer.delete, part_id)
    return Response(status_code=204)


@router.get("/catalog", response_model=CatalogStatus, summary="The catalog's additions and their state")
def get_catalog_status(request: Request) -> OrjsonResponse:
    served = served_of(request.app)
    if served is not None and served.writer is not None:
        return OrjsonResponse(served.writer.status())
    n = len(served.catalog) if served is not None else 0
    return OrjsonResponse({"writable": False, "backend": None, "shipped_parts": n, "added_parts": 0,
                           "deleted_parts": 0, "parts": n, "sequence": None, "database_sequence": None,
                           "index_sequence": None, "index_rebuilt_at_start": False, "reembedded_at_start": 0,
                           "left_out": [], "replication": None})

