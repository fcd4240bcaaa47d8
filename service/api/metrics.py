"""``GET /metrics``: Prometheus text exposition of this process.

Besides the histograms the code observes as it runs (``service.metrics``), a collector reads at
scrape time what this process holds: the inference gate, each loaded atlas's index and how far
it lags the database's change feed, and the jobs table (shared by every process; each replica
reports the same job figures).

Public metrics (``LOOPNET_METRICS_PUBLIC``, the default) name no atlas to a caller without a
key: the index figures then come as totals over the atlases (frames summed, lag the largest)
without the ``atlas`` label; a caller showing a valid key (any caller while the API is open;
an operator where metrics need a key) gets them per atlas, for the atlases its key may use.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request, Response
from fastapi.security import HTTPAuthorizationCredentials
from prometheus_client import CONTENT_TYPE_LATEST, REGISTRY, CollectorRegistry, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily
from prometheus_client.registry import Collector

from service.api.auth import (
    PRINCIPAL_KEY,
    api_key_header,
    bearer,
    client_address,
    get_authenticator,
    key_holder,
)
from service.fleet.keys import Principal, Role
from service.runtime import Runtime

router = APIRouter(tags=["metrics"])

JOB_BUCKETS = (1.0, 5.0, 15.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1800.0, 3600.0)
RECENT_JOBS = 1000  # finished jobs whose durations the histogram covers


class RuntimeCollector(Collector):
    """Gauges and counters read from a :class:`Runtime` at each scrape; index figures per atlas
    that ``viewer`` may use, or (``viewer`` None) as totals that name no atlas."""

    def __init__(self, runtime: Runtime, viewer: Principal | None) -> None:
        self.runtime = runtime
        self.viewer = viewer

    def collect(self) -> Iterator[Any]:
        runtime = self.runtime
        ready = GaugeMetricFamily("loopnet_ready", "1 once models and indexes are loaded.")
        ready.add_metric([], 1.0 if runtime.ready else 0.0)
        yield ready
        if not runtime.ready:
            return
        service = runtime.service
        yield from _gate(service.inference.stats())
        yield from self._indexes(service.served_indexes())
        age = GaugeMetricFamily(
            "loopnet_change_feed_sync_age_seconds",
            "Seconds since this process last caught up with the change feed.",
        )
        last_sync = runtime.last_sync
        if last_sync is not None:
            age.add_metric([], max(0.0, time.time() - last_sync))
        yield age
        figures = runtime.jobs.figures(RECENT_JOBS)
        jobs = GaugeMetricFamily(
            "loopnet_jobs", "Jobs by kind and state.", labels=["kind", "state"]
        )
        for kind, status, count in figures.counts:
            jobs.add_metric([kind, status], float(count))
        yield jobs
        yield _job_durations(figures.durations)

    def _indexes(self, served: Sequence[Any]) -> Iterator[Any]:
        viewer = self.viewer
        if viewer is not None:
            served = [one for one in served if viewer.may_use(one.atlas)]
        labels = ["atlas"] if viewer is not None else []
        count = GaugeMetricFamily("loopnet_atlases_served", "Atlases this process serves.")
        count.add_metric([], float(len(served)))
        size = GaugeMetricFamily(
            "loopnet_index_frames",
            "Frames in this process's index of the atlas (without a key: of all atlases).",
            labels=labels,
        )
        behind = GaugeMetricFamily(
            "loopnet_change_feed_revisions_behind",
            "Atlas revisions the database is ahead of this process's index (without a key: the "
            "largest over the atlases).",
            labels=labels,
        )
        if viewer is not None:
            for one in served:
                size.add_metric([one.atlas], float(one.frames))
                behind.add_metric([one.atlas], float(one.revisions_behind))
        else:
            size.add_metric([], float(sum(one.frames for one in served)))
            behind.add_metric([], float(max((one.revisions_behind for one in served), default=0)))
        yield from (count, size, behind)


def _gate(stats: Any) -> Iterator[Any]:
    for name, doc, value in (
        ("loopnet_admission_queue_depth", "Requests waiting for an inference slot.", stats.waiting),
        ("loopnet_admission_running", "Inferences running now.", stats.running),
        ("loopnet_admission_slots", "Inference slots (LOOPNET_INFERENCE_WORKERS).", stats.workers),
        (
            "loopnet_admission_queue_limit",
            "Waiters allowed (LOOPNET_INFERENCE_QUEUE).",
            stats.queue,
        ),
    ):
        gauge = GaugeMetricFamily(name, doc)
        gauge.add_metric([], float(value))
        yield gauge
    refused = CounterMetricFamily(
        "loopnet_admission_refused", "Requests refused by the inference gate (HTTP 503)."
    )
    refused.add_metric([], float(stats.refused))
    yield refused
    admitted = CounterMetricFamily("loopnet_admission_admitted", "Requests given a slot.")
    admitted.add_metric([], float(stats.admitted))
    yield admitted


def _job_durations(rows: Sequence[tuple[str, str, float]]) -> HistogramMetricFamily:
    """A histogram of the recent finished jobs' run times (started -> finished)."""
    family = HistogramMetricFamily(
        "loopnet_job_duration_seconds",
        f"Run time of the last {RECENT_JOBS} finished jobs, by kind and final state.",
        labels=["kind", "state"],
    )
    groups: dict[tuple[str, str], list[float]] = {}
    for kind, status, seconds in rows:
        groups.setdefault((kind, status), []).append(seconds)
    for labels, durations in sorted(groups.items()):
        buckets = [(str(b), float(sum(d <= b for d in durations))) for b in JOB_BUCKETS]
        buckets.append(("+Inf", float(len(durations))))
        family.add_metric(list(labels), buckets, sum(durations))
    return family


def metrics_access(
    request: Request,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
    api_key: Annotated[str | None, Depends(api_key_header)],
) -> Principal | None:
    """Open unless ``LOOPNET_METRICS_PUBLIC=false``; then an operator key is needed. Returns
    the caller whose atlases may be named (None: name none)."""
    runtime: Runtime = request.app.state.runtime
    if runtime.settings.metrics_public:
        return key_holder(request)
    authenticator = get_authenticator(request)
    principal: Principal | None = request.scope.get(PRINCIPAL_KEY)
    if principal is None:  # an app without the guard
        token = credentials.credentials if credentials is not None else api_key
        principal = authenticator.authenticate(token, client_address(request))
    return authenticator.authorize(principal, Role.operator, None)


@router.get(
    "/metrics",
    response_class=Response,
    responses={200: {"content": {CONTENT_TYPE_LATEST: {}}}},
    summary="Prometheus metrics of this process",
)
def metrics(
    request: Request, viewer: Annotated[Principal | None, Depends(metrics_access)]
) -> Response:
    registry = CollectorRegistry(auto_describe=False)
    registry.register(RuntimeCollector(request.app.state.runtime, viewer))
    body = generate_latest(REGISTRY) + generate_latest(registry)
    return Response(body, media_type=CONTENT_TYPE_LATEST)


def install(app: Any) -> None:
    """Serve ``/metrics`` (of ``app.state.runtime``) on ``app``."""
    app.include_router(router)
