"""Every error leaves the API as ``{"error": {"code": ..., "message": ...}}`` with its status.

Handlers cover the engine's ``ServiceError``s, FastAPI's own validation errors (422, or 400 for a
body that is not JSON at all), Starlette's HTTP errors (404 route, 405, 413) and, as a last
resort, anything unexpected (500, logged with its traceback; client input never gets here).
"""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from service.api.responses import OrjsonResponse
from service.errors import ServiceError, error_body

log = logging.getLogger(__name__)

# Validation problems listed in one error body; the rest are counted, not listed.
MAX_DETAILS = 10

_HTTP_CODES = {
    400: "bad_request", 401: "unauthorized", 403: "forbidden", 404: "not_found", 405: "method_not_allowed",
    408: "body_timeout", 413: "payload_too_large",
    415: "unsupported_media_type", 503: "not_ready",
}


def error_response(status: int, code: str, message: str,
                   details: list[dict[str, Any]] | None = None) -> OrjsonResponse:
    return OrjsonResponse(error_body(code, message, details), status_code=status)


def validation_details(errors: list[Any]) -> tuple[str, list[dict[str, Any]]]:
    """A one-line summary and the first ``MAX_DETAILS`` problems (location, message, type)."""
    details = []
    for err in errors[:MAX_DETAILS]:
        loc = [str(p) for p in err.get("loc", ())]
        details.append({"loc": loc, "message": err.get("msg", ""), "type": err.get("type", "")})
    first = details[0] if details else {"loc": [], "message": "invalid request"}
    where = ".".join(first["loc"]) or "request"
    more = f" (and {len(errors) - 1} more problems)" if len(errors) > 1 else ""
    return f"{where}: {first['message']}{more}", details


def validation_error(exc: ValidationError | RequestValidationError, status: int = 422) -> tuple[int, dict]:
    """Status and body for a pydantic or FastAPI validation error."""
    errors = list(exc.errors())
    if any(e.get("type") == "json_invalid" for e in errors):
        ctx = next(e.get("ctx", {}) for e in errors if e.get("type") == "json_invalid")
        return 400, error_body("invalid_json", f"the request body is not valid JSON ({ctx.get('error', '')})")
    message, details = validation_details(errors)
    return status, error_body("validation_error", message, details)


def service_error_body(exc: ServiceError) -> dict[str, Any]:
    return error_body(exc.code, exc.message)


async def _on_service_error(request: Request, exc: Exception) -> OrjsonResponse:
    assert isinstance(exc, ServiceError)
    # Some errors carry headers (WWW-Authenticate on 401, Retry-After on 503).
    return OrjsonResponse(service_error_body(exc), status_code=exc.status,
                          headers=getattr(exc, "headers", None))


async def _on_validation_error(request: Request, exc: Exception) -> OrjsonResponse:
    assert isinstance(exc, RequestValidationError)
    status, body = validation_error(exc)
    return OrjsonResponse(body, status_code=status)


async def _on_http_error(request: Request, exc: Exception) -> OrjsonResponse:
    assert isinstance(exc, StarletteHTTPException)
    # Errors raised from the body's receive (service.api.middleware, service.api.overload,
    # service.api.json_body) carry their own code.
    code = getattr(exc, "code", None) or _HTTP_CODES.get(exc.status_code, "http_error")
    if exc.status_code == 404 and exc.detail == "Not Found":
        message = f"no route {request.method} {request.url.path}"
    else:
        message = str(exc.detail)
    return OrjsonResponse(error_body(code, message), status_code=exc.status_code, headers=exc.headers)


async def _on_unexpected(request: Request, exc: Exception) -> OrjsonResponse:
    log.exception("unexpected error on %s %s", request.method, request.url.path)
    return error_response(500, "internal_error", "internal server error")


def install_error_handlers(app: FastAPI) -> None:
    app.add_exception_handler(ServiceError, _on_service_error)
    app.add_exception_handler(RequestValidationError, _on_validation_error)
    app.add_exception_handler(StarletteHTTPException, _on_http_error)
    app.add_exception_handler(Exception, _on_unexpected)
