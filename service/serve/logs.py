"""Log format and library log levels of the ``complementme`` command line (``service.serve.cli``)."""

from __future__ import annotations

import logging

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def quiet_libraries() -> None:
    """Keep per-request and loader chatter of libraries out of the CLI's INFO log (shown with -v).

    faiss's loader logs at INFO that it "Could not load library with AVX2 support ...
    ModuleNotFoundError" whenever the wheel's generic build is the one that loads, which reads
    like an error but is not one; httpx logs one INFO line per request (inside progress bars).
    """
    if logging.getLogger().getEffectiveLevel() <= logging.DEBUG:
        return
    for name in ("httpx", "httpcore", "faiss.loader"):
        logging.getLogger(name).setLevel(logging.WARNING)
