"""The Kubernetes manifests in docker/k8s: schema-valid, and consistent with each other and the image."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import kubernetes_validate
import pytest
import tomllib
import yaml
from dockerfile_model import DOCKERFILE, REPO, env_pairs, parse_dockerfile
from kubernetes_validate.utils import latest_version

from service.settings import ENV_PREFIX, Settings

K8S = REPO / "docker" / "k8s"
WRITER = K8S / "single-writer"
DATABASE = K8S / "postgres-example"
# What the replicas' Secret (complementme-secrets) holds, as placeholders for the settings check.
SECRET_SETTINGS = {f"{ENV_PREFIX}API_KEY": "x" * 24,
                   f"{ENV_PREFIX}DATABASE_URL": "postgresql://complementme:pw@complementme-postgres:5432/complementme"}
# The oldest Kubernetes release the manifests are meant for, and the newest the validator knows.
VERSIONS = ["1.29.0", latest_version()]


def load_all(folder: Path = K8S) -> list[tuple[Path, dict[str, Any]]]:
    docs = []
    for path in sorted(folder.glob("*.yaml")):
        for doc in yaml.safe_load_all(path.read_text()):
            if doc is not None:
                docs.append((path, doc))
    return docs


def one(kind: str, folder: Path = K8S) -> dict[str, Any]:
    found = [doc for _, doc in load_all(folder) if doc["kind"] == kind]
    assert len(found) == 1, f"expected one {kind} in {folder}, found {len(found)}"
    return found[0]


def test_the_expected_resources_are_there() -> None:
    kinds = sorted(doc["kind"] for _, doc in load_all())
    assert kinds == ["ConfigMap", "Deployment", "HorizontalPodAutoscaler", "PodDisruptionBudget", "Service"]
    writer = sorted(doc["kind"] for _, doc in load_all(WRITER))
    assert writer == ["Deployment", "PersistentVolumeClaim", "Service"]
    database = sorted(doc["kind"] for _, doc in load_all(DATABASE))
    assert database == ["Service", "StatefulSet"]


@pytest.mark.parametrize("version", VERSIONS)
def test_manifests_match_the_kubernetes_schema(version: str) -> None:
    errors = []
    for path, doc in load_all(K8S) + load_all(WRITER) + load_all(DATABASE):
        try:
            kubernetes_validate.validate(doc, version, strict=True)
        except kubernetes_validate.ValidationError as exc:
            caught = exc.caught
            where = "/".join(str(p) for p in caught.absolute_path)
            errors.append(f"{path.name} ({doc['kind']}) at {where}: {caught.message}")
    assert not errors, "\n".join(errors)


def test_validator_rejects_a_misspelt_field() -> None:
    # Strict mode must refuse unknown fields, or the check above would let typos through.
    deployment = one("Deployment")
    broken = yaml.safe_load(yaml.safe_dump(deployment))
    broken["spec"]["template"]["spec"]["containers"][0]["readinesProbe"] = {}
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(broken, latest_version(), strict=True)


def container() -> dict[str, Any]:
    containers = one("Deployment")["spec"]["template"]["spec"]["containers"]
    assert len(containers) == 1
    return containers[0]


def settings_env() -> dict[str, str]:
    return one("ConfigMap")["data"]


def test_selectors_find_the_pods() -> None:
    deployment = one("Deployment")
    pod_labels = deployment["spec"]["template"]["metadata"]["labels"]
    selectors = {
        "Deployment": deployment["spec"]["selector"]["matchLabels"],
        "Service": one("Service")["spec"]["selector"],
        "PodDisruptionBudget": one("PodDisruptionBudget")["spec"]["selector"]["matchLabels"],
    }
    for kind, selector in selectors.items():
        assert selector.items() <= pod_labels.items(), f"{kind} selector {selector} misses pods {pod_labels}"
    target = one("HorizontalPodAutoscaler")["spec"]["scaleTargetRef"]
    assert (target["kind"], target["name"]) == ("Deployment", deployment["metadata"]["name"])


def test_probes_use_the_service_endpoints() -> None:
    c = container()
    assert c["readinessProbe"]["httpGet"]["path"] == "/readyz"
    assert c["livenessProbe"]["httpGet"]["path"] == "/healthz"
    assert c["startupProbe"]["httpGet"]["path"] == "/healthz"
    port_names = {p["name"]: p["containerPort"] for p in c["ports"]}
    for probe in ("readinessProbe", "livenessProbe", "startupProbe"):
        assert c[probe]["httpGet"]["port"] in port_names, probe


def test_ports_agree_everywhere() -> None:
    c = container()
    port = int(settings_env()["COMPLEMENTME_PORT"])
    assert [p["containerPort"] for p in c["ports"]] == [port]
    assert one("Service")["spec"]["ports"][0]["targetPort"] in {p["name"] for p in c["ports"]}
    annotations = one("Deployment")["spec"]["template"]["metadata"]["annotations"]
    assert int(annotations["prometheus.io/port"]) == port
    assert annotations["prometheus.io/path"] == "/metrics"
    assert settings_env()["COMPLEMENTME_HOST"] == "0.0.0.0"


def test_configmap_sets_only_real_settings_as_strings() -> None:
    fields = {f"{ENV_PREFIX}{name.upper()}" for name in Settings.model_fields}
    data = settings_env()
    assert all(isinstance(v, str) for v in data.values()), data
    unknown = sorted(set(data) - fields)
    assert not unknown, f"not settings of service/settings.py: {unknown}"
    # Every value must parse as that setting (e.g. a port in range, a known log level), with the
    # Secret's settings beside them (the postgres backend needs its URL).
    Settings.model_validate({k[len(ENV_PREFIX):].lower(): v for k, v in {**data, **SECRET_SETTINGS}.items()})
    for secret in SECRET_SETTINGS:
        assert secret not in data, f"{secret} belongs in a Secret"
    sources = container()["envFrom"]
    maps = [s["configMapRef"]["name"] for s in sources if "configMapRef" in s]
    assert maps == [one("ConfigMap")["metadata"]["name"]]
    assert [s["secretRef"]["name"] for s in sources if "secretRef" in s] == ["complementme-secrets"]


def cpu_cores(quantity: str) -> float:
    return float(quantity[:-1]) / 1000 if quantity.endswith("m") else float(quantity)


def test_threads_fit_the_cpu_limit() -> None:
    resources = container()["resources"]
    for kind in ("requests", "limits"):
        assert {"cpu", "memory"} <= resources[kind].keys(), f"{kind} must set cpu and memory"
    cores = cpu_cores(resources["limits"]["cpu"])
    data = settings_env()
    for threads in ("COMPLEMENTME_ONNX_THREADS", "COMPLEMENTME_FAISS_THREADS"):  # one server process per pod
        assert int(data[threads]) <= cores, f"{threads} exceeds the {cores} CPU limit"


def test_pods_match_the_image() -> None:
    runtime = parse_dockerfile(DOCKERFILE)[-1]
    image_env = dict(kv for ins in runtime.of("ENV") for kv in env_pairs(ins.args))
    uid = int(runtime.of("USER")[-1].args.split(":")[0])
    pod = one("Deployment")["spec"]["template"]["spec"]
    assert pod["securityContext"]["runAsUser"] == uid
    assert pod["securityContext"]["runAsNonRoot"] is True
    data = settings_env()
    assert data["COMPLEMENTME_ARTIFACTS"] == image_env["COMPLEMENTME_ARTIFACTS"]
    mounts = {m["mountPath"]: m["name"] for m in container()["volumeMounts"]}
    assert data["COMPLEMENTME_DATA_DIR"] in mounts, "the catalog data folder must be on a volume"
    assert mounts.get("/tmp"), "a read-only root file system needs a writable /tmp"
    volumes = {v["name"] for v in pod["volumes"]}
    assert set(mounts.values()) <= volumes
    with open(REPO / "pyproject.toml", "rb") as fh:
        version = tomllib.load(fh)["project"]["version"]
    image = container()["image"]
    assert image.rsplit("/", 1)[-1] == f"complementme:{version}", f"{image}: tag it with the project version"


def test_rollout_waits_for_readiness() -> None:
    strategy = one("Deployment")["spec"]["strategy"]
    assert strategy["type"] == "RollingUpdate"
    assert strategy["rollingUpdate"]["maxUnavailable"] == 0


def writer_container() -> dict[str, Any]:
    return one("Deployment", WRITER)["spec"]["template"]["spec"]["containers"][0]


def test_one_writer_on_its_own_volume() -> None:
    writer = one("Deployment", WRITER)
    assert writer["spec"]["replicas"] == 1, "SQLite in the data folder allows one writing pod"
    assert writer["spec"]["strategy"]["type"] == "Recreate", "two pods must never share the volume"
    claim = one("PersistentVolumeClaim", WRITER)
    assert claim["spec"]["accessModes"] == ["ReadWriteOnce"]
    volumes = {v["name"]: v for v in writer["spec"]["template"]["spec"]["volumes"]}
    mounts = {m["mountPath"]: m["name"] for m in writer_container()["volumeMounts"]}
    data = volumes[mounts[settings_env()["COMPLEMENTME_DATA_DIR"]]]
    assert data["persistentVolumeClaim"]["claimName"] == claim["metadata"]["name"]
    sources = writer_container()["envFrom"]
    assert {"configMapRef": {"name": one("ConfigMap")["metadata"]["name"]}} in sources
    assert any("secretRef" in s for s in sources), "the writer needs the API key Secret"
    env = {e["name"]: e["value"] for e in writer_container()["env"]}
    assert env[f"{ENV_PREFIX}CATALOG_BACKEND"] == "sqlite", "the single writer keeps its data folder"
    hpa_target = one("HorizontalPodAutoscaler")["spec"]["scaleTargetRef"]["name"]
    assert hpa_target != writer["metadata"]["name"], "the writer must not be scaled out"


def test_reader_and_writer_services_do_not_mix_pods() -> None:
    reader_pods = one("Deployment")["spec"]["template"]["metadata"]["labels"]
    writer_pods = one("Deployment", WRITER)["spec"]["template"]["metadata"]["labels"]
    reader_selector = one("Service")["spec"]["selector"]
    writer_selector = one("Service", WRITER)["spec"]["selector"]
    assert reader_selector.items() <= reader_pods.items()
    assert not reader_selector.items() <= writer_pods.items(), "reader traffic would reach the writer"
    assert writer_selector.items() <= writer_pods.items()
    assert not writer_selector.items() <= reader_pods.items(), "writes would reach a reader"
    pdb = one("PodDisruptionBudget")["spec"]["selector"]["matchLabels"]
    assert not pdb.items() <= writer_pods.items()


def test_writer_runs_the_same_image_and_probes() -> None:
    reader, writer = container(), writer_container()
    assert writer["image"] == reader["image"]
    for key in ("ports", "startupProbe", "livenessProbe", "readinessProbe", "resources", "securityContext"):
        assert writer[key] == reader[key], f"writer {key} differs from the readers'"


def test_replicas_share_the_database_and_the_example_database_is_consistent() -> None:
    assert settings_env()[f"{ENV_PREFIX}CATALOG_BACKEND"] == "postgres"
    assert one("Deployment")["spec"]["replicas"] >= 2, "every replica takes writes: scale freely"
    db, service = one("StatefulSet", DATABASE), one("Service", DATABASE)
    assert db["spec"]["replicas"] == 1 and db["spec"]["serviceName"] == service["metadata"]["name"]
    pods = db["spec"]["template"]["metadata"]["labels"]
    assert db["spec"]["selector"]["matchLabels"].items() <= pods.items()
    assert service["spec"]["selector"].items() <= pods.items()
    api_pods = one("Deployment")["spec"]["template"]["metadata"]["labels"]
    assert not service["spec"]["selector"].items() <= api_pods.items(), "database traffic to the API"
    assert not one("Service")["spec"]["selector"].items() <= pods.items(), "API traffic to the database"
    claim = db["spec"]["volumeClaimTemplates"][0]
    container_ = db["spec"]["template"]["spec"]["containers"][0]
    mounts = {m["name"]: m["mountPath"] for m in container_["volumeMounts"]}
    assert mounts[claim["metadata"]["name"]] == "/var/lib/postgresql/data"
    port = service["spec"]["ports"][0]
    assert port["port"] == 5432
    url = SECRET_SETTINGS[f"{ENV_PREFIX}DATABASE_URL"]
    assert f"@{service['metadata']['name']}:{port['port']}/" in url
