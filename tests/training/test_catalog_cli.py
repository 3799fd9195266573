"""`complementme catalog add` (to a data folder or a running service) and `catalog backup`."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from service.catalog_store.store import CatalogStore
from service.settings import DEFAULT_ARTIFACTS
from training.catalog_cli import catalog_app
from training.catalog_import import shape_components

KEY = "catalog-cli-test-key-000"
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def artifacts() -> Path:
    folder = Path(os.environ.get("COMPLEMENTME_TEST_ARTIFACTS") or DEFAULT_ARTIFACTS)
    if not (folder / "manifest.json").is_file():
        pytest.skip(f"no artifact folder at {folder} (set COMPLEMENTME_TEST_ARTIFACTS or export one)")
    return folder


def _stool(path: Path, seat: float, legs: float) -> None:
    """A GLB scene: a seat, a back and four identical legs (one component after merging)."""
    scene = trimesh.Scene()
    at = trimesh.transformations.translation_matrix
    scene.add_geometry(trimesh.creation.box((seat, 0.06, seat)), node_name="seat",
                       transform=at((0, legs + 0.03, 0)))
    scene.add_geometry(trimesh.creation.box((seat, 0.4, 0.05)), node_name="back",
                       transform=at((0, legs + 0.26, -seat / 2 + 0.025)))
    leg = trimesh.creation.box((0.05, legs, 0.05))
    for i, (sx, sz) in enumerate(((-1, -1), (-1, 1), (1, -1), (1, 1))):
        scene.add_geometry(leg, geom_name="leg", node_name=f"leg{i}",
                           transform=at((sx * (seat / 2 - 0.025), legs / 2, sz * (seat / 2 - 0.025))))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(scene.export(file_type="glb"))


@pytest.fixture()
def shapes(tmp_path: Path) -> Path:
    folder = tmp_path / "shapes"
    _stool(folder / "stool" / "tall.glb", 0.4, 0.6)
    _stool(folder / "stool" / "low.glb", 0.5, 0.3)
    (folder / "stool" / "broken.obj").write_text("v 0 0 0\nthis is not an obj\n")
    return folder


def test_components_follow_the_preprocessing(shapes: Path) -> None:
    shape_id, category, _, comps = shape_components(shapes / "stool" / "tall.glb", "stool")
    assert (shape_id, category, len(comps)) == ("tall", "stool", 3), "seat, back, and the legs merged"
    allv = np.concatenate([c.vertices for c in comps])
    centre = (allv.min(0) + allv.max(0)) / 2
    assert np.allclose(centre, 0, atol=1e-5) and np.isclose(np.linalg.norm(allv - centre, axis=1).max(), 1.0)


def test_add_to_a_data_folder_resumes_and_reports(artifacts: Path, shapes: Path, tmp_path: Path) -> None:
    data = tmp_path / "data"
    runner = CliRunner()
    args = ["add", str(shapes), "--data-dir", str(data), "--artifacts", str(artifacts),
            "--report", str(tmp_path / "report.json")]
    result = runner.invoke(catalog_app, args)
    assert result.exit_code == 1, result.output  # one file skipped
    assert "6 part(s) added from 2 file(s)" in result.output and "broken.obj" in result.output
    store = CatalogStore(data)
    parts = store.parts()
    assert sorted(p.part_id for p in parts) == [f"{s}/{i}" for s in ("low", "tall") for i in range(3)]
    assert {p.category for p in parts} == {"stool"}
    store.close()
    again = runner.invoke(catalog_app, args)
    assert "0 part(s) added" in again.output and "2 shape(s) already in the catalog" in again.output
    backup = runner.invoke(catalog_app, ["backup", str(data), str(tmp_path / "copy")])
    assert backup.exit_code == 0, backup.output
    copy = CatalogStore(tmp_path / "copy")
    assert len(copy.parts()) == 6 and all(copy.read_geometry(p) is not None for p in copy.parts())
    copy.close()


@pytest.fixture()
def live_url(artifacts: Path, tmp_path: Path) -> Iterator[str]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {k: v for k, v in os.environ.items() if not k.startswith("COMPLEMENTME_")}
    env.update(COMPLEMENTME_ARTIFACTS=str(artifacts), COMPLEMENTME_DATA_DIR=str(tmp_path / "served"),
               COMPLEMENTME_API_KEY=KEY, COMPLEMENTME_VERIFY_CHECKSUMS="false", PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-m", "uvicorn", "--factory", "service.api.app:create_app",
                             "--port", str(port), "--log-level", "warning"], env=env, cwd=REPO)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while True:
            assert proc.poll() is None and time.monotonic() < deadline, "the server did not start"
            try:
                if httpx.get(url + "/readyz").status_code == 200:
                    break
            except httpx.HTTPError:
                time.sleep(0.1)
        yield url
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)


def test_add_through_the_api(live_url: str, shapes: Path) -> None:
    runner = CliRunner()
    refused = runner.invoke(catalog_app, ["add", str(shapes), "--url", live_url, "--api-key", "wrong-key"])
    assert refused.exit_code == 2 and "invalid_credentials" in refused.output
    result = runner.invoke(catalog_app, ["add", str(shapes), "--url", live_url, "--api-key", KEY])
    assert result.exit_code == 1 and "6 part(s) added" in result.output, result.output
    query = np.random.default_rng(0).uniform(-0.5, 0.5, (128, 3)).tolist()
    answer = httpx.post(live_url + "/suggest", json={"points": query, "category": "stool", "k": 10}).json()
    expected = {f"{s}/{i}" for s in ("low", "tall") for i in range(3)}
    assert {s["part_id"] for s in answer["suggestions"]} == expected
    assert httpx.get(live_url + "/parts/tall/0").json()["name"] == "tall.glb component 0"
