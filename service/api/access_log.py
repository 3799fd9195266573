"""Keep secrets out of the access log: query parameters that look like credentials are redacted.

Keys belong in the ``Authorization`` header; one sent as ``?api_key=...`` is refused, but uvicorn's
access log would still write the whole URL. The filter rewrites the logged path only.
"""

from __future__ import annotations

import logging
import re

# A query parameter whose name holds one of these words has its value replaced.
_SECRET = re.compile(r"(?i)([?&][^=&#]*(?:key|token|secret|passw|auth|credential)[^=&#]*=)[^&#]*")
REDACTED = "REDACTED"


def redact_query(path: str) -> str:
    """``path`` with the values of credential-like query parameters replaced."""
    return _SECRET.sub(lambda m: m.group(1) + REDACTED, path) if "?" in path else path


class RedactSecrets(logging.Filter):
    """Applied to ``uvicorn.access``, whose records carry the path as their third argument."""

    def filter(self, record: logging.LogRecord) -> bool:
        args = record.args
        if isinstance(args, tuple) and len(args) >= 3 and isinstance(args[2], str):
            record.args = (*args[:2], redact_query(args[2]), *args[3:])
        return True


def install_access_log_redaction() -> None:
    """Add the filter to uvicorn's access logger once per process."""
    logger = logging.getLogger("uvicorn.access")
    if not any(isinstance(f, RedactSecrets) for f in logger.filters):
        logger.addFilter(RedactSecrets())
