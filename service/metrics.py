"""Prometheus metrics the service's own code observes (request latency, inference stages,
admission waits). State read at scrape time (gate, indexes, jobs, change feed) is collected by
``service.api.metrics``; both end up on ``GET /metrics``."""

from __future__ import annotations

from collections.abc import Mapping

from prometheus_client import Histogram

# Every label takes its values from a closed set, or each odd value a client sends becomes a
# series of its own (a request's method is whatever token the client writes: 300 requests with
# 2,000-character methods once grew /metrics tenfold). Routes are the app's path templates.
HTTP_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})
OTHER_METHOD = "other"


def method_label(method: str) -> str:
    """The ``method`` label of a request: a standard HTTP method, else ``other``."""
    return method if method in HTTP_METHODS else OTHER_METHOD


LATENCY_BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0, 60.0)

REQUEST_SECONDS = Histogram(
    "loopnet_http_request_duration_seconds",
    "HTTP request latency by method (standard ones; 'other'), route template ('unmatched' for "
    "paths the API does not serve) and status code.",
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
