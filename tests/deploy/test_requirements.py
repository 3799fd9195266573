"""docker/requirements-service.txt lists exactly pyproject.toml's service dependencies; docker/constraints.txt
locks every package they, and the train, test and bench extras, pull in."""

from __future__ import annotations

import importlib.util
import re

import tomllib
from dockerfile_model import REPO


def load_generator():
    path = REPO / "docker" / "make_requirements.py"
    spec = importlib.util.spec_from_file_location("make_requirements", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_requirements_file_matches_pyproject() -> None:
    generated = load_generator().render(REPO / "pyproject.toml")
    committed = (REPO / "docker" / "requirements-service.txt").read_text()
    assert committed == generated, (
        "docker/requirements-service.txt is out of date with pyproject.toml's dependencies: "
        "run `python docker/make_requirements.py`")


def test_requirements_are_the_dependencies_and_nothing_else() -> None:
    with open(REPO / "pyproject.toml", "rb") as fh:
        project = tomllib.load(fh)["project"]
    lines = (REPO / "docker" / "requirements-service.txt").read_text().splitlines()
    reqs = [line for line in lines if line and not line.startswith("#")]
    assert reqs == project["dependencies"]
    def name(req: str) -> str:
        return re.split(r"[<>=!~\[; ]", req, maxsplit=1)[0].lower()

    train_only = {name(dep) for dep in project["optional-dependencies"]["train"]}
    assert not {name(r) for r in reqs} & train_only, reqs


def test_generator_follows_a_changed_pyproject(tmp_path) -> None:
    # The check above could pass by accident if render() ignored its input.
    fake = tmp_path / "pyproject.toml"
    fake.write_text('[project]\nname = "x"\ndependencies = ["numpy>=2", "orjson"]\n')
    text = load_generator().render(fake)
    assert [line for line in text.splitlines() if not line.startswith("#")] == ["numpy>=2", "orjson"]


def test_constraints_pin_every_requirement_within_pyprojects_bounds() -> None:
    from packaging.requirements import Requirement

    with open(REPO / "pyproject.toml", "rb") as fh:
        project = tomllib.load(fh)["project"]
    lines = (REPO / "docker" / "constraints.txt").read_text().splitlines()
    pins = dict(line.split("==", 1) for line in lines if line and not line.startswith("#"))
    needed = [*project["dependencies"], *project["optional-dependencies"]["train"],
              *project["optional-dependencies"]["test"], *project["optional-dependencies"]["bench"]]
    for line in needed:
        req = Requirement(line)
        if req.marker is not None and not req.marker.evaluate():
            continue
        key = re.sub(r"[-_.]+", "-", req.name).lower()
        assert key in pins, (f"{req.name} is not pinned in docker/constraints.txt: "
                             "run `python docker/make_requirements.py`")
        assert req.specifier.contains(pins[key], prereleases=True), (
            f"docker/constraints.txt pins {key}=={pins[key]}, outside pyproject's {line!r}")


def test_constraints_are_the_versions_installed_here() -> None:
    # CI installs with `-c docker/constraints.txt`, so there the environment is the lock; a lock
    # that names a package nothing needs any more, or misses a new one, fails here.
    committed = (REPO / "docker" / "constraints.txt").read_text()
    assert committed == load_generator().render_constraints(REPO / "pyproject.toml"), (
        "docker/constraints.txt differs from the packages installed here: run "
        "`python docker/make_requirements.py` in the project's venv "
        "(after `pip install -e \".[train,test,bench]\"`)")
