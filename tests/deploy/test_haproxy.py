"""docker/haproxy/haproxy.cfg: several `complementme serve` processes on one machine behind HAProxy.

HAProxy's own check of the shipped file and of the copies the benchmarks write from it, the
route its health check asks for, and the set-up run for real: two `complementme serve` processes
on the shipped artifacts behind HAProxy on loopback, started by ``bench.server.our_servers`` as
the benchmarks start them. Every wait is bounded (start-up, each request); nothing is timed.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest
from dockerfile_model import REPO
from prometheus_client.parser import text_string_to_metric_families

from bench.query import EXAMPLE, load_query
from bench.server import HAPROXY_CONFIG, READY_PATH, haproxy_config, our_servers

ARTIFACTS = REPO / "exported"
HAPROXY = shutil.which("haproxy")
needs_haproxy = pytest.mark.skipif(HAPROXY is None, reason="haproxy is not installed (.ci/run installs "
                                   "Debian's haproxy package)")


def _check(path: Path) -> subprocess.CompletedProcess[str]:
    assert HAPROXY is not None
    return subprocess.run([HAPROXY, "-c", "-f", str(path)], capture_output=True, text=True, timeout=60)


@needs_haproxy
def test_shipped_config_and_the_benchmarks_copies_are_valid(tmp_path: Path) -> None:
    done = _check(HAPROXY_CONFIG)
    assert done.returncode == 0, done.stdout + done.stderr
    copy = tmp_path / "haproxy.cfg"
    copy.write_text(haproxy_config(18000, [18001, 18002, 18003], threads=1, timeout=90))
    done = _check(copy)
    assert done.returncode == 0, done.stdout + done.stderr


def test_the_benchmarks_replace_only_the_address_and_the_servers() -> None:
    shipped = HAPROXY_CONFIG.read_text().splitlines()
    text = haproxy_config(18000, [18001, 18002, 18003])
    lines = text.splitlines()
    assert "    bind 127.0.0.1:18000" in lines
    servers = [line.split() for line in lines if line.split()[:1] == ["server"]]
    assert servers == [["server", f"s{i}", f"127.0.0.1:{18000 + i}"] for i in (1, 2, 3)]
    kept = [line for line in lines if line.split()[:1] not in (["server"], ["bind"])]
    assert kept == [line for line in shipped if line.split()[:1] not in (["server"], ["bind"])]
    tuned = haproxy_config(18000, [18001], mode="tcp", balance="roundrobin", threads=2, timeout=45)
    assert {"    mode tcp", "    balance roundrobin", "    nbthread 2", "    timeout client 45s",
            "    timeout server 45s"} <= set(tuned.splitlines())


def test_health_check_asks_a_route_of_the_service() -> None:
    from service.api.routes.probes import router

    words = [line.split() for line in HAPROXY_CONFIG.read_text().splitlines()]
    checks = [w for w in words if w[:2] == ["option", "httpchk"]]
    assert checks == [["option", "httpchk", "GET", READY_PATH]]
    assert READY_PATH in {route.path for route in router.routes}  # type: ignore[attr-defined]
    assert ["http-check", "expect", "status", "200"] in words
    assert ["balance", "leastconn"] in words


def _stop(pid: int, timeout: float = 60) -> bool:
    """SIGTERM ``pid`` and wait until it has exited (gone, or a zombie its parent has not reaped)."""
    os.kill(pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z":
                return True
        except OSError:
            return True
        time.sleep(0.1)
    return False


def _suggest_answers(backend: str) -> float:
    """``POST /suggest`` answered 200 by one server process, from its own /metrics."""
    text = httpx.get(backend + "/metrics", timeout=30).text
    return sum(s.value for family in text_string_to_metric_families(text) for s in family.samples
               if s.name == "complementme_http_requests_total" and s.labels.get("route") == "/suggest"
               and s.labels.get("method") == "POST" and s.labels.get("status") == "200")


@needs_haproxy
@pytest.mark.slow
def test_two_servers_behind_haproxy_share_the_suggestions(tmp_path: Path) -> None:
    if not (ARTIFACTS / "manifest.json").is_file():
        pytest.skip(f"the set-up serves the shipped model: no artifact folder at {ARTIFACTS}")
    body = load_query(EXAMPLE, n_points=1000, k=5).body("json")
    headers = {"Content-Type": "application/json"}
    env = {"COMPLEMENTME_ARTIFACTS": str(ARTIFACTS), "COMPLEMENTME_LOG_LEVEL": "warning"}
    with our_servers(2, tmp_path, env=env, start_timeout=300) as served:
        assert len(served.backends) == 2 and served.url not in served.backends

        def post(_: int) -> httpx.Response:
            return httpx.post(served.url + "/suggest", content=body, headers=headers, timeout=60)

        # One connection per request, eight at a time: leastconn spreads them over both processes.
        with ThreadPoolExecutor(max_workers=8) as pool:
            answers = list(pool.map(post, range(24)))
        assert [a.status_code for a in answers] == [200] * 24, [a.text[:300] for a in answers]
        assert len({tuple(s["part_id"] for s in a.json()["suggestions"]) for a in answers}) == 1
        counts = [_suggest_answers(b) for b in served.backends]
        assert all(c > 0 for c in counts) and sum(counts) == 24, counts

        # One process stops (as in a restart): the proxy takes it out of rotation and answers
        # from the other (its health check marks the stopped one down after two failures).
        assert _stop(served.roots[0]), "the server process did not stop after SIGTERM"
        answered = 0
        deadline = time.monotonic() + 60
        while answered < 6:
            assert time.monotonic() < deadline, "the proxy kept sending requests to the stopped process"
            answered = answered + 1 if post(0).status_code == 200 else 0
        assert _suggest_answers(served.backends[1]) >= counts[1] + 6
