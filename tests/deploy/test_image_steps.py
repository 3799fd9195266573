"""Run the Dockerfile's own build steps and command in a fresh virtual environment.

No container engine runs on these machines and no base image can be pulled, so this test plays
the builder: it copies the build context the way .dockerignore lets it through, then walks the
Dockerfile instruction by instruction inside one scratch folder that stands for the image's root
file system (every absolute path ``/x`` becomes ``<root>/x``). ENV, WORKDIR and COPY are applied,
each RUN is executed verbatim with ``/bin/sh -c`` (the host's Python 3.11 plays the base image's
``python``), and the CMD is started with the image's environment. Only the user-creation RUN is
left out, as it would change the host; the service then runs as the current user.

What it proves: the install steps work from the repository as it is, they install no torch,
importing the service loads no torch, and the image's command serves until ``/readyz`` says
ready, opens its catalog data folder, and passes the HEALTHCHECK command.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from dockerfile_model import (
    DOCKERFILE,
    REPO,
    DockerIgnore,
    env_pairs,
    exec_form,
    expand,
    parse_dockerfile,
    read_dockerignore,
)

pytestmark = pytest.mark.slow
log = logging.getLogger(__name__)

# RUN steps that change the system (users, folders owned by them) and are not run here.
SYSTEM_STEP_PREFIXES = ("groupadd ",)
READY_TIMEOUT_S = 180.0
BUILD_STEP_TIMEOUT_S = 900


@dataclass
class Built:
    """The outcome of playing the Dockerfile: the scratch root and the final stage's state."""

    root: Path
    env: dict[str, str]
    workdir: Path
    cmd: list[str]
    healthcheck: list[str]
    skipped: list[str] = field(default_factory=list)
    step_seconds: dict[int, float] = field(default_factory=dict)  # Dockerfile line -> seconds


def in_root(root: Path, path: str) -> Path:
    return root / path.lstrip("/")


def map_value(root: Path, value: str) -> str:
    """Map the absolute paths of an ENV value (``/a:/b:$PATH`` style) into the scratch root."""
    return ":".join(str(in_root(root, part)) if part.startswith("/") else part for part in value.split(":"))


def base_env(shim: Path) -> dict[str, str]:
    """The host environment minus this test's own virtualenv, with ``python`` as the base image's."""
    env = {k: v for k, v in os.environ.items()
           if k not in {"VIRTUAL_ENV", "PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP", "PIP_REQUIRE_VIRTUALENV"}
           and not k.startswith("COMPLEMENTME_")}
    env["PATH"] = f"{shim}:/usr/local/bin:/usr/bin:/bin"
    env["LANG"] = "C.UTF-8"
    return env


def make_python_shim(folder: Path) -> Path:
    folder.mkdir(parents=True)
    base = Path(getattr(sys, "_base_executable", sys.executable))
    for name in ("python", "python3"):
        (folder / name).symlink_to(base)
    return folder


def copy_into(src: Path, dest: Path, dest_is_dir: bool) -> None:
    if src.is_dir():
        shutil.copytree(src, dest, dirs_exist_ok=True, symlinks=True)
    else:
        target = dest / src.name if dest_is_dir else dest
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src, target)


def play_dockerfile(scratch: Path) -> Built:
    """Walk the Dockerfile's stages in order in one scratch root; return the final stage's state."""
    context = scratch / "context"
    ignore = DockerIgnore(read_dockerignore())
    for rel in ignore.context_files(REPO):
        (context / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / rel, context / rel)
    # Before the first trained model is committed exported/ may be empty (git keeps no empty
    # folder): give the build an empty one, and let the serving test skip.
    (context / "exported").mkdir(exist_ok=True)
    root = scratch / "root"
    root.mkdir()
    shim = make_python_shim(scratch / "base-image-bin")
    skipped: list[str] = []
    step_seconds: dict[int, float] = {}
    env: dict[str, str] = {}
    workdir = root
    cmd: list[str] = []
    healthcheck: list[str] = []
    for stage in parse_dockerfile(DOCKERFILE):
        env, workdir = base_env(shim), root
        for ins in stage.instructions:
            if ins.keyword == "ENV":
                for key, value in env_pairs(ins.args):
                    env[key] = expand(map_value(root, value), env)
            elif ins.keyword == "WORKDIR":
                workdir = in_root(root, ins.args) if ins.args.startswith("/") else workdir / ins.args
                workdir.mkdir(parents=True, exist_ok=True)
            elif ins.keyword == "COPY":
                *sources, dest = ins.args.split()
                dest_path = in_root(root, dest) if dest.startswith("/") else workdir / dest
                for src in sources:
                    src_path = in_root(root, src) if "from" in ins.flags else context / src
                    if src_path.resolve() != dest_path.resolve():
                        copy_into(src_path, dest_path, dest.endswith("/") or len(sources) > 1)
            elif ins.keyword == "RUN":
                if ins.args.startswith(SYSTEM_STEP_PREFIXES):
                    skipped.append(ins.args)
                    continue
                start = time.monotonic()
                proc = subprocess.run(["/bin/sh", "-c", ins.args], cwd=workdir, env=env, capture_output=True,
                                      text=True, timeout=BUILD_STEP_TIMEOUT_S)
                step_seconds[ins.line] = time.monotonic() - start
                assert proc.returncode == 0, (
                    f"Dockerfile:{ins.line} RUN failed ({proc.returncode}): {ins.args}\n"
                    f"{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
            elif ins.keyword == "CMD":
                cmd = exec_form(ins.args)
            elif ins.keyword == "HEALTHCHECK":
                healthcheck = exec_form(ins.args)
    log.info("Dockerfile RUN steps took %s seconds (by line)",
             {line: round(t, 1) for line, t in step_seconds.items()})
    return Built(root, env, workdir, cmd, healthcheck, skipped, step_seconds)


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Built:
    return play_dockerfile(tmp_path_factory.mktemp("image"))


def venv_python(b: Built) -> Path:
    return in_root(b.root, "/opt/venv/bin/python")


def test_only_the_user_creation_step_was_left_out(built: Built) -> None:
    assert len(built.skipped) == 1 and built.skipped[0].startswith(SYSTEM_STEP_PREFIXES), built.skipped
    assert venv_python(built).is_file()
    assert built.env["VIRTUAL_ENV"] == str(in_root(built.root, "/opt/venv"))


def test_image_has_no_torch_installed_or_imported(built: Built) -> None:
    listed = subprocess.run([str(venv_python(built)), "-m", "pip", "list", "--format=freeze"],
                            capture_output=True, text=True, check=True, env=built.env).stdout.lower()
    assert "complementme==" in listed, "the project's wheel is not installed"
    assert not [line for line in listed.splitlines() if line.startswith(("torch", "nvidia"))], listed
    # Everything `complementme serve` imports, plus every module of the service package.
    probe = (
        "import importlib, importlib.util, pkgutil, sys\n"
        "import service, training.cli\n"
        "for m in pkgutil.walk_packages(service.__path__, 'service.'):\n"
        "    importlib.import_module(m.name)\n"
        "assert importlib.util.find_spec('torch') is None, 'torch is installed'\n"
        "assert 'torch' not in sys.modules, 'torch was imported'\n"
        "print(len([m for m in sys.modules if m.startswith('service.')]))\n"
    )
    proc = subprocess.run([str(venv_python(built)), "-c", probe], cwd=built.workdir, env=built.env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert int(proc.stdout.split()[-1]) >= 5, "too few service modules imported to mean anything"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def get(url: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=5) as resp:
            return resp.status, resp.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def test_image_command_serves_until_ready(built: Built, tmp_path: Path) -> None:
    artifacts = Path(built.env["COMPLEMENTME_ARTIFACTS"])
    if not (REPO / "exported" / "manifest.json").is_file():
        pytest.skip("exported/manifest.json does not exist yet: no trained artifacts to serve")
    assert (artifacts / "manifest.json").is_file(), f"COPY exported/ did not reach {artifacts}"
    data_dir = Path(built.env["COMPLEMENTME_DATA_DIR"])
    data_dir.mkdir(parents=True, exist_ok=True)  # the skipped system step creates it in the image
    port = free_port()
    # Inside a container the server binds 0.0.0.0:8000 in its own network namespace; here it
    # binds the loopback address on a free port. Everything else is the image's environment.
    env = dict(built.env, COMPLEMENTME_HOST="127.0.0.1", COMPLEMENTME_PORT=str(port))
    server_log = tmp_path / "server.log"
    with open(server_log, "wb") as out:
        server = subprocess.Popen(built.cmd, cwd=built.workdir, env=env, stdout=out, stderr=subprocess.STDOUT,
                                  start_new_session=True)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + READY_TIMEOUT_S
        status = None
        while time.monotonic() < deadline:
            assert server.poll() is None, f"CMD exited ({server.returncode}):\n{server_log.read_text()}"
            try:
                status, _ = get(f"{base}/readyz")
            except (urllib.error.URLError, OSError):
                status = None
            if status == 200:
                break
            time.sleep(0.5)
        assert status == 200, f"/readyz never said 200 (last: {status}):\n{server_log.read_text()[-3000:]}"
        assert get(f"{base}/healthz")[0] == 200
        # The image's data folder is where the catalog additions' database lives.
        assert (data_dir / "catalog.sqlite3").is_file(), f"no additions database in {data_dir}"
        code, body = get(f"{base}/metrics")
        assert code == 200 and b"complementme_http_requests" in body
        check = [str(in_root(built.root, a)) if a.startswith("/") else a for a in built.healthcheck]
        hc = subprocess.run(check, cwd=built.workdir, env=env, capture_output=True, text=True, timeout=30)
        assert hc.returncode == 0, f"HEALTHCHECK {built.healthcheck} failed: {hc.stderr}"
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait()
    # The health check must also be able to fail: nothing listens any more.
    hc = subprocess.run(check, cwd=built.workdir, env=env, capture_output=True, text=True, timeout=30)
    assert hc.returncode == 1, hc.stderr
