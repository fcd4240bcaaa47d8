"""Jobs lost by crashes: the worker's sweep re-enqueues them or fails them; claims are atomic.

Real SQLite database and real Huey queue file; no CNN is needed (jobs are rows and queue ids).
"""

from __future__ import annotations

from datetime import timedelta
from pathlib import Path

import pytest
from sqlalchemy.orm import Session, sessionmaker

from service.config import Settings
from service.runtime.queue import Queue
from service.runtime.recovery import recover_jobs
from service.storage import jobs
from service.storage import repository as repo
from service.storage.db import make_engine, make_session_factory, transaction, upgrade_database
from service.storage.models import Job, utcnow
from tests.conftest import make_settings


@pytest.fixture
def setup(tmp_path: Path):  # type: ignore[no-untyped-def]
    settings = make_settings(tmp_path / "data", job_stale_seconds=60.0, job_requeue_seconds=30.0)
    settings.data_dir.mkdir(parents=True)
    upgrade_database(settings.resolved_database_url)
    engine = make_engine(settings.resolved_database_url)
    sessions = make_session_factory(engine)
    with transaction(sessions) as session:  # one active retrain job per atlas: two atlases
        atlas_ids = [
            repo.create_atlas(session, name=name, description="", feature_signature={}).id
            for name in ("campus", "harbour")
        ]
    yield settings, sessions, Queue(settings), atlas_ids
    engine.dispose()


def new_job(sessions: sessionmaker[Session], atlas_id: int, age_seconds: float = 0.0) -> int:
    with transaction(sessions) as session:
        job = jobs.create_job(session, atlas_id=atlas_id, kind="retrain", params={})
        job.updated_at = utcnow() - timedelta(seconds=age_seconds)
        return job.id


def set_row(sessions: sessionmaker[Session], job_id: int, **values: object) -> None:
    with transaction(sessions) as session:
        job = session.get(Job, job_id)
        assert job is not None
        for name, value in values.items():
            setattr(job, name, value)


def status(sessions: sessionmaker[Session], job_id: int) -> tuple[str, str]:
    with sessions() as session:
        job = jobs.get_job(session, job_id=job_id)
        return job.status, job.message


def test_a_queued_job_missing_from_the_queue_is_enqueued_again_once(setup) -> None:  # type: ignore[no-untyped-def]
    settings, sessions, queue, (campus, harbour) = setup
    lost = new_job(sessions, campus, age_seconds=120)  # committed, enqueue lost in a crash
    fresh = new_job(sessions, harbour, age_seconds=0)  # its API call may still be enqueueing
    assert queue.pending_job_ids() == set()

    first = recover_jobs(settings, sessions, queue)
    assert first.requeued == [lost] and first.failed == []
    assert queue.pending_job_ids() == {lost}
    # already waiting in the queue: the next sweep leaves it alone
    assert recover_jobs(settings, sessions, queue).requeued == []
    assert status(sessions, fresh)[0] == "queued"


def test_a_running_job_without_heartbeat_is_failed_and_a_live_one_is_not(setup) -> None:  # type: ignore[no-untyped-def]
    settings, sessions, queue, (campus, harbour) = setup
    dead, live = new_job(sessions, campus), new_job(sessions, harbour)
    for job_id in (dead, live):
        with transaction(sessions) as session:
            assert jobs.start_job(session, job_id=job_id) is not None
    set_row(sessions, dead, updated_at=utcnow() - timedelta(seconds=600))

    found = recover_jobs(settings, sessions, queue)
    assert found.failed == [dead] and found.requeued == []
    state, message = status(sessions, dead)
    assert state == "failed" and "worker running it stopped" in message
    assert status(sessions, live)[0] == "running"


def test_a_job_is_claimed_once_even_when_enqueued_twice(setup) -> None:  # type: ignore[no-untyped-def]
    _, sessions, _, (atlas_id, _) = setup
    job_id = new_job(sessions, atlas_id)
    with transaction(sessions) as session:
        assert jobs.start_job(session, job_id=job_id) is not None
    with transaction(sessions) as session:  # the duplicate id: skipped
        assert jobs.start_job(session, job_id=job_id) is None
    assert status(sessions, job_id)[0] == "running"


def test_a_cancelled_queued_job_is_not_claimed(setup) -> None:  # type: ignore[no-untyped-def]
    _, sessions, _, (atlas_id, _) = setup
    job_id = new_job(sessions, atlas_id)
    set_row(sessions, job_id, cancel_requested=True)
    with transaction(sessions) as session:
        assert jobs.start_job(session, job_id=job_id) is None
    assert status(sessions, job_id)[0] == "cancelled"


def test_recovery_settings_are_validated() -> None:
    with pytest.raises(ValueError):
        Settings(job_stale_seconds=0)
