"""Browser tests: the real service in a thread on a free port, and Debian's chromium driven by Playwright.

Nothing is installed by the tests: they use Debian's chromium at ``/usr/bin/chromium``
(``.ci/run`` installs it; locally Debian's chromium package, see README.md) and fail, saying that,
when it is missing. Playwright's own browser downloads are never used (``executable_path``
points at the system chromium).
"""

from __future__ import annotations

import os
import socket
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
INSTALL_HINT = ("install Debian's chromium package (README.md gives the command) "
                "(as root; .ci/run does this in CI)")


@pytest.fixture(scope="session")
def chromium_path() -> str:
    # A failure, not a skip: a machine without the browser would otherwise pass CI having never
    # run the page's tests.
    if not CHROMIUM.exists():
        pytest.fail(f"no browser at {CHROMIUM}: {INSTALL_HINT}", pytrace=False)
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


def _serve(settings: Settings) -> Iterator[str]:
    """The real app under uvicorn in a thread; yields its base URL once it answers /readyz."""
    import httpx
    import uvicorn

    from service.api.app import create_app

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


@pytest.fixture(scope="session")
def server(artifacts: Path) -> Iterator[str]:
    """The real app on the shipped artifacts with its default settings."""
    yield from _serve(Settings(artifacts=artifacts, onnx_threads=1, faiss_threads=1, seed=0))


@pytest.fixture(scope="session")
def wary_server(artifacts: Path) -> Iterator[str]:
    """The real app with a familiarity threshold of 0.1 (COMPLEMENTME_FAMILIARITY_THRESHOLD), so
    that what it reads warns: with frame fitting, an upload is read in the frame it is most
    familiar in, where the shipped threshold (1.45) no longer warns (docs/training.md)."""
    yield from _serve(Settings(artifacts=artifacts, onnx_threads=1, faiss_threads=1, seed=0,
                               familiarity_threshold=0.1))


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
