"""Container health check: exit 0 when the service answers ``GET /healthz`` with 200, else 1.

Plain standard library, so the image needs no curl. It asks the loopback address on the port
the server listens on (``COMPLEMENTME_PORT``, 8000 by default). Liveness only: readiness
(``/readyz``: artifacts loaded, warm-up passed) is for load balancers and Kubernetes.
"""

from __future__ import annotations

import os
import sys
import urllib.error
import urllib.request


def main() -> int:
    port = os.environ.get("COMPLEMENTME_PORT", "8000")
    url = f"http://127.0.0.1:{port}/healthz"
    try:
        with urllib.request.urlopen(url, timeout=4) as resp:
            status = resp.status
    except (urllib.error.URLError, OSError) as exc:
        sys.stderr.write(f"healthcheck: {url} unreachable: {exc}\n")
        return 1
    if status != 200:
        sys.stderr.write(f"healthcheck: {url} answered {status}\n")
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
