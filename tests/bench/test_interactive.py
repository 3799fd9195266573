"""The interactive-paths benchmark: its query mesh, its /metrics arithmetic, and one quick run end to end."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from bench_testkit import quick_bench_run

from bench.interactive_bench import PATHS, histogram_means, histogram_totals, refine_to_faces
from bench.report import INTERACTIVE_LABELS, render_results


def test_refining_reaches_the_face_count_and_keeps_the_surface() -> None:
    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    v, f = refine_to_faces(box.vertices, box.faces, 1000)
    assert 1000 <= len(f) <= 1002
    assert trimesh.Trimesh(v, f, process=False).area == pytest.approx(box.area)
    again = refine_to_faces(box.vertices, box.faces, 1000)
    np.testing.assert_array_equal(f, again[1])  # deterministic
    np.testing.assert_array_equal(v, again[0])
    same = refine_to_faces(box.vertices, box.faces, 5)  # already enough faces: unchanged
    assert len(same[1]) == len(box.faces)


METRICS = """\
# HELP complementme_search_duration_seconds FAISS search.
# TYPE complementme_search_duration_seconds histogram
complementme_search_duration_seconds_bucket{le="+Inf"} %(n)d
complementme_search_duration_seconds_count %(n)d
complementme_search_duration_seconds_sum %(s)f
# HELP complementme_http_request_duration_seconds Requests.
# TYPE complementme_http_request_duration_seconds histogram
complementme_http_request_duration_seconds_bucket{le="+Inf",method="GET",route="/metrics",status="200"} %(n)d
complementme_http_request_duration_seconds_count{method="GET",route="/metrics",status="200"} %(n)d
complementme_http_request_duration_seconds_sum{method="GET",route="/metrics",status="200"} %(s)f
complementme_http_request_duration_seconds_bucket{le="+Inf",method="POST",route="/place",status="200"} %(n)d
complementme_http_request_duration_seconds_count{method="POST",route="/place",status="200"} %(n)d
complementme_http_request_duration_seconds_sum{method="POST",route="/place",status="200"} %(s)f
# HELP complementme_batch_size Queries per engine call.
# TYPE complementme_batch_size histogram
complementme_batch_size_bucket{le="+Inf"} %(n)d
complementme_batch_size_count %(n)d
complementme_batch_size_sum %(b)f
"""


def test_histogram_means_over_two_snapshots() -> None:
    before = histogram_totals(METRICS % {"n": 10, "s": 1.0, "b": 10})
    after = histogram_totals(METRICS % {"n": 14, "s": 1.2, "b": 22})
    means = histogram_means(before, after)
    assert means["search"] == {"count": 4, "mean_ms": pytest.approx(50.0)}
    assert means["batch_size"] == {"count": 4, "mean": pytest.approx(3.0)}
    assert means["http_request{method=POST,route=/place,status=200}"]["mean_ms"] == pytest.approx(50.0)
    assert not any("/metrics" in key for key in means)  # the snapshots' own requests
    assert histogram_means(after, after) == {}


def test_quick_run_answers_every_path_and_writes_the_results(tmp_path: Path) -> None:
    data = quick_bench_run("interactive", tmp_path)
    cfg, r = data["config"], data["results"]
    assert cfg["requests"] == 3 and cfg["target_faces"] == 100_000
    assert cfg["target_faces"] <= r["mesh"]["faces"] <= cfg["target_faces"] + 2
    assert r["mesh"]["bytes"]["glb"] > 0 and r["mesh"]["bytes"]["obj"] > 0
    assert set(r["paths"]) == set(PATHS)
    for name, row in r["paths"].items():
        assert row["statuses"] == {"200": cfg["requests"]}, (name, row["errors"])
        assert row["latency"]["n"] == cfg["requests"]
        assert row["latency"]["p50_ms"] <= row["latency"]["p99_ms"] <= row["latency"]["max_ms"]
        routes = [k for k in row["server_metrics"] if k.startswith("http_request{")]
        assert len(routes) == 1 and row["server_metrics"][routes[0]]["count"] == cfg["requests"], name
    for name in ("suggest_mesh_glb", "suggest_mesh_obj", "suggest_mesh_glb_body", "suggest_mesh_obj_body",
                 "suggest_mesh_glb_fit", "suggest_contact_off", "suggest_contact_on"):
        assert r["paths"][name]["answer"]["suggestions"] == 10, name
        assert "inference{graph=g}" in r["paths"][name]["server_metrics"], name
    for fmt in ("glb", "obj"):  # the file as the body is the same query as the form
        assert r["paths"][f"suggest_mesh_{fmt}_body"]["answer"] == r["paths"][f"suggest_mesh_{fmt}"]["answer"]
    assert r["paths"]["place_5"]["answer"] == {"placements": 5}
    assert len(r["place_parts"]) == 5
    assert r["paths"]["assemble"]["answer"]["nodes"] >= 2
    assert {"suggest", "contact", "total"} <= set(r["paths"]["assemble"]["answer_timings"])
    first = r["assemble_first"]  # each category's first /assemble after the start, one call each
    assert len(first["ms"]) == 9 and set(first["ms"]) == set(first["starts"])
    assert all(part.startswith(f"{cat}-") for cat, part in first["starts"].items())
    assert all(ms > 0 for ms in first["ms"].values())
    for fmt in ("glb", "obj"):
        assert set(r["mesh_stages_in_process"][fmt]) == {"parse", "sample", "collect", "upload_sample"}
    assert "contact" in r["engine_stages_in_process"]["suggest_contact_on"]
    assert all(len(r["load_average"][k]) == 3 for k in ("start", "end"))

    text = render_results({"interactive": data})
    assert "### e. Interactive paths at concurrency 1 (issue 20)" in text
    assert "each category's first call after the server started" in text
    for label in INTERACTIVE_LABELS.values():
        assert f"| {label} | {cfg['requests']} / {cfg['requests']} |" in text
