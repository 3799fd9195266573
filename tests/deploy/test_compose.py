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
    assert sorted(parsed.service_names()) == ["complementme", "complementme-2", "grafana", "postgres",
                                              "prometheus"]


REPLICAS = ("complementme", "complementme-2")


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


def test_replicas_share_the_postgres_catalog_kept_on_a_named_volume() -> None:
    services = compose()["services"]
    urls = set()
    for name in REPLICAS:
        env = services[name]["environment"]
        assert env["COMPLEMENTME_CATALOG_BACKEND"] == "postgres", name
        urls.add(env["COMPLEMENTME_DATABASE_URL"])
        assert services[name]["depends_on"]["postgres"]["condition"] == "service_healthy", name
        assert services[name]["image"] == services["complementme"]["image"]
    assert len(urls) == 1, "both replicas must use the one database"
    assert "@postgres:5432/" in urls.pop()
    db = services["postgres"]
    targets = {v["target"]: v for v in db["volumes"]}
    assert targets["/var/lib/postgresql/data"]["type"] == "volume"
    published = {p.split(":")[0] for name in REPLICAS for p in services[name]["ports"]}
    assert len(published) == len(REPLICAS), "each replica needs a host port of its own"


def test_environment_names_real_settings_within_the_cpu_budget() -> None:
    fields = {f"{ENV_PREFIX}{name.upper()}" for name in Settings.model_fields}
    for name in REPLICAS:
        api = compose()["services"][name]
        env = api["environment"]
        unknown = sorted(set(env) - fields)
        assert not unknown, f"not settings of service/settings.py: {unknown}"
        Settings.model_validate({k[len(ENV_PREFIX):].lower(): v for k, v in env.items()
                                 if k != f"{ENV_PREFIX}API_KEY"})
        for threads in ("COMPLEMENTME_ONNX_THREADS", "COMPLEMENTME_FAISS_THREADS"):  # one process each
            assert int(env.get(threads, "1")) <= float(api["cpus"]), threads


def test_image_tag_is_the_project_version() -> None:
    with open(REPO / "pyproject.toml", "rb") as fh:
        version = tomllib.load(fh)["project"]["version"]
    assert compose()["services"]["complementme"]["image"] == f"complementme:{version}"
