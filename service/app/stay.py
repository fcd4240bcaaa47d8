"""A robot's current stay: its newest frames that still show the place it is asking about.

A robot that stands still (a train at a station, a robot waiting at a door) keeps sending frames
of one place. The recent-frame exclusion (``exclude_recent_frames`` / ``_seconds``) covers a
fixed window; once the robot has stood longer than that, its own frames from the start of the
stop fall outside it and verify perfectly: a loop with itself that odometry already knows, which
a SLAM back end must not receive. A loop with its own past needs evidence that the robot left
the place in between.

The stay is read from the robot's frames newest first, each scored against the query frame by
the calibrated score against impostors (each frame judged on its own, not as the best of a
search: no ``log10(frames)`` is added), with hysteresis, since a stopped robot's frames vary
(people pass, light changes): from ``loop_score_min`` a frame shows the place, below
``ELSEWHERE_SCORE`` another place (:mod:`service.ml.stays` walks it). The stay never matches;
everything older may. On an uncalibrated model version there is no score that says "as alike
as the same place" (the cosine of unrelated frames may exceed any fixed threshold), so no stay
is recognised and only the recent-frame exclusion applies.

A sequence holds each of its frames to the same rule: the stays of its earlier frames (read
among the robot's frames older than each) are left out of its alignment too
(:class:`~service.app.sequences.SequenceScorer`).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from sqlalchemy.orm import Session

from service.app.sequence_map import SequenceMap
from service.app.state import LoadedAtlas
from service.config import Settings
from service.ml.stays import ELSEWHERE_SCORE, StayRule
from service.storage import repository as repo


def stay_rule(state: LoadedAtlas, settings: Settings) -> StayRule | None:
    """The rule on the atlas's active version; None with ``exclude_stay`` off or on an
    uncalibrated version (no score says "as alike as the same place")."""
    if not settings.exclude_stay or not state.model.scores:
        return None
    model = state.model

    def scores(similarities: np.ndarray) -> np.ndarray:
        out = np.full(len(similarities), np.nan)
        known = np.isfinite(similarities)
        out[known] = np.asarray(model.score(similarities[known].astype(np.float64)))
        return out

    return StayRule(
        scores,
        alike=settings.loop_score_min,
        elsewhere=min(ELSEWHERE_SCORE, settings.loop_score_min),
    )


class RobotFrames:
    """One robot's frame ids newest first (ids grow with arrival), read from the database once
    per request in growing chunks: the stays of a query and of its sequence's frames all walk
    the same few dozen frames."""

    CHUNK = 64

    def __init__(self, session: Session, atlas_id: int, robot_id: str) -> None:
        self.session, self.atlas_id, self.robot_id = session, atlas_id, robot_id
        self._ids = np.zeros(0, np.int64)
        self._complete = False

    def _read_to(self, count: int) -> None:
        """Hold at least ``count`` ids (or all there are)."""
        while len(self._ids) < count and not self._complete:
            wanted = max(count - len(self._ids), self.CHUNK, len(self._ids))
            more = repo.robot_frames_newest_first(
                self.session,
                atlas_id=self.atlas_id,
                robot_id=self.robot_id,
                offset=len(self._ids),
                limit=wanted,
            )
            self._complete = len(more) < wanted
            self._ids = np.concatenate([self._ids, more])

    def older_than(self, frame_id: int | None) -> Callable[[int, int], np.ndarray]:
        """``(offset, limit)`` -> ids older than ``frame_id`` (None: all), newest first."""

        def own_frames(offset: int, limit: int) -> np.ndarray:
            start = 0
            if frame_id is not None:
                while not self._complete and (not len(self._ids) or self._ids[-1] >= frame_id):
                    self._read_to(len(self._ids) + self.CHUNK)
                start = int(np.count_nonzero(self._ids >= frame_id))
            self._read_to(start + offset + limit)
            return self._ids[start + offset : start + offset + limit]

        return own_frames


def frame_stay(
    own: RobotFrames,
    view: SequenceMap,
    rule: StayRule,
    vector: np.ndarray,
    before: int | None = None,
) -> np.ndarray:
    """The stay of a frame of ``own``'s robot whose vector is ``vector``: among the robot's
    frames older than frame id ``before`` (None: all of them, for the frame being asked about)."""
    return rule.stay(own.older_than(before), vector, lambda ids: _held_vectors(view, ids))


def _held_vectors(view: SequenceMap, ids: np.ndarray) -> np.ndarray:
    """The map's vectors of ``ids``; rows of NaN for frames the index does not hold yet (a
    replica catching up): they show another place."""
    positions = view.positions(ids)
    rows = np.full((len(ids), view.vectors.shape[1]), np.nan, np.float32)
    held = positions >= 0
    rows[held] = view.lookup(positions[held])
    return rows
