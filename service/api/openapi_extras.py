"""Answers every operation can give, added to the OpenAPI document in one place.

Some answers do not come from a route but from the layers around every route: the overload
gate (503 ``overloaded`` with Retry-After) and the deadline (504) on every POST and DELETE, the
body limit (413) and the parsers (400 for a body that is not JSON or not valid multipart) on
every operation with a body, and 503 ``not_ready`` before the artifacts are loaded. Declaring
them here keeps each route's own ``responses`` about what the route itself decides, and keeps
the document true for every operation, including ones added later.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fastapi import FastAPI

_ERROR = {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorResponse"}}}
# FastAPI declares its own {"detail": [...]} body for a 422; service.api.errors answers every
# validation error with the ErrorResponse envelope instead (code validation_error).
_FASTAPI_422 = "#/components/schemas/HTTPValidationError"
# Probes answer without the artifacts and without a deadline that could matter.
_ALWAYS_UP = ("/healthz", "/metrics")


def _common(path: str, op: dict[str, Any]) -> dict[str, str]:
    """Status -> description of the answers the layers around ``op`` may give."""
    extra: dict[str, str] = {}
    if "requestBody" in op:
        extra["400"] = "The body is not valid JSON, or not a valid multipart form."
        extra["413"] = ("The body is larger than COMPLEMENTME_MAX_BODY_BYTES (COMPLEMENTME_MAX_UPLOAD_BYTES "
                        "for mesh uploads).")
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
