"""The server sends nothing anywhere: start-up and a stretch of requests make no connection or
DNS lookup beyond loopback.

The real server (``complementme serve``, one worker, the shipped artifacts) runs under
``strace -f``, which records every ``connect``, ``sendto`` and ``sendmsg`` of every thread and
child, whatever library makes it (onnxruntime's telemetry is C++, below any Python hook). A DNS
lookup shows up as a connect or send to port 53 (or to nscd's or systemd-resolved's socket), so
loopback resolvers count as outbound too.

The window: start-up plus ``COMPLEMENTME_TEST_OUTBOUND_SECONDS`` (default 20) of mixed requests.
The lookups the issue saw came about every 2 minutes; with onnxruntime's telemetry switched off
where the sessions are built (``service.artifacts.loading.build_session``) and FastAPI's OTLP exporters off
(``create_app``), no code path in the service is left that sends. A manual run with 150 s found
nothing either (see docs/deploy.md); set the variable to 150 to repeat it.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest
from catalog_testkit import free_port
from service_testkit import AssemblyQuery

from service.geometry.inputs import points_to_base64

REPO = Path(__file__).resolve().parents[2]
WINDOW = float(os.environ.get("COMPLEMENTME_TEST_OUTBOUND_SECONDS", "20"))

_ADDR = re.compile(r'sa_family=(AF_\w+), (.*?)\}')
_LOOPBACK = re.compile(r'inet_addr\("127\.|inet_pton\(AF_INET6, "::1"|sun_path=')
_DNS = re.compile(r'htons\(53\)|nscd|resolve')


def _strace_works() -> bool:
    if shutil.which("strace") is None:
        return False
    return subprocess.run(["strace", "-f", "-qq", "-e", "trace=connect", "true"],
                          capture_output=True).returncode == 0


def outbound(trace: str) -> list[str]:
    """Lines of an strace log that connect or send to anything but loopback, or resolve a name."""
    bad = []
    for line in trace.splitlines():
        if not re.search(r"\b(connect|sendto|sendmsg)\(", line):
            continue
        addr = _ADDR.search(line)
        if addr is None:
            continue  # a send on a connected socket: its connect was checked
        family, rest = addr.groups()
        remote = family in ("AF_INET", "AF_INET6") and not _LOOPBACK.search(rest)
        unknown = family not in ("AF_INET", "AF_INET6", "AF_UNIX", "AF_NETLINK")
        if _DNS.search(rest) or remote or unknown:
            bad.append(line)
    return bad


def test_outbound_filter_sees_a_lookup_and_a_remote_connect() -> None:
    trace = "\n".join([
        '12 connect(5, {sa_family=AF_INET, sin_port=htons(8000), sin_addr=inet_addr("127.0.0.1")}, 16) = 0',
        '12 connect(6, {sa_family=AF_INET, sin_port=htons(53), sin_addr=inet_addr("127.0.0.53")}, 16) = 0',
        '12 sendto(7, "x", 1, 0, {sa_family=AF_INET, sin_port=htons(443), '
        'sin_addr=inet_addr("1.2.3.4")}, 16)',
        '12 connect(8, {sa_family=AF_UNIX, sun_path="/var/run/nscd/socket"}, 110) = -1 ENOENT',
    ])
    assert len(outbound(trace)) == 3


@pytest.mark.slow
@pytest.mark.skipif(not _strace_works(), reason="strace is missing or ptrace is not permitted here")
def test_serve_makes_no_outbound_connection(artifacts: Path, query: AssemblyQuery, tmp_path: Path) -> None:
    port, log = free_port(), tmp_path / "strace.log"
    env = {k: v for k, v in os.environ.items() if not k.startswith("COMPLEMENTME_")}
    env.update({"COMPLEMENTME_ARTIFACTS": str(artifacts), "PYTHONPATH": str(REPO),
                "COMPLEMENTME_LOG_LEVEL": "warning"})
    proc = subprocess.Popen(
        ["strace", "-f", "-qq", "-e", "trace=connect,sendto,sendmsg", "-o", str(log),
         sys.executable, "-m", "training", "serve", "--host", "127.0.0.1", "--port", str(port)],
        env=env, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        start_new_session=True)  # its own process group: strace and the server it traces
    url = f"http://127.0.0.1:{port}"
    try:
        with httpx.Client(base_url=url, timeout=30) as http:
            deadline = time.monotonic() + 180
            while True:
                assert proc.poll() is None and time.monotonic() < deadline, "the server did not start"
                try:
                    if http.get("/readyz").status_code == 200:
                        break
                except httpx.TransportError:
                    pass
                time.sleep(0.5)
            body = {"points_base64": points_to_base64(query.points), "k": 5}
            obj = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
            answered = 0
            end = time.monotonic() + WINDOW
            while time.monotonic() < end:
                for response in (http.post("/suggest", json=body), http.get("/metrics"),
                                 http.post("/suggest/mesh", files={"file": ("t.obj", obj.encode())}),
                                 http.get("/parts", params={"limit": 5})):
                    assert response.status_code == 200, response.text
                    answered += 1
                time.sleep(0.2)
            assert answered >= 20
    finally:
        # To the whole group: strace detaches on SIGINT and exits, which left the server it traced
        # running after the suite (seen after CI runs); the server stops on its own SIGINT.
        os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        deadline = time.monotonic() + 30
        while _group_alive(proc.pid) and time.monotonic() < deadline:
            time.sleep(0.2)
        if _group_alive(proc.pid):
            os.killpg(proc.pid, signal.SIGKILL)
    trace = log.read_text()
    assert outbound(trace) == [], "\n".join(outbound(trace)[:20])


def _group_alive(pgid: int) -> bool:
    """Whether any process of the group is still running."""
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True
