"""The report renderer on a fixed results dict, and writing it into docs/performance.md."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from bench.report import BEGIN, END, framework_target, render_results, targets, write_report
from bench.results import load_results, save_result

DOC = Path(__file__).resolve().parents[2] / "docs" / "performance.md"


def _stat(p50: float, p99: float | None = None) -> dict[str, float]:
    return {"n": 100, "mean_ms": p50, "min_ms": p50, "p50_ms": p50, "p90_ms": p50,
            "p99_ms": p99 if p99 is not None else 2 * p50, "max_ms": 3 * p50}


MACHINE = {"cpu_model": "Test CPU 9000", "cpu_flags": ["avx2"], "cores": 2, "usable_cores": 2,
           "ram_gib": 24.0, "kernel": "6.1", "python": "3.11.7", "load_average_at_start": [0.1, 0.2, 0.3],
           "packages": {"onnxruntime": "1.31.1", "faiss-cpu": "1.15.1", "numpy": "2.0", "fastapi": "0.1",
                        "uvicorn": "0.3", "torch": "2.13.0"},
           "artifacts": {"model_version": "model-xyz", "created": "2026-11-22", "part_count": 7315,
                         "n_points": 512},
           "date": "2026-11-22T10:00:00+00:00", "command": "python -m bench all"}


def _level(body: str, c: int, rps: float, p50: float, p99: float, errors: int = 0) -> dict[str, Any]:
    return {"body": body, "connections": c, "requests": int(rps * 10), "throughput_rps": rps,
            "p50_ms": p50, "p90_ms": p50, "p99_ms": p99, "errors": errors, "non2xx": errors, "timeouts": 0,
            "socket_errors": 0,
            "statuses": {"200": int(rps * 10), **({"503": errors} if errors else {})}}


def _results() -> dict[str, dict[str, Any]]:
    stages = {k: _stat(v) for k, v in {"parse": 0.5, "validate": 0.6, "suggest": 2.5, "serialise": 0.2,
                                         "end_to_end": 3.8, "resample": 0.1}.items()}
    timings = {k: _stat(v) for k, v in {"prepare": 0.2, "g": 0.9, "search": 0.7, "contact": 0.4,
                                          "total": 2.5}.items()}
    variant = {"body": "json", "refine_contact": None, "contact_applied": False, "stages": stages,
               "engine_timings": timings,
               "body_bytes": 30000, "answer_bytes": 6000, "suggestions": 10, "top_part": "chair-0035/1"}
    engine = {"query": {"source": "x.json", "points": 1000, "k": 10}, "network_points": 512,
              "catalog_parts": 7315, "index": "IndexFlatL2", "settings": {}, "variants": [variant]}
    http = {"levels": [_level("json", 1, 200, 5.0, 7.0), _level("json", 32, 350, 80.0, 95.0),
                       _level("json", 64, 340, 90.0, 250.0, errors=12), _level("base64", 1, 220, 4.5, 6.0)]}
    row = {"search": _stat(0.5), "exact_search": _stat(0.6), "recall_k": 64, "recall_means": 512,
           "engine_timings": {"search": _stat(0.5)}, "top_part": "chair-0035/1"}
    query = {"body": "json", "refine_contact": None, "contact_applied": False}
    catalog = {"query": query, "n_modes": 8, "rows": [
        {**row, "parts": 7315, "kind": "shipped", "index": {"type": "IndexFlatL2", "params": {}},
         "build_seconds": None, "recall_at_k": 1.0, "engine": {"suggest": _stat(2.0)}},
        {**row, "parts": 1_000_000, "kind": "replicated", "build_seconds": 12.5, "recall_at_k": 0.93,
         "index": {"type": "IndexIVFFlat", "nlist": 4096, "nprobe": 24, "dim": 50},
         "engine": {"suggest": _stat(3.0)}}]}
    peer = {"sanity": {"peer_top": ["chair-0035/1"], "our_top": ["chair-0035/1"], "same_top_part": True},
            "peer": [_level("json", 1, 40, 25.0, 30.0), _level("json", 32, 30, 900.0, 1500.0)],
            "ours": [_level("json", 1, 200, 5.0, 7.0), _level("json", 32, 350, 80.0, 95.0)],
            "ratios": [{"connections": 1, "throughput": 5.0, "p50": 5.0, "p99": 30 / 7},
                       {"connections": 32, "throughput": 350 / 30, "p50": 11.25, "p99": 1500 / 95}]}
    cfg_load = {"duration": 10.0, "warmup": 3.0, "threads": 1, "timeout": 30.0}
    ours = [_level("json", 1, 180, 5.5, 8.0), _level("json", 32, 400, 75.0, 90.0)]
    answers = {"peer_ids": ["a", "b"], "our_ids": ["a", "b"], "same_ids": True, "max_translation_gap": 0.0,
               "match": True}

    def fw(version: str, rps32: float, p99: float, wait_ms: float) -> dict[str, Any]:
        levels = [_level("json", 1, 150, 6.0, 9.0), _level("json", 32, rps32, 100.0, p99)]
        return {"version": version, "config": {"max_batch_size": 32, "max_latency_ms": wait_ms},
                "answers": answers, "levels": levels,
                "ratios": [{"connections": 1, "throughput": 180 / 150, "p50": 6.0 / 5.5, "p99": 9.0 / 8.0},
                           {"connections": 32, "throughput": 400 / rps32, "p50": 100 / 75.0,
                            "p99": p99 / 90}]}

    framework = {"ours": ours, "peers": {"bentoml": fw("1.4.30", 200, 300.0, 1000.0),
                                         "litserve": fw("0.2.19", 320, 120.0, 2.0)}}
    configs = {"engine": {}, "http": {"load": cfg_load, "server_env": {}},
               "catalog": {"noise": 0.05, "index_kind": "auto", "recall_k": 64, "recall_queries": 63},
               "peer": {"load": cfg_load}, "framework": {"load": cfg_load, "workers": 2}}
    data = {"engine": engine, "http": http, "catalog": catalog, "peer": peer, "framework": framework}
    return {k: {"benchmark": k, "machine": MACHINE, "config": configs[k], "results": v}
            for k, v in data.items()}


def test_targets_are_judged_from_the_numbers() -> None:
    rows = {t: (m, ok) for t, m, ok in targets(_results())}
    assert rows["Engine p50 < 3 ms (1000 points, k = 10, shipped catalog)"] == ("2.50 ms", True)
    assert rows["HTTP at concurrency 1: p50 < 6 ms"][1] is True
    assert rows["Concurrency 32 (JSON body): >= 300 req/s, p99 < 100 ms, no errors"][1] is True
    assert rows[">= 10x the peer baseline's throughput at concurrency 32"] == ("11.7x", True)
    assert rows["1M parts: /suggest p50 at most 2x the shipped catalog's"][1] is True  # 3.0 vs 2.0 ms
    m, ok = rows["1M parts: recall@64 >= 0.95 against exact search"]
    assert (m, ok) == ("0.930", False)


def test_a_missed_latency_target_names_the_slowest_stages() -> None:
    res = _results()
    res["engine"]["results"]["variants"][0]["stages"]["suggest"] = _stat(4.0)
    m, ok = next((m, ok) for t, m, ok in targets(res) if t.startswith("Engine p50"))
    assert not ok and "slowest stages (p50): g 0.90 ms, search 0.70 ms, validate 0.60 ms" in m


def test_missing_benchmarks_are_not_measured() -> None:
    res = {"engine": _results()["engine"]}
    assert [ok for _, _, ok in targets(res)][1:] == [None] * 5
    text = render_results(res)
    assert "Not run (`python -m bench peer`)." in text


def test_rendered_tables_hold_the_numbers() -> None:
    text = render_results(_results())
    assert text.startswith(BEGIN) and text.rstrip().endswith(END)
    assert "Test CPU 9000" in text and "onnxruntime 1.31.1" in text and "`model-xyz`" in text
    assert "`python -m bench all`" in text and "2026-11-22T10:00:00+00:00" in text
    assert "| json | 64 | 3400 | 340 | 90.00 | 90.00 | 250 | 12 (12x 503) |" in text
    assert "| 1,000,000 | IndexIVFFlat nlist=4096, nprobe=24 | 12.5 |" in text
    assert "| 32 | 30.0 | 350 | 11.7x |" in text
    assert "our most likely part: **yes**" in text
    assert "| **end to end, in process** | 3.80 / 7.60 |" in text
    assert "| Stage | json, contact default (off) |" in text


def test_report_names_h_s_own_point_count_when_the_artifacts_give_one() -> None:
    res = _results()
    assert "h 512" not in render_results(res)        # n_points only: as before
    res["engine"]["results"]["placement_points"] = 1024
    res["engine"]["machine"] = {**MACHINE, "artifacts": {**MACHINE["artifacts"], "placement_points": 1024}}
    text = render_results(res)
    assert "the networks see 512 points, h 1024. " in text
    assert "512 network points, h 1024)" in text


def test_http_section_says_how_our_service_ran() -> None:
    res = _results()
    res["http"]["config"]["server_env"] = {"COMPLEMENTME_WORKERS": "2"}  # results from before issue 17
    assert "against `complementme serve` (2 worker processes)," in render_results(res)
    res["http"]["config"]["processes"] = 2  # since: one process per core behind HAProxy
    assert "against 2 x `complementme serve` behind HAProxy," in render_results(res)
    res["http"]["config"]["processes"] = 1
    assert "against `complementme serve` (one process)," in render_results(res)


def test_framework_section_judges_against_the_strongest_peer() -> None:
    res = _results()
    _, measured, ok = framework_target(res["framework"])
    # LitServe has more req/s at c = 32 than BentoML: 400 / 320 = 1.25x, short of 1.5x.
    assert ok is False
    assert measured.startswith("1.2x LitServe's throughput (400 vs 320 req/s), p99 90.00 vs 120")
    res["framework"]["results"]["peers"]["litserve"]["levels"][1]["throughput_rps"] = 250
    assert framework_target(res["framework"])[2] is True  # 400 / 250 = 1.6x, p99 90 < 120 ms
    text = render_results(res)
    assert "### f. Framework peers (issue 20)" in text
    assert "**BentoML 1.4.30** (max_batch_size 32, max_latency_ms 1000)" in text
    assert "**LitServe 0.2.19** (max_batch_size 32, batch_timeout 0.002 s)" in text
    assert "same top-2 part ids as ours **yes**" in text
    assert "| 32 | 200 | 400 | 2.0x | 100 / 300 | 75.00 / 90.00 | 1.3x | 3.3x | 0 / 0 |" in text


def test_report_replaces_only_the_generated_section(tmp_path: Path) -> None:
    doc = tmp_path / "performance.md"
    doc.write_text(DOC.read_text())
    before, after = DOC.read_text().split(BEGIN)[0], DOC.read_text().split(END)[1]
    write_report(doc, render_results(_results()))
    write_report(doc, render_results(_results()))  # idempotent
    text = doc.read_text()
    assert text.startswith(before) and text.endswith(after)
    assert text.count(BEGIN) == 1 and "Test CPU 9000" in text
    (tmp_path / "plain.md").write_text("# no markers\n")
    with pytest.raises(ValueError, match=r"plain\.md"):
        write_report(tmp_path / "plain.md", render_results({}))


def test_results_round_trip_through_json_files(tmp_path: Path) -> None:
    res = _results()
    for name, data in res.items():
        save_result(tmp_path, name, data["machine"], data["config"], data["results"])
    assert load_results(tmp_path) == json.loads(json.dumps(res))
    (tmp_path / "http.json").write_text("{")
    with pytest.raises(ValueError, match=r"http\.json"):
        load_results(tmp_path)
    with pytest.raises(ValueError, match="unknown benchmark"):
        save_result(tmp_path, "nope", {}, {}, {})
