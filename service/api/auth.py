"""Who may change the catalog: a bearer API key from the settings, secure by default.

Reads need no key. Writes need ``Authorization: Bearer <COMPLEMENTME_API_KEY>``; the key is
compared in constant time (``hmac.compare_digest``). The order of refusals:

1. no key configured: 403 ``writes_disabled`` (a server nobody configured accepts no writes);
2. no or malformed credentials: 401 ``missing_credentials``; wrong key: 401
   ``invalid_credentials`` (both with ``WWW-Authenticate: Bearer``);
3. no data folder (and not the postgres backend) configured: 403 ``read_only``;
4. artifacts not loaded yet: 503 ``not_ready``.
"""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.api.deps import served_of
from service.catalog_store.writer import CatalogWriter
from service.errors import ForbiddenError, NotReadyError, UnauthorizedError
from service.settings import Settings

bearer = HTTPBearer(auto_error=False, scheme_name="ApiKey", description=(
    "Catalog writes: `Authorization: Bearer <COMPLEMENTME_API_KEY>`."))


def check_api_key(settings: Settings, credentials: HTTPAuthorizationCredentials | None) -> None:
    """Raise the refusal a write with these credentials gets (see the module doc), if any."""
    if settings.api_key is None:
        raise ForbiddenError("writes_disabled", "catalog writes are disabled on this server: no API key is "
                             "configured (COMPLEMENTME_API_KEY)")
    if credentials is None or not credentials.credentials:
        raise UnauthorizedError("missing_credentials", "catalog writes need an API key: send "
                                "'Authorization: Bearer <key>'")
    given = credentials.credentials.encode("utf-8", "surrogateescape")
    if not hmac.compare_digest(given, settings.api_key.get_secret_value().encode("utf-8")):
        raise UnauthorizedError("invalid_credentials", "the API key is not valid")


async def require_writer(request: Request,
                         credentials: HTTPAuthorizationCredentials | None = Depends(bearer)) -> CatalogWriter:
    """The catalog writer, for a request that may write (else the refusal above)."""
    settings: Settings = request.app.state.settings
    check_api_key(settings, credentials)
    if not settings.catalog_enabled:
        raise ForbiddenError("read_only", "this server's catalog is read-only: no data folder is configured "
                             "(COMPLEMENTME_DATA_DIR)")
    served = served_of(request.app)
    if served is None or served.writer is None:
        raise NotReadyError("not_ready", "the catalog is not loaded yet")
    return served.writer


WriterDep = Annotated[CatalogWriter, Depends(require_writer)]
