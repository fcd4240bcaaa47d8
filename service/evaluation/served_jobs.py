"""The jobs a served replay's frames queue (a calibration milestone, automatic adaptation),
run in this process before the next frame, as a worker would between two frames: the harness
then measures the atlas the service would be serving. Shared by ``loopnet eval``'s robot row
(:mod:`service.evaluation.served_pass`) and ``eval-online``'s
(:mod:`service.evaluation.online_served`).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from service.app.catalog import AtlasService
from service.config import Settings
from service.jobs.retraining import JobRunner
from service.storage import jobs
from service.storage.models import Job


@dataclass(frozen=True)
class JobRun:
    """A job a frame queued and the replay ran before the next frame.

    Attributes:
        frame: the frame (query) whose insert or observation queued it.
        milestone: the calibration milestone it was queued for (None: another kind).
        model_version: the version it published (None: it published none).
        seconds: wall time of the job and of loading its version.
        frames_at_fit: frames the calibration was fitted on.
        min_inliers: the minimum inliers it calibrated on the atlas's hard impostors.
        message: the job's one line to the operator (whether its version became active, and
            the gate's figures for an adapt job).
    """

    job_id: int
    kind: str
    frame: int
    milestone: int | None
    status: str
    model_version: int | None
    seconds: float
    frames_at_fit: int | None = None
    min_inliers: int | None = None
    error: str | None = None
    message: str = ""


def run_job_now(service: AtlasService, job_id: int, settings: Settings | None = None) -> Job:
    """Run a queued job in this process as a worker would (the job runner's own code, with
    ``settings``, default the service's), then bring the service's loaded atlases up to date;
    returns the finished job row."""
    JobRunner(settings or service.settings, service.sessions).run(job_id)
    with service.sessions() as session:
        job = jobs.get_job(session, job_id=job_id)
        session.expunge(job)
    service.catch_up()
    return job


def run_queued(service: AtlasService, job_id: int, frame: int) -> JobRun:
    """Run one job ``frame`` queued now; a failed job is reported, the replay goes on (as the
    service goes on answering with its active version)."""
    start = time.perf_counter()
    job = run_job_now(service, job_id)
    metrics = job.metrics or {}
    verification = metrics.get("verification") or {}
    return JobRun(
        job_id=job.id,
        kind=job.kind,
        frame=frame,
        milestone=(job.params or {}).get("milestone"),
        status=job.status,
        model_version=job.model_version,
        seconds=round(time.perf_counter() - start, 3),
        frames_at_fit=metrics.get("frames_at_fit"),
        min_inliers=verification.get("min_inliers"),
        error=job.error,
        message=job.message or "",
    )


@contextmanager
def queued_jobs(service: AtlasService, adapt_after_pairs: int | None = None) -> Iterator[list[int]]:
    """While the block runs, the ids of the jobs the service queues are collected in the list
    yielded, for the caller to run (:func:`run_queued`), instead of going to the process's
    queue; ``adapt_after_pairs`` (None: the service's setting as it is) sets automatic
    adaptation for the block."""
    queued: list[int] = []
    before = (service.settings, service.frames.enqueue)
    if adapt_after_pairs is not None:
        update = {"adapt_after_pairs": adapt_after_pairs}
        service.settings = service.settings.model_copy(update=update)
    service.frames.enqueue = queued.append
    try:
        yield queued
    finally:
        service.settings, service.frames.enqueue = before
