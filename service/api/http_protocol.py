"""uvicorn's HTTP protocol, with the service's JSON error body for requests its parser refuses.

A request that uvicorn's HTTP parser cannot read (a malformed request line, method or header, a
bad chunk size) never reaches the app: uvicorn answers it itself with a plain-text 400 ("Invalid
HTTP request received.") and closes the connection. Every other error of the service is
``{"error": {"code", "message"}}``, so ``JsonErrorProtocol`` writes that body instead (code
``bad_http``); the status, and closing the connection after it, stay uvicorn's.

The hook is uvicorn's ``send_400_response``, through which its httptools protocol answers a
parser error. It is not public API: ``tests/service/test_http_protocol.py`` pins
it on a real uvicorn server, so an upgrade that moves it fails there rather than silently
bringing the plain-text answer back. ``complementme serve`` runs uvicorn with this protocol
(``service.serve.cli.HTTP_PROTOCOL``); with uvicorn's own command line, pass it as ``--http
service.api.http_protocol:JsonErrorProtocol``.
"""

from __future__ import annotations

import orjson
from uvicorn.protocols.http.httptools_impl import STATUS_LINE, HttpToolsProtocol

from service.errors import error_body

BAD_HTTP = "bad_http"
_MESSAGE = ("the request is not valid HTTP/1.1: uvicorn's parser refused its request line, headers "
            "or body framing ({})")


def _json_400(reason: str) -> bytes:
    return orjson.dumps(error_body(BAD_HTTP, _MESSAGE.format(reason.rstrip("."))))


class JsonErrorProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol (what its "auto" picks: httptools is a requirement of the
    service); a parser error is answered with a JSON body."""

    def send_400_response(self, msg: str) -> None:
        body = _json_400(msg)
        content = [STATUS_LINE[400]]
        for name, value in self.server_state.default_headers:
            content.extend([name, b": ", value, b"\r\n"])
        content.extend([b"content-type: application/json\r\n",
                        b"content-length: " + str(len(body)).encode("ascii") + b"\r\n",
                        b"connection: close\r\n", b"\r\n", body])
        self.transport.write(b"".join(content))
        self.transport.close()
