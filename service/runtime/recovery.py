"""Jobs the queue lost: enqueue queued jobs again, fail running jobs whose worker died.

Two crash windows leave a job row that nothing will ever finish: an API process killed between
committing the job row and enqueueing its id (the row says "queued", the queue is empty), and a
worker killed mid-job (the row says "running" for ever). Every worker sweeps for both when it
starts and then every ``job_sweep_seconds``. Re-enqueueing is safe because a job is claimed with
one conditional UPDATE (:func:`service.storage.jobs.start_job`): a duplicate id is skipped.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass, field
from datetime import timedelta

from sqlalchemy.orm import Session, sessionmaker

from service.config import Settings
from service.runtime.queue import Queue
from service.storage import jobs
from service.storage.db import transaction
from service.storage.models import JobStatus, utcnow

log = logging.getLogger(__name__)


@dataclass
class Recovery:
    requeued: list[int] = field(default_factory=list)
    failed: list[int] = field(default_factory=list)


def recover_jobs(settings: Settings, sessions: sessionmaker[Session], queue: Queue) -> Recovery:
    """One sweep: requeue lost queued jobs, fail running jobs without a heartbeat."""
    now = utcnow()
    found = Recovery()
    with transaction(sessions) as session:
        dead = jobs.stale_jobs(
            session,
            status=JobStatus.RUNNING,
            not_updated_since=now - timedelta(seconds=settings.job_stale_seconds),
        )
        for job in dead:
            message = (
                f"the worker running it stopped (no progress for {settings.job_stale_seconds:g} s);"
                " the active model version is unchanged: submit the job again"
            )
            jobs.finish_job(session, job=job, status=JobStatus.FAILED, message=message)
            found.failed.append(job.id)
    pending = queue.pending_job_ids()
    with sessions() as session:
        lost = [
            job.id
            for job in jobs.stale_jobs(
                session,
                status=JobStatus.QUEUED,
                not_updated_since=now - timedelta(seconds=settings.job_requeue_seconds),
            )
            if job.id not in pending
        ]
    for job_id in lost:
        queue.enqueue(job_id)
        found.requeued.append(job_id)
    if found.failed or found.requeued:
        log.warning("job sweep: failed %s (worker gone), requeued %s", found.failed, found.requeued)
    return found


def start_sweeper(
    settings: Settings, sessions: sessionmaker[Session], queue: Queue
) -> threading.Event:
    """Sweep now and then every ``job_sweep_seconds`` in a daemon thread; set the event to stop."""
    stop = threading.Event()

    def loop() -> None:
        while True:
            try:
                recover_jobs(settings, sessions, queue)
            except Exception:  # a sweep must never take the worker down
                log.exception("job sweep failed; retrying in %g s", settings.job_sweep_seconds)
            if stop.wait(settings.job_sweep_seconds):
                return

    threading.Thread(target=loop, name="loopnet-job-sweeper", daemon=True).start()
    return stop
