"""Revisit pairs: two stored frames of one place, what an adaptation job learns from.

``observe`` records one whenever its best candidate is geometrically verified (inliers at or
above the atlas's minimum; source ``observe``): the new frame and the frame it matched, often
across a change of condition or robot; and, unless the setting turns it off, whenever it
answers ``loop`` on its robot's sequence without such a match, or confirms the loops its robot's
frames just before left pending (source ``sequence``: each frame and its loop's frame), which on
low-texture or changed frames is most of the loops it closes. Operators label more through the
API (and delete wrong ones). A ``query`` keeps no frame, so it gives no pair. Pairs are chosen
for a job by robot, time and submap (:class:`PairFilter`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

from sqlalchemy import func, or_, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, aliased, sessionmaker

from service.app.milestones import adaptation_due
from service.app.results import QueryResult
from service.config import Settings
from service.domain.pairs import PairFilter as PairFilter
from service.errors import Conflict, InvalidInput, NotFound
from service.storage import repository as repo
from service.storage.db import transaction
from service.storage.models import Frame, RevisitPair, Submap

log = logging.getLogger(__name__)

SOURCES = ("observe", "sequence", "operator")


@dataclass(frozen=True)
class PairRow:
    """A pair as the API lists it."""

    pair: RevisitPair
    robot_id: str
    other_robot_id: str
    submap: str
    other_submap: str


def closure_partner(
    result: QueryResult, *, from_sequence_loops: bool
) -> tuple[int, str, int | None] | None:
    """The frame an observation's answer pairs its new frame with, the pair's source and the
    partner's inliers: the verified match (``observe``), else, when ``from_sequence_loops``,
    the frame of a ``loop`` answer that geometry did not verify (``sequence``); None when the
    answer is neither."""
    match = result.match
    if match is not None and match.verified:
        return match.frame_id, "observe", match.inliers
    if from_sequence_loops and result.status == "loop" and result.loop_frame_id is not None:
        inliers = next(
            (c.inliers for c in result.candidates if c.frame_id == result.loop_frame_id), None
        )
        return result.loop_frame_id, "sequence", inliers
    return None


def record_verified(
    sessions: sessionmaker[Session],
    settings: Settings,
    *,
    result: QueryResult,
    frame_id: int,
    enqueue: Callable[[int], None] | None = None,
) -> int | None:
    """Keep an observation's closure as a pair (its stored frame ``frame_id`` and the partner
    :func:`closure_partner` names), and the pending loops of the robot's earlier frames that
    this answer confirmed (source ``sequence``, as if each had been answered at once); queues an
    adaptation job when the atlas has collected its setting's number of new pairs. Returns the
    id of the pair of ``frame_id``, None when the answer is no closure."""
    for confirmed in result.confirmed if settings.pairs_from_sequence_loops else ():
        _keep_pair(
            sessions,
            settings,
            (confirmed.frame_id, confirmed.loop_frame_id, "sequence", None),
            enqueue,
        )
    partner = closure_partner(result, from_sequence_loops=settings.pairs_from_sequence_loops)
    if partner is None or partner[0] == frame_id:
        return None
    other_id, source, inliers = partner
    return _keep_pair(sessions, settings, (frame_id, other_id, source, inliers), enqueue)


def _keep_pair(
    sessions: sessionmaker[Session],
    settings: Settings,
    pair_of: tuple[int, int, str, int | None],
    enqueue: Callable[[int], None] | None,
) -> int | None:
    """Store the pair ``(frame, other frame, source, inliers)`` and queue the adaptation it
    makes due; None when either frame was deleted since the search or the pair is kept
    already (a pending loop onto the frame its observation verified)."""
    frame_id, other_id, source, inliers = pair_of
    job_id = None
    with transaction(sessions) as session:
        frame = session.get(Frame, frame_id)
        other = session.get(Frame, other_id)
        if frame is None or other is None or frame.atlas_id != other.atlas_id:
            return None  # deleted since the search
        kept = select(RevisitPair.id).where(
            (RevisitPair.frame_id == frame_id) & (RevisitPair.other_frame_id == other_id)
        )
        if session.scalar(kept) is not None:
            return None
        pair = RevisitPair(
            atlas_id=frame.atlas_id,
            frame_id=frame.id,
            other_frame_id=other.id,
            source=source,
            inliers=inliers,
        )
        session.add(pair)
        session.flush()
        job = adaptation_due(session, settings, frame.atlas_id)
        job_id = job.id if job is not None else None
        pair_id = pair.id
    if job_id is not None and enqueue is not None:
        try:
            enqueue(job_id)
        except Exception as exc:  # the job is stored queued; a worker's sweep will enqueue it
            log.warning("adaptation job %d not queued now (%s); a worker will find it", job_id, exc)
    return pair_id


def label_pair(sessions: sessionmaker[Session], *, atlas: str, frame_id: int, other: int) -> int:
    """An operator's pair of two frames of ``atlas`` (404 for a frame not in it, 422 for a
    frame with itself, 409 when the pair exists in either order)."""
    if frame_id == other:
        raise InvalidInput("a pair needs two different frames")
    try:
        with transaction(sessions) as session:
            found = repo.get_atlas(session, name=atlas)
            for frame in (frame_id, other):
                repo.get_frame(session, atlas=found, frame_id=frame)
            exists = session.scalar(
                select(RevisitPair.id).where(
                    or_(
                        (RevisitPair.frame_id == frame_id) & (RevisitPair.other_frame_id == other),
                        (RevisitPair.frame_id == other) & (RevisitPair.other_frame_id == frame_id),
                    )
                )
            )
            if exists is not None:
                raise Conflict(f"frames {frame_id} and {other} are already pair {exists}")
            pair = RevisitPair(
                atlas_id=found.id, frame_id=frame_id, other_frame_id=other, source="operator"
            )
            session.add(pair)
            session.flush()
            return int(pair.id)
    except IntegrityError as exc:  # the same pair written concurrently
        raise Conflict(f"frames {frame_id} and {other} are already a pair") from exc


def delete_pair(sessions: sessionmaker[Session], *, atlas: str, pair_id: int) -> None:
    """Delete one pair of ``atlas`` (404 when it has no such pair)."""
    with transaction(sessions) as session:
        found = repo.get_atlas(session, name=atlas)
        pair = session.get(RevisitPair, pair_id)
        if pair is None or pair.atlas_id != found.id:
            raise NotFound(f"atlas '{atlas}' has no revisit pair {pair_id}")
        session.delete(pair)


def _filtered(atlas_id: int, where: PairFilter):  # type: ignore[no-untyped-def]
    """The select of (pair, robot, other robot, submap, other submap) under ``where``."""
    first, second = aliased(Frame), aliased(Frame)
    first_submap, second_submap = aliased(Submap), aliased(Submap)
    query = (
        select(RevisitPair, first.robot_id, second.robot_id, first_submap.name, second_submap.name)
        .join(first, first.id == RevisitPair.frame_id)
        .join(second, second.id == RevisitPair.other_frame_id)
        .join(first_submap, first_submap.id == first.submap_id)
        .join(second_submap, second_submap.id == second.submap_id)
        .where(RevisitPair.atlas_id == atlas_id)
    )
    if where.robots:
        query = query.where(
            or_(first.robot_id.in_(where.robots), second.robot_id.in_(where.robots))
        )
    if where.submaps:
        query = query.where(
            or_(first_submap.name.in_(where.submaps), second_submap.name.in_(where.submaps))
        )
    if where.since is not None:
        query = query.where(RevisitPair.created_at >= where.since)
    if where.until is not None:
        query = query.where(RevisitPair.created_at < where.until)
    return query


def list_pairs(
    sessions: sessionmaker[Session], *, atlas: str, where: PairFilter, limit: int = 100
) -> list[PairRow]:
    """Newest first."""
    with sessions() as session:
        found = repo.get_atlas(session, name=atlas)
        query = _filtered(found.id, where).order_by(
            RevisitPair.created_at.desc(), RevisitPair.id.desc()
        )
        return [PairRow(*row) for row in session.execute(query.limit(limit))]


def get_pair(sessions: sessionmaker[Session], *, atlas: str, pair_id: int) -> PairRow:
    """One pair of ``atlas`` (404 when it has no such pair)."""
    with sessions() as session:
        found = repo.get_atlas(session, name=atlas)
        row = session.execute(
            _filtered(found.id, PairFilter()).where(RevisitPair.id == pair_id)
        ).first()
        if row is None:
            raise NotFound(f"atlas '{atlas}' has no revisit pair {pair_id}")
        return PairRow(*row)


def pair_frames(
    session: Session, *, atlas_id: int, where: PairFilter
) -> list[tuple[int, int, int]]:
    """The (pair, frame, other frame) ids of every pair under ``where``, oldest first."""
    query = _filtered(atlas_id, where).order_by(RevisitPair.id)
    return [(row[0].id, row[0].frame_id, row[0].other_frame_id) for row in session.execute(query)]


def pair_sources(session: Session, *, atlas_id: int, where: PairFilter) -> dict[str, int]:
    """How many pairs under ``where`` came from each source."""
    chosen = _filtered(atlas_id, where).subquery()
    rows = session.execute(select(chosen.c.source, func.count()).group_by(chosen.c.source))
    return {str(source): int(n) for source, n in rows}


def count_pairs(session: Session, *, atlas_id: int, after_id: int = 0) -> int:
    """Pairs of the atlas with an id above ``after_id`` (0: all)."""
    return int(
        session.scalar(
            select(func.count(RevisitPair.id)).where(
                RevisitPair.atlas_id == atlas_id, RevisitPair.id > after_id
            )
        )
        or 0
    )
