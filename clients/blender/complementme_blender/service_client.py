"""The HTTP calls the add-on makes, with ``urllib`` only, and their errors as one-line messages.

Every failure becomes a ``ServiceError`` whose text is what the user reads in Blender's report
area: the service's own ``code`` and ``message`` for a 4xx or 5xx answer (its error body is
``{"error": {"code", "message", "details"?}}``), or what went wrong on the way (connection
refused, no answer within the timeout, a URL that is not http(s)).
"""

from __future__ import annotations

import http.client
import json
import socket
import urllib.error
import urllib.parse
import urllib.request
from typing import Any

MAX_ERROR_BODY = 64 * 1024  # bytes of an error answer read to find its message
# The selection goes to the mesh routes as the request body, in this media type.
GLB_MEDIA_TYPE = "model/gltf-binary"


class ServiceError(Exception):
    """A call that did not give an answer; ``str()`` is a one-line message for the user."""


class Client:
    """Calls to one ComplementMe service.

    Args:
        base_url: e.g. ``http://127.0.0.1:8000`` (a trailing slash is ignored).
        api_key: sent as ``Authorization: Bearer <key>`` when not empty.
        timeout: seconds to wait for the connection and for each read of the answer.
    """

    def __init__(self, base_url: str, api_key: str = "", timeout: float = 30.0) -> None:
        url = base_url.strip().rstrip("/")
        parts = urllib.parse.urlsplit(url)
        if parts.scheme not in ("http", "https") or not parts.netloc:
            raise ServiceError(f"the server URL must look like http://host:port, found {base_url!r}")
        self.base_url = url
        self.api_key = api_key.strip()
        self.timeout = timeout

    # -- the service's routes --------------------------------------------------------------

    def suggest_mesh(self, glb: bytes, options: dict[str, Any]) -> dict[str, Any]:
        """``POST /suggest/mesh`` with a GLB and the options of ``/suggest``; the parsed answer."""
        return self._json("POST", _with_options("/suggest/mesh", options), glb, GLB_MEDIA_TYPE)

    def assemble_mesh(self, glb: bytes, options: dict[str, Any]) -> dict[str, Any]:
        """``POST /assemble/mesh`` with a GLB start and the options of ``/assemble``."""
        return self._json("POST", _with_options("/assemble/mesh", options), glb, GLB_MEDIA_TYPE)

    def part_mesh_obj(self, part_id: str) -> str:
        """``GET /parts/{id}/mesh?format=obj``: the part's centred mesh, canonical units, as OBJ text."""
        path = "/parts/" + urllib.parse.quote(part_id, safe="/") + "/mesh?format=obj"
        return self._call("GET", path).decode("utf-8")

    # -- plumbing --------------------------------------------------------------------------

    def _json(self, method: str, path: str, body: bytes | None = None,
              content_type: str | None = None) -> dict[str, Any]:
        raw = self._call(method, path, body, content_type)
        where = f"{method} {self.base_url}{path.split('?')[0]}"
        try:
            answer = json.loads(raw)
        except ValueError:
            raise ServiceError(f"{where}: the answer is not JSON") from None
        if not isinstance(answer, dict):
            raise ServiceError(f"{where}: the answer is not a JSON object")
        return answer

    def _call(self, method: str, path: str, body: bytes | None = None,
              content_type: str | None = None) -> bytes:
        headers = {"Accept": "application/json, model/obj, */*", "User-Agent": "complementme-blender"}
        if content_type:
            headers["Content-Type"] = content_type
        if self.api_key:
            headers["Authorization"] = f"Bearer {self.api_key}"
        request = urllib.request.Request(self.base_url + path, data=body, headers=headers, method=method)
        where = f"{method} {self.base_url}{path.split('?')[0]}"
        try:
            with urllib.request.urlopen(request, timeout=self.timeout) as answer:
                data: bytes = answer.read()
                return data
        except urllib.error.HTTPError as exc:
            raise ServiceError(f"{where}: {http_error_message(exc.code, exc.read(MAX_ERROR_BODY))}") from None
        except urllib.error.URLError as exc:
            raise ServiceError(f"{where}: {_network_reason(exc.reason, self.timeout)}") from None
        except TimeoutError:
            raise ServiceError(f"{where}: no answer within {self.timeout:g} s") from None
        except (OSError, http.client.HTTPException) as exc:
            raise ServiceError(f"{where}: {_network_reason(exc, self.timeout)}") from None


def http_error_message(status: int, body: bytes) -> str:
    """``"<status> <code>: <message>"`` from the service's error body (or the raw start of it)."""
    try:
        error = json.loads(body)["error"]
        text = f"{status} {error['code']}: {error['message']}"
        details = error.get("details") or []
        if details and isinstance(details[0], dict) and details[0].get("message"):
            loc = ".".join(str(x) for x in details[0].get("loc", []))
            text += f" ({loc}: {details[0]['message']})" if loc else f" ({details[0]['message']})"
        return text
    except (ValueError, KeyError, TypeError, IndexError):
        snippet = body[:200].decode("utf-8", "replace").strip()
        return f"HTTP {status}" + (f": {snippet}" if snippet else "")


def _network_reason(reason: object, timeout: float) -> str:
    if isinstance(reason, TimeoutError):  # socket.timeout is TimeoutError from Python 3.10
        return f"no answer within {timeout:g} s"
    if isinstance(reason, ConnectionRefusedError):
        return "connection refused (is the service running?)"
    if isinstance(reason, socket.gaierror):
        return "unknown host name"
    return f"cannot reach the server ({reason})"


def _with_options(path: str, options: dict[str, Any]) -> str:
    """A mesh route's path with its options (JSON) in the query string: the GLB is the body."""
    return path + "?" + urllib.parse.urlencode({"options": json.dumps(options)})
