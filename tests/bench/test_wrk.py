"""wrk with the benchmark's Lua script against a tiny local server, and wrk output parsing."""

from __future__ import annotations

import shutil
import sys
import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import ClassVar

import pytest

from bench.http_bench import batch_means, parse_batch_counters
from bench.server import free_port, free_ports, running_server
from bench.wrk import LoadSettings, parse_wrk_output, run_wrk

LINE = ('BENCH_JSON {"duration_us": 2000000, "requests": 100, "responses": 100, "bytes": 5000, '
        '"connect_errors": 1, "read_errors": 0, "write_errors": 0, "status_errors": 20, "timeouts": 2, '
        '"non2xx": 20, "statuses": {"200": 80, "503": 20}, "latency_us": {"min": 900, "mean": 2500.0, '
        '"stdev": 10.0, "max": 9000, "p50": 2000, "p90": 4000, "p99": 8000, "p999": 9000}}')


def test_parse_counts_only_2xx_as_throughput() -> None:
    r = parse_wrk_output("Running 2s test\n" + LINE + "\n")
    assert r["throughput_rps"] == 40.0 and r["answers_rps"] == 50.0
    assert (r["p50_ms"], r["p99_ms"]) == (2.0, 8.0)
    assert r["errors"] == 20 + 2 + 1
    assert r["statuses"] == {"200": 80, "503": 20}


def test_parse_without_answers_has_no_latencies() -> None:
    none = LINE.replace('"requests": 100', '"requests": 0').replace('"non2xx": 20', '"non2xx": 0')
    r = parse_wrk_output(none)
    assert r["p50_ms"] is None and r["throughput_rps"] == 0.0
    with pytest.raises(ValueError, match="BENCH_JSON"):
        parse_wrk_output("wrk crashed\n")


class _Handler(BaseHTTPRequestHandler):
    """Answers every third POST with 503, the others with 200; counts the bodies it saw."""

    protocol_version = "HTTP/1.1"
    count = 0
    bodies: ClassVar[set[bytes]] = set()
    lock = threading.Lock()

    def do_POST(self) -> None:
        body = self.rfile.read(int(self.headers["Content-Length"]))
        with _Handler.lock:
            _Handler.count += 1
            n = _Handler.count
            _Handler.bodies.add(body)
        status = 503 if n % 3 == 0 else 200
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", "2")
        self.end_headers()
        self.wfile.write(b"{}")

    def log_message(self, *args: object) -> None:
        pass


@pytest.fixture
def tiny_server() -> Iterator[str]:
    server = ThreadingHTTPServer(("127.0.0.1", free_port()), _Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}/suggest"
    server.shutdown()
    server.server_close()


@pytest.mark.skipif(shutil.which("wrk") is None, reason="wrk is not installed")
def test_wrk_posts_the_body_and_counts_statuses(tiny_server: str, tmp_path: Path) -> None:
    body = tmp_path / "body.json"
    body.write_bytes(b'{"points_base64": "AAAA", "k": 10}')
    drains: list[int] = []
    r = run_wrk(tiny_server, body, 2, LoadSettings(duration=1, warmup=1, timeout=5),
                drain=lambda: drains.append(1))
    assert drains == [1, 1]  # after the warm-up and after the measured run
    assert _Handler.bodies == {body.read_bytes()}
    assert r["connections"] == 2 and r["requests"] > 10
    assert sum(r["statuses"].values()) == r["requests"]
    assert r["non2xx"] == r["statuses"].get("503", 0) > 0
    assert r["throughput_rps"] == pytest.approx((r["requests"] - r["non2xx"]) / r["seconds"])
    assert 0 < r["p50_ms"] <= r["p99_ms"]


def test_running_server_waits_for_ready_and_reports_early_exit(tmp_path: Path) -> None:
    port = free_port()
    cmd = [sys.executable, "-m", "http.server", str(port), "--bind", "127.0.0.1",
           "--directory", str(tmp_path)]
    with running_server(cmd, port=port, ready_path="/", log_path=tmp_path / "log") as server:
        assert server.url == f"http://127.0.0.1:{port}" and server.process.poll() is None
    assert server.process.poll() is not None  # stopped at the end of the block
    failing = [sys.executable, "-c", "import sys; print('boom'); sys.exit(3)"]
    with pytest.raises(RuntimeError, match=r"(?s)exited with status 3.*boom"), \
            running_server(failing, port=free_port(), ready_path="/", log_path=tmp_path / "log2"):
        pass


METRICS = """# HELP complementme_batch_size Queries per engine call.
# TYPE complementme_batch_size histogram
complementme_batch_size_bucket{le="1.0"} 3.0
complementme_batch_size_bucket{le="+Inf"} 5.0
complementme_batch_size_count 5.0
complementme_batch_size_sum 20.0
# HELP complementme_batch_queue_wait_seconds Seconds in the queue.
# TYPE complementme_batch_queue_wait_seconds histogram
complementme_batch_queue_wait_seconds_count{route="/suggest"} 10.0
complementme_batch_queue_wait_seconds_sum{route="/suggest"} 0.05
complementme_batch_queue_wait_seconds_count{route="/suggest/batch"} 10.0
complementme_batch_queue_wait_seconds_sum{route="/suggest/batch"} 0.15
# HELP complementme_http_requests_total Requests.
# TYPE complementme_http_requests_total counter
complementme_http_requests_total{status="200"} 7.0
"""


def test_ports_picked_together_are_distinct_and_free() -> None:
    """Servers started together get distinct ports (two told the same port would look ready as one)."""
    ports = free_ports(64)
    assert len(set(ports)) == 64
    server = ThreadingHTTPServer(("127.0.0.1", ports[0]), _Handler)   # free: it binds
    server.server_close()


def test_batch_means_from_metrics_differences() -> None:
    before = parse_batch_counters(METRICS)
    assert before == {"complementme_batch_size_count": 5.0, "complementme_batch_size_sum": 20.0,
                      "complementme_batch_queue_wait_seconds_count": 20.0,
                      "complementme_batch_queue_wait_seconds_sum": pytest.approx(0.2)}
    after = {**before, "complementme_batch_size_count": 9.0, "complementme_batch_size_sum": 60.0,
             "complementme_batch_queue_wait_seconds_count": 30.0,
             "complementme_batch_queue_wait_seconds_sum": 0.3}
    means = batch_means({k: v - before[k] for k, v in after.items()})
    assert means == {"batch_size": 10.0, "batch_queue_wait_ms": pytest.approx(10.0)}
    assert batch_means({"complementme_batch_size_sum": 0.0, "complementme_batch_size_count": 0.0}) == {}
