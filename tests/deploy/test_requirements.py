"""docker/requirements-service.txt must list exactly pyproject.toml's service dependencies."""

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
