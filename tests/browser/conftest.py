"""Browser tests: the real service in a thread on a free port, and Debian's chromium driven by Playwright.

Nothing is installed by hand: when ``/usr/bin/chromium`` is missing and the tests run as root
with apt available (CI containers), the session installs it with ``apt-get update && apt-get
install -y chromium``; otherwise the tests skip and say why. Playwright's own browser downloads
are never used (``executable_path`` points at the system chromium).
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import threading
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest

warnings.filterwarnings("ignore", message=".*httpx.*starlette.testclient.*")

from service.settings import DEFAULT_ARTIFACTS, Settings  # noqa: E402

ARTIFACTS_ENV = "COMPLEMENTME_TEST_ARTIFACTS"
CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--no-first-run", "--use-gl=swiftshader",
                 "--enable-unsafe-swiftshader"]
ARTIFACT_DIR = Path(__file__).resolve().parents[2] / "test-artifacts"
APT_TIMEOUT = 900  # seconds for apt-get update + install


def _install_chromium() -> str | None:
    """Install Debian's chromium with apt when possible; the reason it is impossible otherwise."""
    if CHROMIUM.exists():
        return None
    if shutil.which("apt-get") is None:
        return "no /usr/bin/chromium and no apt-get to install it (install Debian's chromium)"
    if hasattr(os, "geteuid") and os.geteuid() != 0:
        return "no /usr/bin/chromium and not root: run `apt-get update && apt-get install -y chromium`"
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    try:
        for cmd in (["apt-get", "update"],
                    ["apt-get", "install", "-y", "--no-install-recommends", "chromium"]):
            done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=APT_TIMEOUT)
            if done.returncode != 0:
                return f"`{' '.join(cmd)}` failed ({done.returncode}): {done.stderr.strip()[-300:]}"
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"installing chromium failed: {exc}"
    return None if CHROMIUM.exists() else "apt-get installed chromium but /usr/bin/chromium is missing"


@pytest.fixture(scope="session")
def chromium_path() -> str:
    reason = _install_chromium()
    if reason:
        pytest.skip(reason)
    return str(CHROMIUM)


@pytest.fixture(scope="session")
def artifacts() -> Path:
    folder = Path(os.environ.get(ARTIFACTS_ENV) or DEFAULT_ARTIFACTS)
    if not (folder / "manifest.json").is_file():
        pytest.skip(f"no artifact folder at {folder} (set {ARTIFACTS_ENV} or export to exported/)")
    return folder


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="session")
def server(artifacts: Path) -> Iterator[str]:
    """The real app under uvicorn in a thread; yields its base URL once it answers /readyz."""
    import httpx
    import uvicorn

    from service.api import create_app

    settings = Settings(artifacts=artifacts, onnx_threads=1, faiss_threads=1, seed=0)
    port = _free_port()
    config = uvicorn.Config(create_app(settings), host="127.0.0.1", port=port, log_level="warning")
    srv = uvicorn.Server(config)
    thread = threading.Thread(target=srv.run, daemon=True)
    thread.start()
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while True:
        try:
            if httpx.get(base + "/readyz", timeout=2).status_code == 200:
                break
        except httpx.HTTPError:
            pass
        if not thread.is_alive() or time.monotonic() > deadline:
            raise RuntimeError("the service did not become ready")
        time.sleep(0.2)
    yield base
    srv.should_exit = True
    thread.join(timeout=30)


# Module scope: Playwright's sync API keeps an event loop running in this thread while it is
# open, and later tests that call asyncio.run() would fail if it stayed open for the session.
@pytest.fixture(scope="module")
def browser(chromium_path: str) -> Iterator[object]:
    playwright = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    with playwright.sync_playwright() as p:
        b = p.chromium.launch(executable_path=chromium_path, args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture(scope="session")
def artifact_dir() -> Path:
    ARTIFACT_DIR.mkdir(parents=True, exist_ok=True)
    return ARTIFACT_DIR
