"""Automatic jobs: an atlas is calibrated when its frame count reaches a milestone, and adapted
when it has collected ``adapt_after_pairs`` new revisit pairs.

Checked in the transaction that stores a frame, so the job row commits with the frame that
crossed the milestone. Each milestone gets one job, ever; when another job of the atlas is
running at that moment, the first frame stored after it finishes creates it.
"""

from __future__ import annotations

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from service.config import Settings
from service.domain.pairs import MIN_ADAPTATION_PAIRS
from service.storage import jobs
from service.storage import repository as repo
from service.storage.models import Job, RevisitPair


def due_milestone(milestones: tuple[int, ...], frames: int) -> int | None:
    """The largest milestone ``frames`` has reached, if any."""
    reached = [m for m in milestones if m <= frames]
    return max(reached) if reached else None


def calibration_due(session: Session, settings: Settings, atlas_id: int) -> Job | None:
    """Create the calibration job of the milestone the atlas has just reached, if it has none."""
    if not settings.milestones:
        return None
    milestone = due_milestone(settings.milestones, repo.count_frames(session, atlas_id=atlas_id))
    if milestone is None:
        return None
    if jobs.calibration_jobs_for_milestone(session, atlas_id=atlas_id, milestone=milestone):
        return None
    if jobs.has_active_job(session, atlas_id=atlas_id):
        return None
    return jobs.create_job(
        session, atlas_id=atlas_id, kind="calibrate", params={"milestone": milestone}
    )


def adaptation_due(session: Session, settings: Settings, atlas_id: int) -> Job | None:
    """Create an adaptation job once the atlas has ``adapt_after_pairs`` revisit pairs newer
    than the ones its last adaptation job was queued with (off at 0, the default), and at
    least the pairs a job needs (``MIN_ADAPTATION_PAIRS``, a job's default ``min_pairs``: a job
    queued with fewer would only be refused)."""
    every = settings.adapt_after_pairs
    if every <= 0:
        return None
    total = session.scalar(
        select(func.count(RevisitPair.id)).where(RevisitPair.atlas_id == atlas_id)
    )
    if int(total or 0) < MIN_ADAPTATION_PAIRS:
        return None
    last = session.scalars(
        select(Job)
        .where(Job.atlas_id == atlas_id, Job.kind == "adapt")
        .order_by(Job.id.desc())
        .limit(1)
    ).first()
    through = int((last.params or {}).get("through_pair") or 0) if last is not None else 0
    newer = session.scalars(
        select(RevisitPair.id).where(RevisitPair.atlas_id == atlas_id, RevisitPair.id > through)
    ).all()
    if len(newer) < every or jobs.has_active_job(session, atlas_id=atlas_id):
        return None
    return jobs.create_job(
        session,
        atlas_id=atlas_id,
        kind="adapt",
        params={"through_pair": max(newer), "automatic": True},
    )
