"""docker/compose.yaml: valid by the Compose specification, and its references resolve.

The specification check is the `compose-spec` package (Python bindings of the Rust `compose_spec`
crate, which refuses unknown keys and malformed values). It does not follow references between
services, volumes and files, so those are checked here.
"""

from __future__ import annotations

from typing import Any

import pytest
import tomllib
import yaml
from compose_spec import PyCompose
from dockerfile_model import REPO

from service.settings import ENV_PREFIX, Settings

DOCKER = REPO / "docker"
COMPOSE = DOCKER / "compose.yaml"


def compose() -> dict[str, Any]:
    return yaml.safe_load(COMPOSE.read_text())


def test_compose_file_follows_the_specification() -> None:
    parsed = PyCompose.from_yaml(COMPOSE.read_text())
    parsed.validate()
    assert sorted(parsed.service_names()) == ["complementme", "grafana", "prometheus"]


@pytest.mark.parametrize("broken", [
    "services:\n  api:\n    image: x\n    helthcheck: {}\n",
    "services:\n  api:\n    image: x\n    ports: [\"eighty:80\"]\n",
    "services:\n  api:\n    image: x\n    networks: [missing]\n",
])
def test_specification_check_rejects_mistakes(broken: str) -> None:
    with pytest.raises(ValueError):
        PyCompose.from_yaml(broken).validate()


def test_references_resolve() -> None:
    doc = compose()
    services = doc["services"]
    named_volumes = set(doc.get("volumes", {}))
    for name, service in services.items():
        for dep in service.get("depends_on", []):
            assert dep in services, f"service {name} depends on unknown service {dep}"
        for volume in service.get("volumes", []):
            assert isinstance(volume, dict), f"service {name}: use the long volume syntax"
            if volume["type"] == "volume":
                assert volume["source"] in named_volumes, f"{name}: volume {volume['source']} not declared"
            elif volume["type"] == "bind":
                assert (DOCKER / volume["source"]).exists(), f"{name}: bind source {volume['source']} missing"
        if "build" in service:
            context = (DOCKER / service["build"]["context"]).resolve()
            assert context == REPO
            assert (context / service["build"]["dockerfile"]).is_file()


def test_service_keeps_its_catalog_data_on_a_named_volume() -> None:
    api = compose()["services"]["complementme"]
    targets = {v["target"]: v for v in api["volumes"]}
    assert targets["/data"]["type"] == "volume"
    dockerfile = (REPO / "Dockerfile").read_text()
    assert "COMPLEMENTME_DATA_DIR=/data" in dockerfile, "the image's data folder moved: update compose"


def test_environment_names_real_settings_within_the_cpu_budget() -> None:
    api = compose()["services"]["complementme"]
    env = api["environment"]
    fields = {f"{ENV_PREFIX}{name.upper()}" for name in Settings.model_fields}
    unknown = sorted(set(env) - fields)
    assert not unknown, f"not settings of service/settings.py: {unknown}"
    workers = int(env.get("COMPLEMENTME_WORKERS", "1"))
    for threads in ("COMPLEMENTME_ONNX_THREADS", "COMPLEMENTME_FAISS_THREADS"):
        assert workers * int(env.get(threads, "1")) <= float(api["cpus"]), threads


def test_image_tag_is_the_project_version() -> None:
    with open(REPO / "pyproject.toml", "rb") as fh:
        version = tomllib.load(fh)["project"]["version"]
    assert compose()["services"]["complementme"]["image"] == f"complementme:{version}"

