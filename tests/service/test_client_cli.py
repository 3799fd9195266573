"""The Python client and the `suggest` / `batch` commands against a live uvicorn server."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from pathlib import Path

import httpx
import numpy as np
import pytest
import trimesh
import typer
from fastapi.testclient import TestClient
from service_testkit import AssemblyQuery
from typer.testing import CliRunner

from service.api.app import create_app
from service.artifacts.catalog import Catalog
from service.serve.cli import register_service_commands
from service.serve.client import ClientError, ComplementMeClient, read_points_file
from service.settings import Settings


@pytest.fixture(scope="module")
def live_url(settings: Settings,
             serve_in_thread: Callable[..., AbstractContextManager[int]]) -> Iterator[str]:
    with serve_in_thread(create_app(settings)) as port:
        yield f"http://127.0.0.1:{port}"


@pytest.fixture(scope="module")
def cli() -> typer.Typer:
    app = typer.Typer()
    register_service_commands(app)
    return app


def test_client_routes(live_url: str, client: TestClient, query: AssemblyQuery, catalog: Catalog) -> None:
    with ComplementMeClient(live_url, timeout=30) as c:
        assert c.ready()
        answer = c.suggest(query.points, k=4, category=None)
        direct = client.post("/suggest", json={"points": query.points.tolist(), "k": 4}).json()
        assert answer == direct
        ids = [s["part_id"] for s in answer["suggestions"]]
        assert [p["part_id"] for p in c.place(query.points, ids)["placements"]] == ids
        batch = c.suggest_batch([query.points, query.points[:2]], k=2)
        assert [r["ok"] for r in batch["results"]] == [True, False]
        assert c.part(ids[0])["part_id"] == ids[0]
        assert c.part_mesh(ids[0], "obj").startswith(b"#") or b"v " in c.part_mesh(ids[0], "obj")
        assert c.model()["part_count"] == len(catalog)
        with pytest.raises(ClientError) as info:
            c.suggest(query.points[:3])
        assert info.value.status == 422 and info.value.code == "too_few_points"


def test_client_retries_connection_errors() -> None:
    attempts = []
    with ComplementMeClient("http://127.0.0.1:9", timeout=2, retries=2, backoff=0.01) as c:
        c.http.event_hooks["request"].append(attempts.append)
        with pytest.raises(ClientError) as info:
            c.model()
        assert info.value.code == "unreachable" and len(attempts) == 3
        assert not c.ready()


def test_client_retries_503_and_429_then_succeeds() -> None:
    # A stand-in server that is not ready, then refuses the client for its errors, then answers.
    answers = iter([503, 503, 429, 200])

    def handler(request: httpx.Request) -> httpx.Response:
        status = next(answers)
        if status == 503:
            return httpx.Response(503, json={"error": {"code": "not_ready", "message": "loading"}})
        if status == 429:
            return httpx.Response(429, json={"error": {"code": "too_many_errors", "message": "later"}},
                                  headers={"Retry-After": "0"})
        return httpx.Response(200, json={"model_version": "v"})

    transport = httpx.MockTransport(handler)
    with ComplementMeClient("http://svc", retries=3, backoff=0.01, transport=transport) as c:
        assert c.model() == {"model_version": "v"}


def test_client_gives_up_after_retries_on_503() -> None:
    def handler(request: httpx.Request) -> httpx.Response:
        return httpx.Response(503, json={"error": {"code": "not_ready", "message": "loading"}})

    transport = httpx.MockTransport(handler)
    with ComplementMeClient("http://svc", retries=1, backoff=0.01, transport=transport) as c, \
            pytest.raises(ClientError) as info:
        c.model()
    assert info.value.status == 503 and info.value.code == "not_ready"


def test_read_points_files(tmp_path: Path) -> None:
    pts = np.random.default_rng(0).normal(size=(40, 3)).astype(np.float32)
    np.save(tmp_path / "a.npy", pts)
    np.testing.assert_array_equal(read_points_file(tmp_path / "a.npy"), pts)
    lines = ["40", "# x y z nx ny nz"] + [" ".join(f"{v:.9g}" for v in p) + " 0 0 1" for p in pts]
    (tmp_path / "a.xyz").write_text("\n".join(lines))
    np.testing.assert_allclose(read_points_file(tmp_path / "a.xyz"), pts, rtol=1e-6)
    (tmp_path / "bad.pts").write_text("1 2 3\n4 5\n")
    with pytest.raises(ValueError, match=r"bad\.pts"):
        read_points_file(tmp_path / "bad.pts")
    np.save(tmp_path / "flat.npy", pts.ravel())
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        read_points_file(tmp_path / "flat.npy")


def _query_files(folder: Path, query: AssemblyQuery) -> None:
    folder.mkdir()
    np.save(folder / "a.npy", query.points)
    np.savetxt(folder / "b.xyz", query.points)
    trimesh.PointCloud(query.points).convex_hull.export(folder / "c.obj")
    (folder / "d.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    (folder / "ignored.md").write_text("not a query")


def test_suggest_command_prints_a_ranked_table(live_url: str, cli: typer.Typer, tmp_path: Path,
                                               query: AssemblyQuery, client: TestClient) -> None:
    np.save(tmp_path / "q.npy", query.points)
    result = CliRunner().invoke(cli, ["suggest", str(tmp_path / "q.npy"), "--url", live_url, "-k", "3"])
    assert result.exit_code == 0, result.output
    expected = client.post("/suggest", json={"points": query.points.tolist(), "k": 3}).json()
    lines = result.output.strip().splitlines()
    assert lines[1].startswith("frame: centre [0, 0, 0], radius 1, up y")
    assert lines[2].split()[:2] == ["rank", "part_id"]
    assert [line.split()[1] for line in lines[3:]] == [s["part_id"] for s in expected["suggestions"]]
    args = ["suggest", str(tmp_path / "q.npy"), "--url", live_url]
    as_json = CliRunner().invoke(cli, [*args, "-k", "3", "--json"])
    assert json.loads(as_json.output) == expected
    frame = ["--up-axis", "z", "--center", "1,2,3", "--radius", "2"]
    framed = CliRunner().invoke(cli, [*args, *frame, "--json"])
    assert json.loads(framed.output)["frame"]["center"] == [1.0, 2.0, 3.0]
    failed = CliRunner().invoke(cli, [*args, "-k", "0"])
    assert failed.exit_code == 1 and "k_out_of_range" in failed.output
    # --fit: the service estimates the frame (here: of canonical points, up axis kept) and says so.
    fitted = CliRunner().invoke(cli, [*args, "--fit", "--up-axis", "y", "-k", "3"])
    assert fitted.exit_code == 0, fitted.output
    assert fitted.output.splitlines()[1].startswith("frame (fitted): centre [")
    assert fitted.output.splitlines()[1].endswith("up y")
    # A mesh without a frame is fitted by the service's default; --no-fit reads it canonical.
    mesh = tmp_path / "q.obj"
    trimesh.PointCloud(query.points).convex_hull.export(mesh)
    default = CliRunner().invoke(cli, ["suggest", str(mesh), "--url", live_url, "-k", "3"])
    assert default.exit_code == 0, default.output
    assert default.output.splitlines()[1].startswith("frame (fitted)"), default.output
    declined = CliRunner().invoke(cli, ["suggest", str(mesh), "--url", live_url, "-k", "3", "--no-fit"])
    assert declined.exit_code == 0, declined.output
    assert declined.output.splitlines()[1].startswith("frame: centre [0, 0, 0], radius 1, up y")


def test_batch_command_writes_json_lines(live_url: str, cli: typer.Typer, tmp_path: Path,
                                         query: AssemblyQuery) -> None:
    _query_files(tmp_path / "in", query)
    out = tmp_path / "results.jsonl"
    result = CliRunner().invoke(cli, ["batch", str(tmp_path / "in"), "--url", live_url, "--out", str(out),
                                      "--concurrency", "2", "-k", "2"])
    assert result.exit_code == 1, result.output  # one file is broken
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    by_file = {Path(line["file"]).name: line for line in lines}
    assert sorted(by_file) == ["a.npy", "b.xyz", "c.obj", "d.ply"]
    assert [by_file[n]["ok"] for n in ("a.npy", "b.xyz", "c.obj")] == [True, True, True]
    assert by_file["d.ply"]["error"]["code"] == "corrupt_mesh"
    assert len(by_file["a.npy"]["result"]["suggestions"]) == 2
    assert "3 answered, 1 failed" in result.output


EXAMPLE_REQUEST = Path(__file__).resolve().parents[2] / "examples" / "chair-without-legs.json"


def test_suggest_command_reads_the_example_request(live_url: str, cli: typer.Typer,
                                                   client: TestClient) -> None:
    # The README's shipped request file: sent as it is (its k and category), -k overriding its k.
    request = json.loads(EXAMPLE_REQUEST.read_text())
    result = CliRunner().invoke(cli, ["suggest", str(EXAMPLE_REQUEST), "--url", live_url, "--json"])
    assert result.exit_code == 0, result.output
    assert json.loads(result.output) == client.post("/suggest", json=request).json()
    fewer = CliRunner().invoke(cli, ["suggest", str(EXAMPLE_REQUEST), "--url", live_url, "--json", "-k", "2"])
    assert len(json.loads(fewer.output)["suggestions"]) == 2


def test_suggest_command_refuses_a_bad_file_in_one_line(live_url: str, cli: typer.Typer,
                                                        tmp_path: Path) -> None:
    for name, text in (("other.json", '{"items": []}'), ("broken.json", "{"), ("bad.xyz", "1 2\n")):
        (tmp_path / name).write_text(text)
        result = CliRunner().invoke(cli, ["suggest", str(tmp_path / name), "--url", live_url])
        assert result.exit_code == 1, result.output
        assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
        assert result.output.startswith(f"error: {tmp_path / name}: ") and result.output.count("\n") == 1


def test_batch_command_lists_what_it_skipped(live_url: str, cli: typer.Typer, tmp_path: Path,
                                             query: AssemblyQuery) -> None:
    folder = tmp_path / "in"
    folder.mkdir()
    np.save(folder / "a.npy", query.points)
    (folder / "b.json").write_text(json.dumps({"points": query.points.tolist(), "k": 3}))
    (folder / "notes.md").write_text("not a query")
    (folder / "more").mkdir()
    out = tmp_path / "results.jsonl"
    result = CliRunner().invoke(cli, ["batch", str(folder), "--url", live_url, "--out", str(out)])
    assert result.exit_code == 0, result.output
    by_file = {Path(line["file"]).name: line for line in map(json.loads, out.read_text().splitlines())}
    assert sorted(by_file) == ["a.npy", "b.json"]
    assert len(by_file["b.json"]["result"]["suggestions"]) == 3
    assert f"skipped {folder / 'more'}: a folder" in result.output
    assert f"skipped {folder / 'notes.md'}: not a mesh, point or request file (.md)" in result.output
    assert "2 answered, 0 failed, 2 skipped" in result.output
