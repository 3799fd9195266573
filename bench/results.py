"""Benchmark results as JSON files, one per command, under ``bench/results/`` by default.

Each file holds ``{"benchmark", "machine", "config", "results"}``; the report renders whatever
files are present, so a command can be re-run alone and the report rebuilt.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

RESULTS_DIR = Path(__file__).resolve().parent / "results"
CACHE_DIR = Path(__file__).resolve().parent / ".cache"
BENCHMARKS = ("engine", "http", "catalog", "peer", "interactive", "framework", "balancers")


def _clean(value: Any) -> Any:
    """JSON-safe copy: NaN and infinities become None (JSON has no such numbers)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    return value


def save_result(folder: Path, name: str, machine: dict[str, Any], config: dict[str, Any],
                results: dict[str, Any]) -> Path:
    """Write one benchmark's result file ``<folder>/<name>.json`` and return its path."""
    if name not in BENCHMARKS:
        raise ValueError(f"unknown benchmark {name!r}; expected one of {', '.join(BENCHMARKS)}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.json"
    payload = {"benchmark": name, "machine": machine, "config": config, "results": results}
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(_clean(payload), indent=1, sort_keys=False) + "\n")
    tmp.replace(path)
    return path


def load_results(folder: Path) -> dict[str, dict[str, Any]]:
    """Every result file present in ``folder``, by benchmark name; a broken file is an error naming it."""
    out: dict[str, dict[str, Any]] = {}
    for name in BENCHMARKS:
        path = Path(folder) / f"{name}.json"
        if not path.is_file():
            continue
        try:
            data = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: not valid JSON ({exc})") from exc
        if not isinstance(data, dict) or data.get("benchmark") != name or "results" not in data:
            raise ValueError(f"{path}: not a result file of benchmark {name!r}")
        out[name] = data
    return out
