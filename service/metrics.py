"""Prometheus metrics the service's own code observes (request latency, inference stages,
admission waits). State read at scrape time (gate, indexes, jobs, change feed) is collected by
``service.api.metrics``; both end up on ``GET /metrics``."""

from __future__ import annotations

from collections.abc import Mapping

from prometheus_client import Histogram

LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)

REQUEST_SECONDS = Histogram(
    "loopnet_http_request_duration_seconds",
    "HTTP request latency by method, route template and status code.",
    ["method", "route", "status"],
    buckets=LATENCY_BUCKETS,
)
STAGE_SECONDS = Histogram(
    "loopnet_inference_stage_seconds",
    "Time of each inference stage (decode, local/global features, heads, search, verification).",
    ["stage"],
    buckets=LATENCY_BUCKETS,
)
ADMISSION_WAIT_SECONDS = Histogram(
    "loopnet_admission_wait_seconds",
    "Time a request waited at the inference gate before getting a slot or a 503.",
    buckets=(0.0, 0.001, 0.01, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0),
)


def observe_stages(timings_ms: Mapping[str, float]) -> None:
    """Record stage timings given in milliseconds (the shape ``timings_ms`` has everywhere)."""
    for stage, ms in timings_ms.items():
        STAGE_SECONDS.labels(stage).observe(ms / 1000.0)
