"""Artifacts that give h its own point count (manifest ``placement_points``): h takes that many
points of every query (suggest, place, mesh uploads, assembly) and of every added part, while f
and g keep the manifest's ``n_points``. Checked on a copy of the shipped folder whose manifest
asks h for twice the networks' points (the shipped model's own count since stop 49), and on a copy
without the key, a format-1 folder, whose h takes the networks' count as before.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from catalog_testkit import add_part, writable_settings
from fastapi.testclient import TestClient
from service_testkit import multi_part_shapes

from service.api.app import create_app
from service.artifacts.layout import ArtifactError, read_manifest, write_manifest
from service.artifacts.loading import Artifacts, load_artifacts

REPO = Path(__file__).resolve().parents[2]


def copy_with_manifest(src: Path, dst: Path, drop: tuple[str, ...] = (), **changes: Any) -> Path:
    """The folder's files linked, its manifest rewritten without ``drop`` and with ``changes``
    (fresh checksums)."""
    dst.mkdir()
    for f in src.iterdir():
        if f.name != "manifest.json":
            (dst / f.name).symlink_to(f.resolve())
    manifest = read_manifest(src, verify_checksums=False)
    write_manifest(dst, {**{k: v for k, v in manifest.items() if k not in ("files", "format_version", *drop)},
                         **changes})
    return dst


@pytest.fixture(scope="module")
def h_client(artifacts: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    n = int(read_manifest(artifacts, verify_checksums=False)["n_points"])
    folder = copy_with_manifest(artifacts, tmp_path_factory.mktemp("h") / "artifacts", placement_points=2 * n)
    settings = writable_settings(folder, tmp_path_factory.mktemp("h-data"))
    with TestClient(create_app(settings)) as c:
        yield c


class Inputs:
    """The point clouds the networks of an engine are given, recorded as (graph, distinct points)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch, networks: Any) -> None:
        self.seen: list[tuple[str, int, int]] = []
        for name in ("mixture", "query_features", "part_features", "embed"):
            original = getattr(networks, name)
            monkeypatch.setattr(networks, name, self._spy(name, original))

    def _spy(self, name: str, original: Any) -> Any:
        def spy(points: np.ndarray, *args: Any) -> Any:
            for cloud in points:
                self.seen.append((name, len(cloud), len(np.unique(cloud, axis=0))))
            return original(points, *args)
        return spy

    def counts(self, name: str) -> set[tuple[int, int]]:
        return {(n, distinct) for graph, n, distinct in self.seen if graph == name}


def engine_of(client: TestClient) -> Any:
    return client.app.state.served.engine  # type: ignore[attr-defined]


@pytest.fixture(scope="module")
def format1_client(artifacts: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    """The shipped folder without ``placement_points``: a format-1 folder."""
    folder = copy_with_manifest(artifacts, tmp_path_factory.mktemp("f1") / "artifacts",
                                drop=("placement_points",))
    settings = writable_settings(folder, tmp_path_factory.mktemp("f1-data"))
    with TestClient(create_app(settings)) as c:
        yield c


def test_a_folder_without_the_key_gives_h_the_networks_count(artifacts: Path, tmp_path: Path) -> None:
    folder = copy_with_manifest(artifacts, tmp_path / "one", drop=("placement_points",))
    loaded = load_artifacts(folder)
    assert "placement_points" not in loaded.manifest and loaded.manifest["format_version"] == 1
    assert loaded.placement_points == loaded.query_points == loaded.n_points
    shipped = load_artifacts(artifacts, verify_checksums=False)
    assert shipped.placement_points == int(shipped.manifest.get("placement_points", shipped.n_points))


def test_a_format_1_folder_gives_h_the_networks_points(format1_client: TestClient,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    engine = engine_of(format1_client)
    n = engine.artifacts.n_points
    inputs = Inputs(monkeypatch, engine.networks)
    mesh = (REPO / "examples" / "chair-without-legs.obj").read_bytes()
    r = format1_client.post("/suggest/mesh", files={"file": ("chair.obj", mesh)},
                            data={"options": json.dumps({"k": 3, "category": "chair"})})
    assert r.status_code == 200, r.text
    assert inputs.counts("query_features") == inputs.counts("mixture") == {(n, n)}
    assert format1_client.get("/model").json()["placement_points"] == n


@pytest.mark.parametrize("value", [0, -5, "many", 2.5])
def test_a_bad_placement_count_is_refused_naming_the_manifest(artifacts: Path, tmp_path: Path,
                                                               value: Any) -> None:
    folder = copy_with_manifest(artifacts, tmp_path / "bad", placement_points=value)
    with pytest.raises(ArtifactError, match="placement_points must be a positive integer") as info:
        load_artifacts(folder)
    assert str(folder / "manifest.json") in str(info.value)


def test_placement_points_come_with_format_2(artifacts: Path, tmp_path: Path) -> None:
    """A manifest with placement_points is written as format 2, which a format-1 reader refuses
    (it would give h the wrong count); one without stays format 1; format 1 claiming the key is refused."""
    n = int(read_manifest(artifacts, verify_checksums=False)["n_points"])
    folder = copy_with_manifest(artifacts, tmp_path / "two", placement_points=2 * n)
    assert read_manifest(folder)["format_version"] == 2
    one = copy_with_manifest(artifacts, tmp_path / "one", drop=("placement_points",))
    assert read_manifest(one)["format_version"] == 1
    manifest = json.loads((folder / "manifest.json").read_text())
    (folder / "manifest.json").write_text(json.dumps({**manifest, "format_version": 1}))
    with pytest.raises(ArtifactError, match="placement_points needs format_version 2"):
        read_manifest(folder)


def test_suggest_and_place_give_h_its_own_count(h_client: TestClient,
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    engine = engine_of(h_client)
    art: Artifacts = engine.artifacts
    n, nh = art.n_points, art.placement_points
    assert nh == 2 * n and art.query_points == nh
    cat = engine.catalog
    # A whole shape's stored samples (distinct points, more than h takes), less its last part.
    shape = next(s for s in multi_part_shapes(cat, 50) if sum(r["shape_id"] == s for r in cat.records) >= 4)
    rows = [i for i, r in enumerate(cat.records) if r["shape_id"] == shape][:-1]
    points = np.concatenate([cat.part_points(i) + cat.translations[i] for i in rows])
    assert len(np.unique(points, axis=0)) > nh
    inputs = Inputs(monkeypatch, engine.networks)
    r = h_client.post("/suggest", json={"points": points.tolist(), "k": 5})
    assert r.status_code == 200, r.text
    suggestions = r.json()["suggestions"]
    assert suggestions and all(np.isfinite(s["translation"]).all() for s in suggestions)
    assert inputs.counts("mixture") == {(n, n)}
    assert inputs.counts("query_features") == {(nh, nh)}
    assert h_client.get("/model").json()["placement_points"] == nh
    inputs.seen.clear()
    placed = h_client.post("/place", json={"points": points.tolist(),
                                           "part_ids": [suggestions[0]["part_id"]]})
    assert placed.status_code == 200, placed.text
    assert inputs.counts("query_features") == {(nh, nh)}


def test_a_mesh_upload_is_sampled_for_h(h_client: TestClient, monkeypatch: pytest.MonkeyPatch) -> None:
    engine = engine_of(h_client)
    n, nh = engine.artifacts.n_points, engine.artifacts.placement_points
    inputs = Inputs(monkeypatch, engine.networks)
    mesh = (REPO / "examples" / "chair-without-legs.obj").read_bytes()
    r = h_client.post("/suggest/mesh", files={"file": ("chair.obj", mesh)},
                      data={"options": json.dumps({"k": 3, "category": "chair"})})
    assert r.status_code == 200, r.text
    # nh distinct surface samples reach h (not n samples repeated), n of them reach g.
    assert inputs.counts("query_features") == {(nh, nh)}
    assert inputs.counts("mixture") == {(n, n)}


def test_an_assembly_queries_with_enough_points_for_h(h_client: TestClient,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    engine = engine_of(h_client)
    n, nh = engine.artifacts.n_points, engine.artifacts.placement_points
    inputs = Inputs(monkeypatch, engine.networks)
    r = h_client.post("/assemble", json={"part_id": engine.catalog.part_ids[0], "max_parts": 3})
    assert r.status_code == 200, r.text
    assert r.json()["steps"]
    assert {count for count, _distinct in inputs.counts("query_features")} == {nh}
    assert {count for count, _distinct in inputs.counts("mixture")} == {n}


def test_an_added_part_gets_h_features_from_hs_count(h_client: TestClient,
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    engine = engine_of(h_client)
    n, nh = engine.artifacts.n_points, engine.artifacts.placement_points
    inputs = Inputs(monkeypatch, engine.networks)
    r = add_part(h_client, seed=3)
    assert r.status_code == 201, r.text
    assert inputs.counts("embed") == {(n, n)}
    assert inputs.counts("part_features") == {(nh, nh)}
