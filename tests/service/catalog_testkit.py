"""Helpers for the catalog-write tests: an API key, part meshes, writable settings, live servers.

``LiveServer`` runs the real service as a separate uvicorn process (``python -m uvicorn
--factory service.api.app:create_app``) configured through ``COMPLEMENTME_*`` variables, so a
test can kill it with SIGKILL and start it again on the same data folder.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import trimesh
from service_testkit import make_settings

from service.serve.cli import HTTP_PROTOCOL
from service.settings import Settings

KEY = "test-key-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {KEY}"}
REPO = Path(__file__).resolve().parents[2]


def part_mesh(seed: int, file_type: str = "ply") -> bytes:
    """A small box part somewhere in the canonical frame, different for every seed."""
    rng = np.random.default_rng(seed)
    box = trimesh.creation.box(extents=rng.uniform(0.05, 0.4, size=3))
    box.apply_translation(rng.uniform(-0.5, 0.5, size=3))
    data = box.export(file_type=file_type)
    return data.encode() if isinstance(data, str) else bytes(data)


def writable_settings(artifacts: Path, data_dir: Path | None, **overrides: Any) -> Settings:
    """Test settings with a data folder and the test key (checksums verified once per session)."""
    values: dict[str, Any] = {"data_dir": data_dir, "api_key": KEY, "verify_checksums": False,
                              "catalog_poll_seconds": 0, **overrides}
    return make_settings(artifacts, **values)


def add_part(client: Any, seed: int, category: str = "widget", **fields: Any) -> Any:
    """POST /parts with a box mesh; returns the response (``client``: TestClient or httpx.Client)."""
    data = {"category": category, **{k: v for k, v in fields.items() if v is not None}}
    return client.post("/parts", files={"file": (f"part{seed}.ply", part_mesh(seed))}, data=data,
                       headers=AUTH)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class LiveServer:
    """The service in its own process on a free port, with settings from the environment."""

    def __init__(self, artifacts: Path, data_dir: Path, **env: Any):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.env = {k: v for k, v in os.environ.items() if not k.startswith("COMPLEMENTME_")}
        self.env.update({"COMPLEMENTME_ARTIFACTS": str(artifacts), "COMPLEMENTME_DATA_DIR": str(data_dir),
                         "COMPLEMENTME_API_KEY": KEY, "COMPLEMENTME_VERIFY_CHECKSUMS": "false",
                         "COMPLEMENTME_LOG_LEVEL": "warning", "PYTHONPATH": str(REPO),
                         **{f"COMPLEMENTME_{k.upper()}": str(v) for k, v in env.items()}})
        self.proc: subprocess.Popen[bytes] | None = None
        self.log = data_dir.parent / f"server-{self.port}.log"

    def start(self, timeout: float = 120) -> LiveServer:
        with open(self.log, "ab") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "uvicorn", "--factory", "service.api.app:create_app", "--host",
                 "127.0.0.1", "--port", str(self.port), "--log-level", "warning", "--http", HTTP_PROTOCOL],
                env=self.env, cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            assert self.proc.poll() is None, f"the server exited: {self.log.read_text()[-3000:]}"
            try:
                if httpx.get(self.url + "/readyz", timeout=2).status_code == 200:
                    return self
            except httpx.HTTPError:
                pass
            time.sleep(0.1)
        raise AssertionError(f"the server did not become ready: {self.log.read_text()[-3000:]}")

    def kill(self) -> None:
        """SIGKILL: no shutdown code runs, as in a power cut of the process."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(timeout=30)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.kill()
