"""Answers every operation can give, added to the OpenAPI document in one place.

Some answers do not come from a route but from the layers around every route: the overload
gate (503 ``overloaded`` with Retry-After) and the deadline (504) on every POST and DELETE, the
body limit (413) and the parsers (400 for a body that is not JSON or not valid multipart; 415 for
a JSON body of another media type or not in UTF-8) on
every operation with a body, and 503 ``not_ready`` before the artifacts are loaded. Declaring
them here keeps each route's own ``responses`` about what the route itself decides, and keeps
the document true for every operation, including ones added later.

The request limits that are settings (``service.settings.Limits``) are checked at run time, not by
the schemas' static bounds; ``add_limits`` writes this server's values into the document as JSON
Schema bounds (``minimum``, ``maxItems``, ...) and as ``info.x-limits``, so a generated client
sees the limits the server it was generated from enforces.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fastapi import FastAPI

from service.settings import Limits

_ERROR = {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorResponse"}}}
# FastAPI declares its own {"detail": [...]} body for a 422; service.api.errors answers every
# validation error with the ErrorResponse envelope instead (code validation_error).
_FASTAPI_422 = "#/components/schemas/HTTPValidationError"
# Probes answer without the artifacts and without a deadline that could matter.
_ALWAYS_UP = ("/healthz", "/metrics")


# The body limit's answer; a route that can refuse a body for a reason of its own (413
# over_budget) declares this text followed by its reason.
BODY_TOO_LARGE = ("The body is larger than COMPLEMENTME_MAX_BODY_BYTES (COMPLEMENTME_MAX_UPLOAD_BYTES for "
                  "mesh uploads).")


def _common(path: str, op: dict[str, Any]) -> dict[str, str]:
    """Status -> description of the answers the layers around ``op`` may give."""
    extra: dict[str, str] = {}
    if "requestBody" in op:
        extra["400"] = "The body is not valid JSON, or not a valid multipart form."
        if "application/json" in op["requestBody"].get("content", {}):
            extra["415"] = ("unsupported_media_type: a Content-Type other than JSON, or a JSON body that is "
                            "not UTF-8.")
        extra["413"] = BODY_TOO_LARGE
    if path not in _ALWAYS_UP:
        extra["503"] = ("not_ready: the artifacts are not loaded yet; overloaded: more requests than "
                        "COMPLEMENTME_MAX_INFLIGHT + COMPLEMENTME_MAX_QUEUE (with Retry-After).")
        extra["504"] = "deadline_exceeded: the request took longer than COMPLEMENTME_REQUEST_TIMEOUT."
    return extra


def add_common_responses(app: FastAPI) -> None:
    """Make ``app.openapi()`` declare the answers of the layers around every route."""
    generate: Callable[[], dict[str, Any]] = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            schema = generate()
            for path, ops in schema.get("paths", {}).items():
                for op in ops.values():
                    responses = op.setdefault("responses", {})
                    for status, description in _common(path, op).items():
                        responses.setdefault(status, {"description": description, "content": _ERROR})
                    for response in responses.values():
                        if response.get("content", {}).get("application/json", {}).get("schema") == {
                                "$ref": _FASTAPI_422}:
                            response["content"] = _ERROR
            schemas = schema.get("components", {}).get("schemas", {})
            for unused in ("HTTPValidationError", "ValidationError"):
                schemas.pop(unused, None)
        return app.openapi_schema or generate()

    app.openapi = openapi  # type: ignore[method-assign]


# Request schemas whose ``points`` field is a point cloud bounded by the point-count limits.
_POINT_REQUESTS = ("SuggestRequest", "PlaceRequest", "AssembleRequest")
_EXCLUSIONS = ("exclude_parts", "exclude_shapes")


def _branch(prop: dict[str, Any], kind: str) -> dict[str, Any] | None:
    """The branch of type ``kind`` of a property (itself, or one arm of its ``anyOf``)."""
    for option in [prop, *prop.get("anyOf", [])]:
        if option.get("type") == kind:
            return option
    return None


def limit_bounds(schema: dict[str, Any], limits: Limits) -> None:
    """Write ``limits`` into an OpenAPI document's request schemas, in place."""
    schema.setdefault("info", {})["x-limits"] = {
        "min_points": limits.min_points, "max_points": limits.max_points, "default_k": limits.default_k,
        "max_k": limits.max_k, "max_exclude": limits.max_exclude, "max_batch_items": limits.max_batch_items}
    models = schema.get("components", {}).get("schemas", {})
    for name in _POINT_REQUESTS:
        props = models.get(name, {}).get("properties", {})
        cloud = _branch(props.get("points", {}), "array")
        if cloud is not None:
            cloud.update(minItems=limits.min_points, maxItems=limits.max_points)
        for field in _EXCLUSIONS:   # the limit is on both lists together; each alone is bounded by it
            ids = _branch(props.get(field, {}), "array")
            if ids is not None:
                ids["maxItems"] = limits.max_exclude
    k = _branch(models.get("SuggestRequest", {}).get("properties", {}).get("k", {}), "integer")
    if k is not None:
        k.update(minimum=1, maximum=limits.max_k, default=limits.default_k)
    items = _branch(models.get("BatchRequest", {}).get("properties", {}).get("items", {}), "array")
    if items is not None:
        items.update(minItems=1, maxItems=limits.max_batch_items)


def add_limits(app: FastAPI, limits: Limits) -> None:
    """Make ``app.openapi()`` carry this server's request limits (``limit_bounds``)."""
    generate: Callable[[], dict[str, Any]] = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            limit_bounds(generate(), limits)
        return app.openapi_schema or generate()

    app.openapi = openapi  # type: ignore[method-assign]
