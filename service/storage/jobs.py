"""Job rows: the API's view of queued work, written by the API and the worker alike."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from service.errors import Conflict, NotFound
from service.storage.models import Job, JobStatus, utcnow

# the values, as the column holds them (drivers need not know the enum)
ACTIVE = (JobStatus.QUEUED.value, JobStatus.RUNNING.value)
FINISHED = (JobStatus.SUCCEEDED.value, JobStatus.FAILED.value, JobStatus.CANCELLED.value)


def create_job(session: Session, *, atlas_id: int, kind: str, params: dict[str, Any]) -> Job:
    """A queued job; one job per atlas at a time (a second gets 409): every kind writes the
    atlas's next model version."""
    busy = session.scalar(select(Job).where(Job.atlas_id == atlas_id, Job.status.in_(ACTIVE)))
    if busy is not None:
        raise Conflict(
            f"a {busy.kind} job for this atlas is already {busy.status} (job {busy.id}); "
            "submit again when it has finished, or cancel it"
        )
    job = Job(
        atlas_id=atlas_id,
        kind=kind,
        status=JobStatus.QUEUED.value,
        progress=0.0,
        message="queued",
        params=params,
        metrics={},
        cancel_requested=False,
    )
    session.add(job)
    session.flush()
    return job


def calibration_jobs_for_milestone(session: Session, *, atlas_id: int, milestone: int) -> int:
    """How many calibration jobs were ever created for an atlas's frame-count milestone."""
    found = session.scalars(select(Job).where(Job.atlas_id == atlas_id, Job.kind == "calibrate"))
    return sum(1 for job in found if (job.params or {}).get("milestone") == milestone)


def has_active_job(session: Session, *, atlas_id: int) -> bool:
    return (
        session.scalar(select(Job.id).where(Job.atlas_id == atlas_id, Job.status.in_(ACTIVE)))
        is not None
    )


def get_job(session: Session, *, job_id: int, atlas_id: int | None = None) -> Job:
    job = session.get(Job, job_id)
    if job is None or (atlas_id is not None and job.atlas_id != atlas_id):
        raise NotFound(f"job {job_id} does not exist")
    return job


def list_jobs(session: Session, *, atlas_id: int, limit: int = 100) -> list[Job]:
    query = select(Job).where(Job.atlas_id == atlas_id).order_by(Job.id.desc()).limit(limit)
    return list(session.scalars(query))


def start_job(session: Session, *, job_id: int) -> Job | None:
    """Claim a queued job (mark it running); None if it was cancelled or taken meanwhile.

    The claim is one conditional UPDATE, so of two workers handed the same id (a job
    re-enqueued by :func:`stale_jobs`' sweep, say) exactly one runs it, on SQLite and
    PostgreSQL alike.
    """
    now = utcnow()
    claimed = session.execute(
        update(Job)
        .where(
            Job.id == job_id, Job.status == JobStatus.QUEUED.value, Job.cancel_requested.is_(False)
        )
        .values(status=JobStatus.RUNNING.value, started_at=now, updated_at=now, message="started")
        .execution_options(synchronize_session=False)
    )
    job = session.get(Job, job_id, populate_existing=True)
    if job is None:
        return None
    if claimed.rowcount != 1:  # type: ignore[attr-defined]
        if job.status == JobStatus.QUEUED and job.cancel_requested:
            finish_job(
                session, job=job, status=JobStatus.CANCELLED, message="cancelled before it started"
            )
        return None
    return job


def stale_jobs(session: Session, *, status: str, not_updated_since: datetime) -> list[Job]:
    """Jobs in ``status`` whose row has not changed since the given time (oldest first)."""
    query = (
        select(Job)
        .where(Job.status == JobStatus(status).value, Job.updated_at < not_updated_since)
        .order_by(Job.id)
    )
    return list(session.scalars(query))


def report_progress(session: Session, *, job_id: int, progress: float, message: str) -> bool:
    """Record progress (0..100); returns whether cancellation was requested."""
    job = session.get(Job, job_id)
    if job is None:
        return True
    job.progress = round(max(0.0, min(100.0, progress)), 1)
    job.message = message[:500]
    job.updated_at = utcnow()
    return job.cancel_requested


def finish_job(
    session: Session,
    *,
    job: Job,
    status: str,
    message: str,
    metrics: dict[str, Any] | None = None,
    error: str | None = None,
    model_version: int | None = None,
) -> None:
    assert status in FINISHED, status
    job.status, job.message, job.error = (
        JobStatus(status).value,
        message[:500],
        error[:4000] if error else None,
    )
    if status == JobStatus.SUCCEEDED:
        job.progress = 100.0
    if metrics is not None:
        job.metrics = metrics
    job.model_version = model_version
    job.finished_at = job.updated_at = utcnow()


def request_cancel(session: Session, *, job: Job) -> Job:
    """Cancel a queued job at once; ask a running one to stop at its next checkpoint."""
    if job.status in FINISHED:
        raise Conflict(f"job {job.id} has already {job.status}")
    job.cancel_requested = True
    job.updated_at = utcnow()
    if job.status == JobStatus.QUEUED:
        finish_job(
            session, job=job, status=JobStatus.CANCELLED, message="cancelled before it started"
        )
    else:
        job.message = "cancellation requested"
    return job
