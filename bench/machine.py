"""The machine and software a benchmark ran on, recorded next to every result.

Read from ``/proc`` and package metadata only (no heavy imports: describing the machine must not
load torch into a process that is about to be timed).
"""

from __future__ import annotations

import json
import os
import platform
import shlex
import sys
from datetime import datetime, timezone
from importlib import metadata
from pathlib import Path
from typing import Any

PACKAGES = ("numpy", "onnxruntime", "faiss-cpu", "fastapi", "uvicorn", "orjson", "torch")


def cpu_model(cpuinfo: str) -> str:
    """The ``model name`` line of /proc/cpuinfo text ("unknown" when absent)."""
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "model name" and value.strip():
            return value.strip()
    return "unknown"


def cpu_flags(cpuinfo: str, wanted: tuple[str, ...] = ("avx2", "avx512f", "avx512_bf16", "amx_tile")
              ) -> list[str]:
    """Which of the vector-extension flags that matter for the kernels the CPU advertises."""
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        if key.strip() == "flags":
            have = set(value.split())
            return [f for f in wanted if f in have]
    return []


def mem_total_gib(meminfo: str) -> float | None:
    """MemTotal of /proc/meminfo text in GiB (None when absent)."""
    for line in meminfo.splitlines():
        if line.startswith("MemTotal:"):
            return round(int(line.split()[1]) / 1024 / 1024, 1)
    return None


def _read(path: str) -> str:
    try:
        return Path(path).read_text()
    except OSError:
        return ""


def package_versions() -> dict[str, str | None]:
    """Installed versions of the packages whose speed the numbers depend on (None: not installed)."""
    out: dict[str, str | None] = {}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = None
    return out


def artifact_version(folder: Path) -> dict[str, Any]:
    """Model version, creation date, part count and index of an artifact folder's manifest."""
    path = Path(folder) / "manifest.json"
    try:
        m = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        return {"path": str(path), "error": str(exc)}
    return {"path": str(Path(folder)), "model_version": m.get("model_version"), "created": m.get("created"),
            "part_count": m.get("part_count"), "n_points": m.get("n_points"),
            "placement_points": m.get("placement_points", m.get("n_points")), "index": m.get("index")}


def describe_machine(artifacts: Path) -> dict[str, Any]:
    """CPU, cores, RAM, load, Python and package versions, artifact version, date and command."""
    cpuinfo = _read("/proc/cpuinfo")
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    return {
        "cpu_model": cpu_model(cpuinfo),
        "cpu_flags": cpu_flags(cpuinfo),
        "cores": os.cpu_count(),
        "usable_cores": usable_cores(),
        "ram_gib": mem_total_gib(_read("/proc/meminfo")),
        "load_average_at_start": [round(x, 2) for x in load] if load else None,
        "kernel": platform.release(),
        "python": platform.python_version(),
        "packages": package_versions(),
        "artifacts": artifact_version(artifacts),
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "command": command_line(),
    }


def usable_cores() -> int:
    """Cores this process may run on (its affinity mask; all cores where there is none)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def command_line() -> str:
    """The command that is running, as one would type it from the repository root."""
    argv = list(sys.argv)
    if argv and Path(argv[0]).name == "__main__.py" and Path(argv[0]).parent.name == "bench":
        argv = ["python", "-m", "bench", *argv[1:]]
    return shlex.join(argv)
