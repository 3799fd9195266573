"""How a mesh upload arrives: a multipart form, or the file itself as the request body.

``/suggest/mesh`` and ``/assemble/mesh`` take either:

- a ``multipart/form-data`` form with a ``file`` part and optional ``options`` (JSON) and
  ``format`` fields, as a browser's form sends it; or
- the mesh file as the body (``Content-Type: model/obj``, ``model/gltf-binary``, ... or
  ``application/octet-stream`` with ``format``), the ``options`` and ``format`` in the query string.

The raw body skips the multipart parser, the form's spooled file and reading the file back: in
a serving process those cost about 6 ms of a 3.8 MB OBJ's request (docs/performance.md, section
e). The two ways give the same answer for the same file. A form's fields are never mixed with
the query's: a form request that names ``options`` or ``format`` in its query is refused, so no
value is silently ignored.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any, TypeVar

from fastapi import File, Form, Query, Request, UploadFile
from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ValidationError

from service.api.schemas import ErrorResponse
from service.errors import InputError, UnsupportedMediaError
from service.geometry.inputs import mesh_format

# The answers every mesh upload can get from reading the file, whichever route takes it (the
# routes add what they decide themselves; 400 and the JSON body limit are service.api.openapi_extras').
MESH_UPLOAD_ERRORS: dict[int | str, dict[str, Any]] = {
    413: {"model": ErrorResponse, "description": (
        "Upload over COMPLEMENTME_MAX_UPLOAD_BYTES, or a mesh with more vertices, faces, glTF nodes "
        "or nesting than COMPLEMENTME_MAX_MESH_VERTICES, COMPLEMENTME_MAX_MESH_FACES, "
        "COMPLEMENTME_MAX_MESH_NODES or COMPLEMENTME_MAX_MESH_NESTING.")},
    415: {"model": ErrorResponse, "description": "Not OBJ, PLY, STL, OFF, GLB or glTF."},
}

# Media types that name a mesh format; any other raw body needs the ``format`` query parameter.
RAW_MEDIA_FORMATS = {
    "model/obj": "obj",
    "model/gltf-binary": "glb",
    "model/gltf+json": "gltf",
    "model/stl": "stl",
    "application/sla": "stl",
}
# Bodies that are not a mesh file: a form (read as one) or JSON (the points routes' body, sent here
# by mistake); a request with one of these and no form file is told the file is missing.
_FORM_MEDIA = ("multipart/form-data", "application/x-www-form-urlencoded")
_NOT_A_MESH = (*_FORM_MEDIA, "application/json", "")
_QUERY_FIELDS = ("options", "format")
_OBJ_EXAMPLE = "v 0 0 0\nv 0.4 0 0\nv 0 0 0.4\nv 0.4 0 0.4\nf 1 3 2\nf 2 3 4\n"


def with_raw_bodies(openapi_extra: dict[str, Any]) -> dict[str, Any]:
    """A mesh route's ``openapi_extra`` with the raw-body media types added to its request body."""
    content = dict(openapi_extra.get("requestBody", {}).get("content", {}))
    for media in (*RAW_MEDIA_FORMATS, "application/octet-stream"):
        example = _OBJ_EXAMPLE if media == "model/obj" else f"(the {media} file's bytes)"
        content[media] = {"schema": {"type": "string", "format": "binary"}, "example": example}
    return {**openapi_extra, "requestBody": {**openapi_extra.get("requestBody", {}), "content": content}}

OptionsT = TypeVar("OptionsT", bound=BaseModel)


@dataclass(frozen=True)
class MeshUpload:
    """An uploaded mesh's bytes and format, and the request's options as JSON text (or None).

    ``options_loc`` is where the options came from, for validation errors' ``loc``.
    """

    data: bytes
    format: str
    name: str
    options: str | None
    options_loc: tuple[str, ...]

    def parse_options(self, model: type[OptionsT]) -> OptionsT:
        """The options validated as ``model`` (its defaults when none were sent).

        Raises:
            RequestValidationError: the options' errors, located where they were sent.
        """
        try:
            return model.model_validate_json(self.options) if self.options else model()
        except ValidationError as exc:
            raise RequestValidationError([{**e, "loc": (*self.options_loc, *e["loc"])}
                                          for e in exc.errors()]) from None


def _media_type(request: Request) -> str:
    return request.headers.get("content-type", "").split(";")[0].strip().lower()


def mesh_upload_dependency(file_description: str, options_description: str,
                           options_example: str) -> Callable[..., Awaitable[MeshUpload]]:
    """A dependency that reads a mesh upload either way (see the module doc); the descriptions are
    the route's, for its OpenAPI document."""

    async def mesh_upload(
        request: Request,
        file: UploadFile | None = File(None, description=f"{file_description} (a form's file part)."),
        options: str | None = Form(None, description=options_description, examples=[options_example]),
        format: str | None = Form(None, description="Mesh format, when the file name has no extension.",
                                  examples=["obj"]),
        query_options: str | None = Query(None, alias="options", description=(
            f"With the file as the body: {options_description[0].lower()}{options_description[1:]}"),
            examples=[options_example]),
        query_format: str | None = Query(None, alias="format", description=(
            "With the file as the body: its format, when the Content-Type names none "
            "(application/octet-stream)."), examples=["obj"]),
    ) -> MeshUpload:
        media = _media_type(request)
        repeated = [key for key in _QUERY_FIELDS if len(request.query_params.getlist(key)) > 1]
        if repeated:
            raise InputError("duplicate_field", f"query parameter {repeated[0]!r} is given more than once")
        if media == "application/x-www-form-urlencoded":
            # Such a form has no file parts; it is what `curl --data-binary` sends unless told.
            raise UnsupportedMediaError("unsupported_media_type", (
                "an application/x-www-form-urlencoded body cannot carry a mesh: send a "
                "multipart/form-data form with a file part, or the file itself with its media type "
                "(Content-Type: model/obj, model/gltf-binary, ...)"))
        if media in _NOT_A_MESH:
            if media in _FORM_MEDIA:
                await _unique_form_fields(request)
                named = [key for key in _QUERY_FIELDS if key in request.query_params]
                if named:
                    raise InputError("conflicting_fields", (
                        f"a form upload takes its {named[0]!r} as a form field, not in the query string"))
            if file is None:
                raise RequestValidationError([{
                    "type": "missing", "loc": ("body", "file"), "input": None,
                    "msg": ("Field required: send the mesh as a multipart form's file part, or as the "
                            "request body with its media type (model/obj, model/gltf-binary, ...)")}])
            fmt = mesh_format(file.filename, format)
            data = await file.read()
            return MeshUpload(data, fmt, file.filename or "upload", options, ("body", "options"))
        declared = query_format or RAW_MEDIA_FORMATS.get(media)
        if declared is None:
            raise UnsupportedMediaError("unsupported_format", (
                f"a mesh sent as the request body needs its format: a media type that names one "
                f"({', '.join(RAW_MEDIA_FORMATS)}) or the format query parameter "
                f"(?format=obj), not {media!r} alone"))
        fmt = mesh_format(None, declared)
        return MeshUpload(await request.body(), fmt, "upload", query_options, ("query", "options"))

    return mesh_upload


async def _unique_form_fields(request: Request) -> None:
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
