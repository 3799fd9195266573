"""The balancer benchmark: its round order, its CPU accounting from /proc, its summary and report
(of new runs, and of the committed first run, which still had our own supervisor), and one quick
run of all three set-ups end to end. The shipped HAProxy set-up alone: tests/deploy/test_haproxy.py."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from bench_testkit import quick_bench_run

from bench.balancer_bench import (
    REFERENCE,
    SETUPS,
    BalancerBenchConfig,
    cpu_split,
    parse_stat,
    round_order,
    summarize,
    tree_cpu,
)
from bench.report import render_results
from bench.results import RESULTS_DIR, load_results


def test_every_round_runs_every_set_up_and_starts_at_the_next() -> None:
    orders = [round_order(SETUPS, r) for r in range(len(SETUPS) + 1)]
    assert all(sorted(o) == sorted(SETUPS) for o in orders)
    assert [o[0] for o in orders] == [*SETUPS, SETUPS[0]]
    assert round_order(("haproxy",), 3) == ["haproxy"]


def test_config_refuses_unknown_set_ups() -> None:
    with pytest.raises(ValueError, match="nginx"):
        BalancerBenchConfig(setups=("haproxy", "nginx"))
    with pytest.raises(ValueError, match="ours"):  # the supervisor it measured is gone
        BalancerBenchConfig(setups=("ours", "haproxy"))
    with pytest.raises(ValueError, match="haproxy_mode"):
        BalancerBenchConfig(haproxy_mode="udp")


def test_stat_line_with_a_name_holding_spaces_and_parentheses() -> None:
    fields = ["S", "41", *["0"] * 9, "250", "150", *["0"] * 30]  # fields 3.., utime and stime 14 and 15
    name, ppid, cpu = parse_stat("1234 (my (odd) name) " + " ".join(fields))
    hz = os.sysconf("SC_CLK_TCK")
    assert (name, ppid) == ("my (odd) name", 41) and cpu == pytest.approx(400 / hz)


def test_tree_cpu_finds_children_and_their_cpu() -> None:
    # A child that burns some CPU, then waits: its time must show up under our process.
    child = subprocess.Popen([sys.executable, "-c", "import sys, time\nx = sum(range(3_000_000))\n"
                              "print('done', flush=True)\ntime.sleep(60)"], stdout=subprocess.PIPE)
    try:
        assert child.stdout is not None and child.stdout.readline().strip() == b"done"
        cpu = tree_cpu([os.getpid()])
        mine = [k for k in cpu if k.startswith(f"{child.pid} ")]
        assert len(mine) == 1 and cpu[mine[0]] > 0
        assert any(k.startswith(f"{os.getpid()} ") for k in cpu)
        assert tree_cpu([2**22 + 7]) == {}  # no such process: nothing, no error
    finally:
        child.kill()
        child.wait()


def test_cpu_split_names_the_two_busiest_the_servers() -> None:
    before = {"1 supervisor": 1.0, "2 worker": 5.0, "3 worker": 5.0}
    after = {"1 supervisor": 1.2, "2 worker": 11.0, "3 worker": 9.0}
    split = cpu_split(before, after, processes=2, seconds=10.0)
    assert split["servers_cores"] == [0.6, 0.4]
    assert split["busiest_share"] == pytest.approx(0.6)
    assert split["front_cores"] == pytest.approx(0.02)
    assert split["changed"] == []
    assert cpu_split({}, {}, processes=2, seconds=10.0)["busiest_share"] is None


def test_cpu_split_names_a_replaced_worker() -> None:
    before = {"1 supervisor": 1.0, "2 worker": 5.0, "3 worker": 5.0}
    after = {"1 supervisor": 1.0, "2 worker": 9.0, "4 worker": 2.0}
    assert cpu_split(before, after, processes=2, seconds=10.0)["changed"] == ["3 worker", "4 worker"]


def _run(setup: str, round_: int, rps: float, p50: float, p99: float, share: float) -> dict[str, Any]:
    return {"round": round_, "position": 0, "setup": setup, "connections": 32, "requests": int(rps * 20),
            "seconds": 20.0, "throughput_rps": rps, "p50_ms": p50, "p99_ms": p99, "errors": 0,
            "statuses": {"200": int(rps * 20)}, "timeouts": 0, "socket_errors": 0,
            "top_part": "chair-0175/3", "cpu": {"servers_cores": [0.9, 0.9], "busiest_share": share,
                                                "front_cores": 0.05, "processes": {}, "changed": []}}


def _balancers_result() -> dict[str, Any]:
    runs = [_run("gunicorn", 0, 700, 40.0, 70.0, 0.5), _run("haproxy", 0, 600, 45.0, 60.0, 0.51),
            _run("gunicorn", 1, 600, 50.0, 90.0, 0.5), _run("haproxy", 1, 660, 48.0, 66.0, 0.5),
            _run("gunicorn", 2, 650, 44.0, 80.0, 0.52), _run("haproxy", 2, 500, 60.0, 100.0, 0.49)]
    cfg = BalancerBenchConfig(setups=("gunicorn", "haproxy"))
    results = {"query": {"source": "x", "points": 1000, "k": 10},
               "versions": {"haproxy": "2.6.12-1+deb12u4", "gunicorn": "23.0.0", "uvicorn-worker": "0.3.0"},
               "same_top_part": True, "runs": runs,
               "summary": summarize(runs, cfg.setups)}
    machine = {"cpu_model": "Test CPU", "cpu_flags": [], "cores": 2, "usable_cores": 2, "ram_gib": 1.0,
               "kernel": "6", "python": "3.11", "load_average_at_start": [0.1, 0.1, 0.1], "packages": {},
               "artifacts": {}, "date": "2026-12-02T19:00:00+00:00", "command": "python -m bench balancers"}
    return {"benchmark": "balancers", "machine": machine, "config": cfg.as_dict(), "results": results}


def test_summary_takes_medians_over_rounds_and_compares_with_haproxy() -> None:
    assert REFERENCE == "haproxy"  # the shipped set-up
    summary = {row["setup"]: row for row in _balancers_result()["results"]["summary"]}
    gunicorn, haproxy = summary["gunicorn"], summary["haproxy"]
    assert (gunicorn["runs"], gunicorn["throughput_rps"], gunicorn["p99_ms"]) == (3, 650, 80.0)
    assert gunicorn["throughput_range"] == [600, 700] and gunicorn["p99_range"] == [70.0, 90.0]
    assert (haproxy["throughput_rps"], haproxy["p50_ms"], haproxy["p99_ms"]) == (600, 48.0, 66.0)
    assert gunicorn["vs_reference"]["throughput"] == pytest.approx(650 / 600)
    assert gunicorn["vs_reference"]["p99"] == pytest.approx(66 / 80)  # below 1: a higher p99 than HAProxy's
    assert haproxy["vs_reference"] == {"throughput": 1.0, "p50": 1.0, "p99": 1.0}
    assert {row["reference"] for row in summary.values()} == {"haproxy"}
    assert summarize(_balancers_result()["results"]["runs"], ("gunicorn",))[0]["vs_reference"] is None


def test_report_renders_the_summary_and_every_run() -> None:
    text = render_results({"balancers": _balancers_result()})
    assert "### g. Balancers: two processes behind one port (issue 17)" in text
    assert ("| gunicorn 23.0.0, 2 uvicorn workers (uvicorn-worker 0.3.0) | 650 (600-700) | 44.00 | 80.00 "
            "(70.00-90.00) | 0 | 50 % |") in text
    assert "| HAProxy 2.6.12-1+deb12u4 (http, leastconn) + 2 x `complementme serve` | 600 (500-660) |" in text
    assert "| Against haproxy: req/s, p50, p99 |" in text and "ours" not in text
    assert "replaced" not in text
    assert "| 1.08, 1.09, 0.82 |" in text  # gunicorn against haproxy: req/s, p50, p99
    assert text.count("| haproxy | ") == 3 and "| 3 | haproxy | 500 | 60.00 | 100 | 0 | 49 % |" in text
    data = _balancers_result()
    data["results"]["runs"][1]["cpu"]["changed"] = ["18351 python", "18569 python"]
    assert "| 1 | haproxy | 600 | 45.00 | 60.00 | 0 | 51 % (processes replaced: 18351, 18569) |" \
        in render_results({"balancers": data})


def test_the_committed_first_run_still_renders_with_our_removed_supervisor() -> None:
    data = load_results(RESULTS_DIR)["balancers"]
    text = render_results({"balancers": data})
    assert "| Against ours: req/s, p50, p99 |" in text
    assert "| ours (since removed): `complementme serve --workers 2` | 565 (490-576) |" in text
    assert "+ 2 x `complementme serve` | 551 (540-563) |" in text


def test_quick_run_of_all_three_set_ups_writes_the_results(tmp_path: Path) -> None:
    data = quick_bench_run("balancers", tmp_path)
    r = data["results"]
    assert [run["setup"] for run in r["runs"]] == list(SETUPS)
    for run in r["runs"]:
        assert run["requests"] > 0 and run["errors"] == 0 and set(run["statuses"]) == {"200"}, run
        # Two server processes and at least one more (arbiter, supervisor, proxy) in every set-up.
        assert len(run["cpu"]["processes"]) >= 3 and len(run["cpu"]["servers_cores"]) == 2, run["cpu"]
    assert r["same_top_part"]
    assert r["versions"]["gunicorn"] and r["versions"]["uvicorn-worker"] and r["versions"]["haproxy"]
    text = render_results({"balancers": data})
    assert all(f"| 1 | {name} | " in text for name in SETUPS)
