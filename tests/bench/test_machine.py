"""The machine description read from /proc text and the artifact manifest."""

from __future__ import annotations

import json
from pathlib import Path

from bench.machine import artifact_version, cpu_flags, cpu_model, describe_machine, mem_total_gib

CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
model name\t: AMD EPYC 9R45 96-Core Processor
flags\t\t: fpu sse2 avx2 avx512f avx512bw
"""


def test_cpu_and_memory_from_proc_text() -> None:
    assert cpu_model(CPUINFO) == "AMD EPYC 9R45 96-Core Processor"
    assert cpu_model("processor : 0\n") == "unknown"
    assert cpu_flags(CPUINFO) == ["avx2", "avx512f"]
    assert mem_total_gib("MemTotal:       24641536 kB\nMemFree: 1 kB\n") == 23.5
    assert mem_total_gib("") is None


def test_artifact_version_from_manifest(tmp_path: Path) -> None:
    (tmp_path / "manifest.json").write_text(json.dumps(
        {"model_version": "m-1", "created": "2026-01-01", "part_count": 3, "n_points": 512,
         "index": {"type": "IndexFlatL2"}}))
    v = artifact_version(tmp_path)
    assert v["model_version"] == "m-1" and v["part_count"] == 3 and v["index"] == {"type": "IndexFlatL2"}
    assert "error" in artifact_version(tmp_path / "missing")


def test_describe_machine_has_every_field(tmp_path: Path) -> None:
    m = describe_machine(tmp_path)
    for key in ("cpu_model", "cores", "ram_gib", "python", "packages", "artifacts", "date", "command"):
        assert key in m
    assert "onnxruntime" in m["packages"] and "faiss-cpu" in m["packages"]
