"""The compose file's optional Prometheus scrapes the API replicas, and the Grafana dashboard
reads only series the service exports."""

from __future__ import annotations

import json
import re
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
EXPORTERS = (ROOT / "service" / "metrics.py", ROOT / "service" / "api" / "metrics.py")


def exported_names() -> set[str]:
    names = set()
    for path in EXPORTERS:
        names |= set(re.findall(r'"(loopnet_[a-z_]+)"', path.read_text()))
    return names


def test_prometheus_scrapes_every_api_replica_under_an_optional_profile() -> None:
    services = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]
    prometheus, grafana = services["prometheus"], services["grafana"]
    assert prometheus["profiles"] == grafana["profiles"] == ["metrics"]
    mounted = {v.split(":")[0] for v in prometheus["volumes"]}
    assert "./deploy/prometheus/prometheus.yml" in mounted
    config = yaml.safe_load((ROOT / "deploy" / "prometheus" / "prometheus.yml").read_text())
    (job,) = config["scrape_configs"]
    assert job["metrics_path"] == "/metrics"
    (discovery,) = job["dns_sd_configs"]
    assert discovery["names"] == ["api"] and discovery["port"] == 8000  # one record per replica


def test_dashboard_queries_only_exported_series() -> None:
    dashboard = json.loads((ROOT / "deploy" / "grafana" / "loopnet.json").read_text())
    exprs = [t["expr"] for panel in dashboard["panels"] for t in panel["targets"]]
    used = {
        re.sub(r"_(bucket|sum|count|total)$", "", n)
        for e in exprs
        for n in re.findall(r"loopnet_[a-z_]+", e)
    }
    exported = exported_names()
    assert used <= exported, used - exported
    for family in (
        "loopnet_http_request_duration_seconds",
        "loopnet_inference_stage_seconds",
        "loopnet_admission_queue_depth",
        "loopnet_admission_refused",
        "loopnet_index_frames",
        "loopnet_jobs",
        "loopnet_job_duration_seconds",
        "loopnet_change_feed_sync_age_seconds",
    ):
        assert family in used, family
