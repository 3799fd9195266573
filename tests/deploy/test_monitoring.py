"""Prometheus scrape config and the Grafana dashboard: they must ask for metrics the service exports.

The metric and label names are taken from the service's own ``Metrics`` class after it recorded
one request and one engine call, and every dashboard query is parsed as PromQL, so a renamed
metric, a misspelt label or a broken query fails here instead of as an empty panel.
"""

from __future__ import annotations

import json
import re
from typing import Any

import promql_parser
import pytest
import yaml
from dockerfile_model import REPO
from prometheus_client.parser import text_string_to_metric_families

from service.api.metrics import Metrics

DOCKER = REPO / "docker"
DASHBOARD = DOCKER / "grafana" / "dashboards" / "complementme.json"
DATASOURCES = DOCKER / "grafana" / "provisioning" / "datasources" / "prometheus.yaml"
PROVIDERS = DOCKER / "grafana" / "provisioning" / "dashboards" / "complementme.yaml"


def exported_series() -> dict[str, set[str]]:
    """Sample name -> label names, as the service renders them at /metrics."""
    metrics = Metrics()
    metrics.observe_request("POST", "/suggest", 200, 0.004)
    metrics.observe_engine({"g": 0.001, "h_query": 0.0005, "h_head": 0.0002, "search": 0.0004,
                            "score": 0.0003}, batch_size=2, candidates=[40, 52])
    metrics.set_model("test-model", 10)
    series: dict[str, set[str]] = {}
    for family in text_string_to_metric_families(metrics.render().decode()):
        for sample in family.samples:
            series.setdefault(sample.name, set()).update(sample.labels)
    return series


def dashboard() -> dict[str, Any]:
    return json.loads(DASHBOARD.read_text())


def queries() -> list[tuple[str, str]]:
    return [(panel["title"], t["expr"]) for panel in dashboard()["panels"] for t in panel["targets"]]


def parse(expr: str):
    # Grafana substitutes $__rate_interval before Prometheus sees the query.
    return promql_parser.parse(expr.replace("$__rate_interval", "1m"))


def test_dashboard_covers_rate_latency_batches_and_errors() -> None:
    exprs = " ".join(e for _, e in queries())
    assert "complementme_http_requests_total" in exprs
    assert re.search(r"histogram_quantile\(0\.99, .*complementme_http_request_duration_seconds_bucket", exprs)
    assert "complementme_batch_size_bucket" in exprs
    assert 'status=~"5..' in exprs or 'status=~"4..|5..' in exprs


@pytest.mark.parametrize(("title", "expr"), queries())
def test_dashboard_query_uses_exported_metrics_and_labels(title: str, expr: str) -> None:
    series = exported_series()
    names: list[str] = []
    matcher_labels: list[str] = []
    grouping: list[str] = []

    def visit(node) -> None:
        if isinstance(node, promql_parser.VectorSelector):
            assert node.name, f"panel {title!r}: select metrics by name: {expr}"
            names.append(node.name)
            matcher_labels.extend(m.name for m in node.matchers.matchers)
        if isinstance(node, promql_parser.AggregateExpr) and node.modifier is not None:
            grouping.extend(node.modifier.labels)

    promql_parser.walk(parse(expr), visit)
    assert names, f"panel {title!r}: query selects no metric: {expr}"
    unknown = [n for n in names if n not in series]
    assert not unknown, (f"panel {title!r}: {unknown} not exported by service/api/metrics.py "
                         f"({sorted(series)})")
    labels = set().union(*(series[n] for n in names))
    missing = sorted(set(matcher_labels + grouping) - labels)
    assert not missing, f"panel {title!r}: labels {missing} not on {names}"


def test_parser_rejects_a_broken_query() -> None:
    with pytest.raises(Exception, match="parenthes"):
        parse("sum(rate(complementme_http_requests_total[$__rate_interval])")


def test_dashboard_panels_are_laid_out_and_use_the_provisioned_data_source() -> None:
    source = yaml.safe_load(DATASOURCES.read_text())["datasources"][0]
    board = dashboard()
    assert board["uid"] and board["title"]
    ids = [p["id"] for p in board["panels"]]
    assert len(ids) == len(set(ids)), "panel ids must be unique"
    for panel in board["panels"]:
        assert panel["datasource"]["uid"] == source["uid"], panel["title"]
        assert all(t["datasource"]["uid"] == source["uid"] for t in panel["targets"]), panel["title"]
        grid = panel["gridPos"]
        assert grid["x"] + grid["w"] <= 24, f"panel {panel['title']!r} runs past the 24-column grid"
    refs = [[t["refId"] for t in p["targets"]] for p in board["panels"]]
    assert all(len(r) == len(set(r)) for r in refs)


def test_prometheus_scrapes_the_service_metrics_endpoint() -> None:
    config = yaml.safe_load((DOCKER / "prometheus.yml").read_text())
    compose = yaml.safe_load((DOCKER / "compose.yaml").read_text())
    jobs = {job["job_name"]: job for job in config["scrape_configs"]}
    job = jobs["complementme"]
    assert job.get("metrics_path", "/metrics") == "/metrics"
    targets = [t for sc in job["static_configs"] for t in sc["targets"]]
    for target in targets:  # every replica
        host, port = target.split(":")
        assert host in compose["services"], f"scrape target {host} is no compose service"
        published = [p.split(":")[-1] for p in compose["services"][host]["ports"]]
        assert port in published, f"scrape port {port} is not the service's port {published}"
    replicas = {n for n, s in compose["services"].items() if s.get("image", "").startswith("complementme:")}
    assert {t.split(":")[0] for t in targets} == replicas, "Prometheus must scrape every replica"


def test_grafana_provisioning_matches_the_compose_mounts() -> None:
    compose = yaml.safe_load((DOCKER / "compose.yaml").read_text())
    grafana = compose["services"]["grafana"]
    mounts = {v["target"]: v["source"] for v in grafana["volumes"]}
    provider = yaml.safe_load(PROVIDERS.read_text())["providers"][0]
    dashboards_in = provider["options"]["path"]
    assert (DOCKER / mounts[dashboards_in]).resolve() == DASHBOARD.parent
    assert (DOCKER / mounts["/etc/grafana/provisioning"]).resolve() == PROVIDERS.parent.parent
    home = grafana["environment"]["GF_DASHBOARDS_DEFAULT_HOME_DASHBOARD_PATH"]
    assert home == f"{dashboards_in}/{DASHBOARD.name}"
    source = yaml.safe_load(DATASOURCES.read_text())["datasources"][0]
    host = source["url"].split("//")[1].split(":")[0]
    assert host in compose["services"], f"Grafana's data source {source['url']} is no compose service"
