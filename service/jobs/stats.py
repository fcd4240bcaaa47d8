"""Figures about the jobs table that ``/metrics`` reports: jobs by kind and state, and the run
times of the recently finished ones."""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import func, select
from sqlalchemy.orm import Session, sessionmaker

from service.storage.models import Job


@dataclass(frozen=True)
class JobFigures:
    counts: list[tuple[str, str, int]]  # (kind, state, jobs)
    durations: list[tuple[str, str, float]]  # (kind, final state, seconds), newest first


def job_figures(sessions: sessionmaker[Session], recent: int) -> JobFigures:
    """Counts of every job and the run times of the last ``recent`` finished ones."""
    with sessions() as session:
        counts = session.execute(
            select(Job.kind, Job.status, func.count(Job.id)).group_by(Job.kind, Job.status)
        ).all()
        finished = session.execute(
            select(Job.kind, Job.status, Job.started_at, Job.finished_at)
            .where(Job.finished_at.is_not(None), Job.started_at.is_not(None))
            .order_by(Job.id.desc())
            .limit(recent)
        ).all()
    return JobFigures(
        [(kind, str(status), int(n)) for kind, status, n in counts],
        [
            (kind, str(status), (end - start).total_seconds())
            for kind, status, start, end in finished
            if start is not None and end is not None  # the query's filter; narrows the types
        ],
    )
