"""What the benchmark tests share: a quick run of one benchmark command."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from bench.query import REPO
from bench.results import load_results

ARTIFACTS = REPO / "exported"


def quick_bench_run(command: str, tmp_path: Path) -> dict[str, Any]:
    """``python -m bench <command> --quick`` into ``tmp_path`` (bounded: 15 minutes); its results.

    Skips when there is no shipped model to serve.
    """
    if not (ARTIFACTS / "manifest.json").is_file():
        pytest.skip(f"the benchmark serves the shipped model: no artifact folder at {ARTIFACTS}")
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    cmd = [sys.executable, "-m", "bench", command, "--quick",
           "--results-dir", str(tmp_path / "results"), "--cache-dir", str(tmp_path / "cache")]
    done = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    return load_results(tmp_path / "results")[command]
