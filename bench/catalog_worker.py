"""One worker serving a memory-mapped replicated catalog: start-up and resident memory.

Started by ``bench.catalog_bench.run_worker`` as its own process, so that what it holds is what
one serving process would hold: the artifacts (networks, the real catalog), the replica's
per-part arrays memory-mapped (``bench.replicate.open_replica_arrays``), the compressed index
read memory-mapped (``service.artifacts.indexing.read_flags``), the engine. It reads a JSON spec
on stdin (``folder``, ``index``, ``params``, ``body``, ``reps``), prints ``ready`` once its first
/suggest is answered, then times ``reps`` more and prints a JSON report: the seconds of each
start-up phase, the p50 of the timed requests and its memory from ``/proc/self/status``.

Memory-mapped file pages that a request has read count in the resident set (``RssFile``) but
belong to the page cache: the kernel can drop them at any time and every worker on the machine
shares them. What one worker adds of its own is ``RssAnon``; both are reported.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Any


def memory_status() -> dict[str, int]:
    """The process's resident memory in bytes: VmRSS, RssAnon, RssFile, RssShmem and VmHWM."""
    keys = ("VmRSS", "RssAnon", "RssFile", "RssShmem", "VmHWM")
    out: dict[str, int] = {}
    with open("/proc/self/status") as f:
        for line in f:
            name, _, value = line.partition(":")
            if name in keys:
                out[name] = int(value.split()[0]) * 1024  # reported in kB
    return out


def main() -> None:
    t0 = time.perf_counter()
    spec: dict[str, Any] = json.loads(sys.stdin.read())
    import faiss
    import numpy as np

    from bench.engine_bench import load_engine, request_once
    from bench.replicate import ReplicatedCatalog, open_replica_arrays
    from service.artifacts.indexing import configure_search, read_flags
    from service.settings import get_settings
    from service.suggest.engine import SuggestionEngine

    phases: dict[str, float] = {"imports": time.perf_counter() - t0}
    t = time.perf_counter()
    settings = get_settings()
    shipped = load_engine(settings)
    phases["artifacts"] = time.perf_counter() - t
    t = time.perf_counter()
    catalog = ReplicatedCatalog(shipped.catalog, arrays=open_replica_arrays(Path(spec["folder"])))
    phases["catalog_mapped"] = time.perf_counter() - t
    t = time.perf_counter()
    index = faiss.read_index(spec["index"], read_flags(spec["params"]))
    configure_search(index, spec["params"])
    faiss.omp_set_num_threads(settings.faiss_threads)
    phases["index_read"] = time.perf_counter() - t
    t = time.perf_counter()
    engine = SuggestionEngine(dataclasses.replace(shipped.artifacts, index=index, catalog=catalog), settings)
    del shipped
    body = spec["body"].encode()
    request_once(engine, body)
    phases["engine_and_first_answer"] = time.perf_counter() - t
    phases["total_in_process"] = time.perf_counter() - t0
    at_ready = memory_status()
    print("ready", flush=True)
    suggest = []
    for _ in range(int(spec["reps"])):
        stages, _, _ = request_once(engine, body)
        suggest.append(stages["suggest"])
    report = {"phases_seconds": phases, "memory_at_ready": at_ready, "memory_after": memory_status(),
              "requests": len(suggest), "suggest_p50_ms": 1e3 * float(np.median(suggest)),
              "parts": len(catalog), "index_type": type(index).__name__}
    print(json.dumps(report), flush=True)


if __name__ == "__main__":
    main()
