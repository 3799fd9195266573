"""ComplementMe service: the torch-free suggestion engine and its HTTP API."""

import os

# A self-hosted service sends nothing anywhere. onnxruntime's Linux wheels carry Microsoft's 1DS
# telemetry, which resolved its events host about every 2 minutes (4 lookups in 15 s of an idle
# session, measured with strace). Only this variable, read when onnxruntime creates its
# environment, stops it: ``onnxruntime.disable_telemetry_events()`` after import does not (still
# 4 lookups). Set here, before any module of the package imports onnxruntime; an operator's own
# value wins.
os.environ.setdefault("ORT_DISABLE_TELEMETRY", "1")

__version__ = "0.1.0"
