"""The Blender add-on, inside Blender, against a real ``complementme serve`` on the shipped artifacts.

Needs Debian's ``blender`` package (`.ci/run` installs it; README.md says how). When
``blender`` is missing the test skips and says how to install it, except when
``COMPLEMENTME_REQUIRE_BLENDER`` is set (as `.ci/run` does): then it fails, so that CI cannot pass
without running it. Blender runs with its user folders in a temporary directory, so the add-on
install touches nothing of the user's own Blender.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest

from service.settings import DEFAULT_ARTIFACTS

ROOT = Path(__file__).resolve().parents[2]
MAKE_ZIP = ROOT / "clients" / "blender" / "make_addon_zip.py"
SCRIPT = Path(__file__).resolve().parent / "in_blender.py"
REQUIRE_ENV = "COMPLEMENTME_REQUIRE_BLENDER"
READY_TIMEOUT = 120  # seconds for the service to load the artifacts (5 s measured on an idle host)
BLENDER_TIMEOUT = 300  # seconds for the whole in-Blender script (about 10 s measured)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def blender() -> str:
    path = shutil.which("blender")
    if path is None:
        message = ("blender is not installed: install Debian's blender package (3.4 or newer; "
                   "README.md gives the command), which runs the in-Blender test")
        if os.environ.get(REQUIRE_ENV):
            pytest.fail(f"{message}; {REQUIRE_ENV} is set, so it must run")
        pytest.skip(message)
    return path


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _complementme() -> list[str]:
    """The ``complementme`` command of this environment."""
    script = Path(sys.executable).with_name("complementme")
    if script.is_file():
        return [str(script)]
    main = "import sys; from training.cli import app; sys.argv[0] = 'complementme'; app()"
    return [sys.executable, "-c", main]


@pytest.fixture()
def server(tmp_path: Path) -> Iterator[tuple[str, subprocess.Popen[bytes]]]:
    """A real ``complementme serve`` on a free loopback port; its URL and process."""
    artifacts = Path(os.environ.get("COMPLEMENTME_TEST_ARTIFACTS") or DEFAULT_ARTIFACTS)
    if not (artifacts / "manifest.json").is_file():
        pytest.skip(f"no artifact folder at {artifacts}")
    port = _free_port()
    log = (tmp_path / "serve.log").open("wb")
    pythonpath = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
    env = {**os.environ, "PYTHONPATH": pythonpath}
    proc = subprocess.Popen([*_complementme(), "serve", "--artifacts", str(artifacts), "--host", "127.0.0.1",
                             "--port", str(port)], stdout=log, stderr=subprocess.STDOUT, env=env)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + READY_TIMEOUT
        while True:
            try:
                with urllib.request.urlopen(url + "/readyz", timeout=2) as answer:
                    if answer.status == 200:
                        break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                raise AssertionError(f"complementme serve did not become ready:\n"
                                     f"{(tmp_path / 'serve.log').read_text()[-2000:]}")
            time.sleep(0.25)
        yield url, proc
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        log.close()


def test_addon_suggests_imports_completes_and_reports_errors_in_blender(
        blender: str, server: tuple[str, subprocess.Popen[bytes]], tmp_path: Path) -> None:
    url, proc = server
    # The zip made by the documented command, as a user would install it.
    made = subprocess.run([sys.executable, str(MAKE_ZIP), "--out", str(tmp_path / "addon.zip")],
                          capture_output=True, text=True, check=True)
    addon_zip = Path(made.stdout.strip())
    result_file = tmp_path / "result.json"
    home = tmp_path / "blender-home"
    env = {**os.environ, "CM_ADDON_ZIP": str(addon_zip), "CM_URL": url, "CM_SERVER_PID": str(proc.pid),
           "CM_RESULT": str(result_file),
           # The add-on is installed into these folders, not into the user's ~/.config/blender.
           "BLENDER_USER_SCRIPTS": str(home / "scripts"), "BLENDER_USER_CONFIG": str(home / "config"),
           "HOME": str(home)}
    done = subprocess.run([blender, "--background", "--factory-startup", "--python-exit-code", "1",
                           "--python", str(SCRIPT)], env=env, capture_output=True, text=True,
                          timeout=BLENDER_TIMEOUT)
    output = (done.stdout + done.stderr)[-4000:]
    assert done.returncode == 0, f"blender exited with {done.returncode}:\n{output}"
    result = json.loads(result_file.read_text())

    assert (home / "scripts/addons/complementme_blender/__init__.py").is_file(), "installed from the zip"
    assert len(result["suggestions"]) == 5 and result["imported"]["name"] == result["suggestions"][0][1]
    assert result["assembled"], "auto-complete imported no part"
    assert proc.wait(timeout=30) is not None, "the in-Blender script stopped the service"
    for key in ("error_4xx", "error_timeout", "error_offline", "error_stopped", "error_import_stopped"):
        assert result[key].count("\n") == 0 and result[key].startswith("Error: ComplementMe:"), result[key]
