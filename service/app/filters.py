"""Which frames a query may match: by robot (own, others, all), submap and capture time, minus
the asking robot's own most recent frames (online SLAM: the frames just behind a robot are not
loop closures).

The filters resolve, in the database, to a set of frame ids the index search keeps
(``include``) and a set it drops (``exclude``); ``include`` is None when every frame may match.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from service.app.names import validate_name
from service.config import Settings
from service.errors import InvalidInput
from service.storage import repository as repo
from service.storage.models import Atlas, Frame

RobotScope = Literal["all", "own", "others"]
ROBOT_SCOPES: tuple[RobotScope, ...] = ("all", "own", "others")
# The SQL LIMIT of the recent-frame exclusion is a BIGINT: larger is a bad request, not a 500.
MAX_RECENT_FRAMES = 2**63 - 1


@dataclass(frozen=True)
class QueryFilter:
    """A query's filters.

    Attributes:
        robot_id: the robot asking (None: anonymous; no own-frame exclusion).
        robots: "all" frames, the asking robot's "own", or "others"' only.
        submap: only frames of this submap.
        since, until: only frames whose timestamp lies in [since, until] (frames without a
            timestamp are left out when either is given).
        timestamp: the query frame's capture time, the reference of ``exclude_recent_seconds``
            (None: the asking robot's latest frame timestamp).
        exclude_recent_frames: the asking robot's last N inserted frames never match.
        exclude_recent_seconds: nor do its frames taken within T seconds of ``timestamp``.
    """

    robot_id: str | None = None
    robots: str = "all"
    submap: str | None = None
    since: float | None = None
    until: float | None = None
    timestamp: float | None = None
    exclude_recent_frames: int = 0
    exclude_recent_seconds: float = 0.0

    def validate(self) -> None:
        if self.robots not in ROBOT_SCOPES:
            raise InvalidInput(
                f"robots must be one of {', '.join(ROBOT_SCOPES)}, got {self.robots!r}"
            )
        if self.robots != "all" and self.robot_id is None:
            raise InvalidInput(f"robots={self.robots!r} needs robot_id (the robot asking)")
        for name in ("since", "until", "timestamp"):
            value = getattr(self, name)
            if value is not None and not math.isfinite(value):
                raise InvalidInput(f"{name} must be a finite number of seconds")
        if self.since is not None and self.until is not None and self.since > self.until:
            raise InvalidInput(f"since ({self.since}) is after until ({self.until})")
        if self.exclude_recent_frames < 0:
            raise InvalidInput("exclude_recent_frames must be 0 or more")
        if self.exclude_recent_frames > MAX_RECENT_FRAMES:
            raise InvalidInput(f"exclude_recent_frames must be at most {MAX_RECENT_FRAMES}")
        if not math.isfinite(self.exclude_recent_seconds) or self.exclude_recent_seconds < 0:
            raise InvalidInput("exclude_recent_seconds must be a finite number, 0 or more")

    @property
    def restricts(self) -> bool:
        """Whether only a subset of the atlas may match (before the recent-frame exclusion)."""
        return (
            self.robots != "all"
            or self.submap is not None
            or self.since is not None
            or self.until is not None
        )


@dataclass(frozen=True)
class Selection:
    """Frame ids for the index search: keep only ``include`` (None: all), then drop ``exclude``."""

    include: np.ndarray | None
    exclude: np.ndarray


def resolve(session: Session, atlas: Atlas, query_filter: QueryFilter) -> Selection:
    """The frames a query may match, from the database (unknown submap: NotFound)."""
    query_filter.validate()
    include = None
    if query_filter.restricts:
        query = select(Frame.id).where(Frame.atlas_id == atlas.id)
        if query_filter.robots == "own":
            query = query.where(Frame.robot_id == query_filter.robot_id)
        elif query_filter.robots == "others":
            query = query.where(Frame.robot_id != query_filter.robot_id)
        if query_filter.submap is not None:
            submap = repo.get_submap(session, atlas=atlas, name=query_filter.submap)
            query = query.where(Frame.submap_id == submap.id)
        if query_filter.since is not None:
            query = query.where(Frame.timestamp >= query_filter.since)
        if query_filter.until is not None:
            query = query.where(Frame.timestamp <= query_filter.until)
        include = np.fromiter(session.scalars(query), np.int64)
    return Selection(include, recent_own_frames(session, atlas.id, query_filter))


def recent_own_frames(session: Session, atlas_id: int, query_filter: QueryFilter) -> np.ndarray:
    """The asking robot's frames that may not match: its last N inserted (highest ids) and those
    taken within T seconds of the query's timestamp (or of its latest frame's)."""
    robot = query_filter.robot_id
    if robot is None:
        return np.zeros(0, np.int64)
    own = (Frame.atlas_id == atlas_id) & (Frame.robot_id == robot)
    ids: set[int] = set()
    if query_filter.exclude_recent_frames > 0:
        last = select(Frame.id).where(own).order_by(Frame.id.desc())
        ids.update(session.scalars(last.limit(query_filter.exclude_recent_frames)))
    if query_filter.exclude_recent_seconds > 0:
        now = query_filter.timestamp
        if now is None:
            now = session.scalar(select(func.max(Frame.timestamp)).where(own))
        if now is not None:
            window = select(Frame.id).where(
                own, Frame.timestamp >= now - query_filter.exclude_recent_seconds
            )
            ids.update(session.scalars(window))
    return np.array(sorted(ids), np.int64)


def make_filter(
    settings: Settings,
    *,
    robot_id: str | None = None,
    robots: str = "all",
    submap: str | None = None,
    since: float | None = None,
    until: float | None = None,
    timestamp: float | None = None,
    exclude_recent_frames: int | None = None,
    exclude_recent_seconds: float | None = None,
) -> QueryFilter:
    """A validated :class:`QueryFilter`, with the settings' recent-frame exclusion unless the
    request overrides it (empty strings, as forms send them, mean "not given")."""
    robot_id = robot_id or None
    submap = submap or None
    if robot_id is not None:
        validate_name("robot", robot_id)
    if submap is not None:
        validate_name("submap", submap)
    query_filter = QueryFilter(
        robot_id=robot_id,
        robots=robots,
        submap=submap,
        since=since,
        until=until,
        timestamp=timestamp,
        exclude_recent_frames=(
            settings.exclude_recent_frames
            if exclude_recent_frames is None
            else exclude_recent_frames
        ),
        exclude_recent_seconds=(
            settings.exclude_recent_seconds
            if exclude_recent_seconds is None
            else exclude_recent_seconds
        ),
    )
    query_filter.validate()
    return query_filter
