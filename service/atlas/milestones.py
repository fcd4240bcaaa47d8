"""Automatic calibration: an atlas is calibrated when its frame count reaches a milestone.

Checked in the transaction that stores a frame, so the job row commits with the frame that
crossed the milestone. Each milestone gets one job, ever; when another job of the atlas is
running at that moment, the first frame stored after it finishes creates it.
"""

from __future__ import annotations

from sqlalchemy.orm import Session

from service.config import Settings
from service.storage import jobs
from service.storage import repository as repo
from service.storage.models import Job


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
