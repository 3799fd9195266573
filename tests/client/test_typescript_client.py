"""Other ecosystems bind to the API as published: a TypeScript client generated from /openapi.json
by openapi-typescript compiles with tsc, and so do calls written against it (``call.ts``).

The tools come from npm at the versions in ``package-lock.json`` (``npm ci``); node and npm are
system packages (``.ci/run`` installs them; locally Debian's nodejs and npm packages). A call
with a wrong type must fail to compile, so the check can fail.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from service.api.app import create_app
from service.settings import Settings

HERE = Path(__file__).resolve().parent
NPM_TIMEOUT = 600  # seconds: npm ci fetches ~25 MB on a cold cache

BAD_CALL = """
import createClient from "openapi-fetch";
import type { paths } from "./api";
const client = createClient<paths>({ baseUrl: "http://127.0.0.1:8000" });
export const wrong = client.POST("/suggest", { body: { points: [[0, 0, 0]], k: "five" } });
"""


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, cwd=cwd, capture_output=True, text=True, timeout=NPM_TIMEOUT)


@pytest.fixture(scope="module")
def project(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with the npm tools installed, the generated ``api.d.ts`` and the calls."""
    if shutil.which("npm") is None or shutil.which("npx") is None:
        pytest.fail("no npm: install Debian's nodejs and npm packages (README.md; .ci/run does this in CI)",
                    pytrace=False)
    folder = tmp_path_factory.mktemp("ts-client")
    for name in ("package.json", "package-lock.json", "tsconfig.json", "call.ts"):
        shutil.copy(HERE / name, folder / name)
    (folder / "openapi.json").write_text(json.dumps(create_app(Settings()).openapi()))
    installed = _run(["npm", "ci", "--no-audit", "--no-fund"], folder)
    assert installed.returncode == 0, installed.stderr[-3000:]
    # --default-non-nullable false: openapi-typescript 7 otherwise makes every field that has a
    # default required, in request bodies too (a /suggest body would need collapse_duplicates).
    generated = _run(["npx", "--no-install", "openapi-typescript", "openapi.json", "-o", "api.d.ts",
                      "--default-non-nullable", "false"], folder)
    assert generated.returncode == 0, generated.stderr[-3000:]
    return folder


def test_generated_client_and_calls_type_check(project: Path) -> None:
    api = (project / "api.d.ts").read_text()
    assert '"/suggest"' in api and "ErrorResponse" in api
    checked = _run(["npx", "--no-install", "tsc", "-p", "."], project)
    assert checked.returncode == 0, checked.stdout[-3000:] + checked.stderr[-3000:]


def test_a_wrongly_typed_call_does_not_compile(project: Path) -> None:
    (project / "bad.ts").write_text(BAD_CALL)
    checked = _run(["npx", "--no-install", "tsc", "--noEmit", "--strict", "--skipLibCheck",
                    "--moduleResolution", "bundler", "--module", "esnext", "--target", "es2022",
                    "--lib", "es2022,dom", "bad.ts"], project)
    assert checked.returncode != 0, checked.stdout
    assert "bad.ts" in checked.stdout and "TS2" in checked.stdout, checked.stdout
