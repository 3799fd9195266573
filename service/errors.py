"""Errors the engine raises for a caller's bad input, each with a stable machine-readable code.

They carry no HTTP types: the API maps them to statuses (``InputError`` 422, ``NotFoundError``
404, ``PayloadTooLargeError`` 413), and the CLI and tests catch them as plain exceptions.
"""

from __future__ import annotations

from typing import Any


class ServiceError(Exception):
    """A request the service refuses; ``code`` is stable, ``message`` says what was wrong."""

    status = 400

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code
        self.message = message


class InputError(ServiceError, ValueError):
    """The request is well-formed but its content cannot be used (bad points, k out of range, ...)."""

    status = 422


class NotFoundError(ServiceError, LookupError):
    """A part, shape or category the request names is not in the catalog."""

    status = 404


class PayloadTooLargeError(ServiceError):
    """The request body is larger than the configured limit."""

    status = 413


class UnsupportedMediaError(ServiceError):
    """An upload in a format the service cannot read."""

    status = 415


class NotReadyError(ServiceError):
    """The artifacts are not loaded (yet)."""

    status = 503


class UnavailableError(ServiceError):
    """A catalog write while the database cannot be reached: nothing was stored; retry later."""

    status = 503

    def __init__(self, code: str, message: str, retry_after: int):
        super().__init__(code, message)
        self.retry_after = retry_after

    @property
    def headers(self) -> dict[str, str]:
        return {"Retry-After": str(self.retry_after)}


class UnauthorizedError(ServiceError):
    """A catalog write without the API key, or with a wrong one (answered with WWW-Authenticate)."""

    status = 401

    @property
    def headers(self) -> dict[str, str]:
        if self.code == "invalid_credentials":
            return {"WWW-Authenticate": 'Bearer realm="complementme", error="invalid_token"'}
        return {"WWW-Authenticate": 'Bearer realm="complementme"'}


class ForbiddenError(ServiceError):
    """A catalog write on a server that accepts none (no API key or no data folder configured)."""

    status = 403


class ConflictError(ServiceError):
    """A write that contradicts the catalog's state (e.g. deleting a shipped part)."""

    status = 409


class StorageFullError(ServiceError):
    """The data folder holds the most parts the settings allow."""

    status = 507



class DeadlineError(ServiceError):
    """The request's deadline passed before its work started (it waited in a queue too long)."""

    status = 504


def error_body(code: str, message: str, details: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """The JSON body of every error answer: ``{"error": {"code", "message", "details"?}}``."""
    err: dict[str, Any] = {"code": code, "message": message}
    if details is not None:
        err["details"] = details
    return {"error": err}
