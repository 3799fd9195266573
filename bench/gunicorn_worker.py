"""The gunicorn worker class of the balancer benchmark: uvicorn's, with the service's HTTP protocol.

``uvicorn-worker``'s ``UvicornWorker`` runs uvicorn inside a gunicorn worker process with
uvicorn's automatic choices (uvloop, httptools). The service is served with its own httptools
protocol, which answers what the parser refuses with the JSON error body
(``service.serve.cli.HTTP_PROTOCOL``); this class makes gunicorn's workers use it too, so that
all set-ups of ``bench/balancer_bench.py`` serve the same code.
"""

from __future__ import annotations

from typing import Any, ClassVar

from uvicorn_worker import UvicornWorker

from service.serve.cli import HTTP_PROTOCOL


class JsonErrorUvicornWorker(UvicornWorker):
    CONFIG_KWARGS: ClassVar[dict[str, Any]] = {**UvicornWorker.CONFIG_KWARGS, "http": HTTP_PROTOCOL}
