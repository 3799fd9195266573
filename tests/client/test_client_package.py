"""clients/python works with httpx and numpy alone: none of the server's packages are needed.

The client runs in a subprocess where the server's dependencies (and this repository's
``service`` and ``training``) cannot be imported, against the real service on a free port.
"""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from pathlib import Path

import pytest
import tomllib

warnings.filterwarnings("ignore", message=".*httpx.*starlette.testclient.*")

from fastapi.testclient import TestClient  # noqa: E402

from service.api.app import create_app  # noqa: E402
from service.settings import DEFAULT_ARTIFACTS, Settings  # noqa: E402

REPO = Path(__file__).resolve().parents[2]
CLIENT = REPO / "clients" / "python"
EXAMPLE = REPO / "examples" / "chair-without-legs.json"
SERVER_ONLY = ["onnxruntime", "faiss", "scipy", "trimesh", "fastapi", "starlette", "uvicorn", "orjson",
               "pydantic", "torch", "service", "training"]

# The client with the server's packages made unimportable, on the example request.
ALONE = """
import json, sys
class ServerOnly:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {blocked!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}} (blocked)", name=name)
sys.meta_path.insert(0, ServerOnly())
import numpy as np
from complementme_client import ClientError, ComplementMeClient
request = json.load(open({example!r}))
with ComplementMeClient(sys.argv[1], timeout=60) as client:
    answer = client.suggest(np.array(request["points"], dtype=np.float32), k=request["k"],
                            category=request["category"])
    try:
        client.suggest(np.zeros((3, 3), dtype=np.float32))
    except ClientError as exc:
        refused = [exc.status, exc.code]
print(json.dumps({{"answer": answer, "refused": refused,
                  "loaded": sorted(m for m in sys.modules if m.split(".")[0] in {blocked!r})}}))
"""


def test_client_needs_only_httpx_and_numpy() -> None:
    with open(CLIENT / "pyproject.toml", "rb") as fh:
        deps = tomllib.load(fh)["project"]["dependencies"]
    assert sorted(d.split(">")[0].split("=")[0] for d in deps) == ["httpx", "numpy"]


@pytest.fixture(scope="module")
def settings() -> Settings:
    if not (DEFAULT_ARTIFACTS / "manifest.json").is_file():
        pytest.skip(f"no artifact folder at {DEFAULT_ARTIFACTS}")
    return Settings(artifacts=DEFAULT_ARTIFACTS, onnx_threads=1, faiss_threads=1, seed=0)


@pytest.fixture(scope="module")
def live_url(settings: Settings,
             serve_in_thread: Callable[..., AbstractContextManager[int]]) -> Iterator[str]:
    with serve_in_thread(create_app(settings)) as port:
        yield f"http://127.0.0.1:{port}"


def test_client_alone_against_the_service(live_url: str, settings: Settings) -> None:
    code = ALONE.format(blocked=SERVER_ONLY, example=str(EXAMPLE))
    done = subprocess.run([sys.executable, "-c", code, live_url], cwd=CLIENT, capture_output=True, text=True,
                          timeout=120, env={"PYTHONPATH": str(CLIENT), "PATH": "/usr/bin:/bin"})
    assert done.returncode == 0, done.stderr[-3000:]
    out = json.loads(done.stdout)
    assert out["loaded"] == []
    assert out["refused"] == [422, "too_few_points"]
    with TestClient(create_app(settings)) as direct:
        expected = direct.post("/suggest", json=json.loads(EXAMPLE.read_text())).json()
    got = [s["part_id"] for s in out["answer"]["suggestions"]]
    assert got == [s["part_id"] for s in expected["suggestions"]]
