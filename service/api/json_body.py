"""JSON request bodies: UTF-8 JSON only, and a point count checked while the body is read.

Pure ASGI like the other middleware. For every request with a body except the multipart mesh
uploads (``MESH_UPLOAD_PATHS``), the first ``receive`` checks the media type (``application/json``
or ``+json``, UTF-8; none at all is read as JSON) and each chunk's ``[`` are counted: an
``[x, y, z]`` triple has one, so a body with more than ``max_body_points`` (plus
``SPARE_BRACKETS`` for the request's other lists) holds too many points, and is refused before
any of it is parsed. Parsing is what cost: an 8.3 MB body of 1.04M points held the event loop
(and every ``/healthz``) for 1.4-1.7 s, while counting it takes a few milliseconds. Brackets inside
strings count too; the strings of a valid request (ids, categories) hold none.

The refusals are raised from ``receive`` (as ``BodyTooLarge`` is), so they reach only routes that
read a body, after routing: metrics see the route.
"""

from __future__ import annotations

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.middleware import MESH_UPLOAD_PATHS

SPARE_BRACKETS = 1024
_BODY_METHODS = frozenset({"POST", "PUT", "PATCH"})


class BodyRefused(HTTPException):
    """Raised from ``receive``; the HTTP error handler answers it with its ``code``."""

    def __init__(self, status: int, code: str, message: str):
        super().__init__(status, message)
        self.code = code


def json_media_problem(content_type: str | None) -> str | None:
    """Why a Content-Type is not UTF-8 JSON (None when it is, or when there is none)."""
    if content_type is None:
        return None
    media, *params = (p.strip().lower() for p in content_type.split(";"))
    if media != "application/json" and not (media.startswith("application/") and media.endswith("+json")):
        return f"the body must be application/json, not {media or 'an empty media type'!r}"
    for param in params:
        key, _, value = param.partition("=")
        if key.strip() == "charset" and value.strip().strip('"') not in ("utf-8", "utf8"):
            return f"JSON bodies must be UTF-8, not {value.strip()!r}"
    return None


def _not_utf8(first: bytes) -> bool:
    """Whether a body starts like UTF-16 or UTF-32 JSON, which the standard library would decode:
    a byte-order mark, or the NUL pattern of two ASCII characters (RFC 4627, section 3)."""
    if first[:2] in (b"\xff\xfe", b"\xfe\xff"):
        return True
    nul = [b == 0 for b in first[:4]]
    return len(nul) == 4 and nul in ([True, True, True, False], [True, False, True, False],
                                     [False, True, True, True], [False, True, False, True])


class JsonBodyMiddleware:
    """Refuse non-JSON and non-UTF-8 bodies (415) and bodies with too many points (422)."""

    def __init__(self, app: ASGIApp, max_body_points: int):
        self.app = app
        self.max_brackets = max_body_points + SPARE_BRACKETS
        self.max_body_points = max_body_points

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (scope["type"] != "http" or scope["method"] not in _BODY_METHODS
                or scope["path"] in MESH_UPLOAD_PATHS):
            await self.app(scope, receive, send)
            return
        content_type = next((v.decode("latin-1") for k, v in scope["headers"] if k == b"content-type"), None)
        problem = json_media_problem(content_type)
        brackets = 0
        first = True

        async def checked_receive() -> Message:
            nonlocal brackets, first
            if problem is not None:
                raise BodyRefused(415, "unsupported_media_type", problem)
            message = await receive()
            if message["type"] == "http.request":
                chunk = message.get("body", b"")
                if first and chunk:
                    first = False
                    if _not_utf8(chunk):
                        raise BodyRefused(415, "unsupported_media_type", "JSON bodies must be UTF-8 "
                                          "(RFC 8259); this one looks like UTF-16 or UTF-32")
                brackets += chunk.count(b"[")
                if brackets > self.max_brackets:
                    raise BodyRefused(422, "too_many_points", f"the body holds more than "
                                      f"{self.max_body_points} [x, y, z] points (counted by its '[' "
                                      "before parsing; COMPLEMENTME_MAX_BODY_POINTS, all items together)")
            return message

        await self.app(scope, checked_receive, send)
