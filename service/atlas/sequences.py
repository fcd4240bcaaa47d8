"""Sequence scoring and temporal consistency for a query or observation that names its robot.

The query sequence is the robot's most recent stored frames (arrival order; a time gap longer
than ``sequence_max_gap_seconds`` or a backwards jump starts a new sequence) followed by the frame
asked about. Candidates are the newest frame's own search hits (and their trajectory
neighbours), each scored by summed standardised similarities along the reference trajectory over
a range of speeds (:mod:`service.ml.sequences`). Temporal consistency (as DBoW2): the robot's
previous observations in the sequence each get their best single-frame match (one small search
each) and the newest passing answer is a loop only when the last ``consistency_frames`` of them
passed and point at one stretch of one trajectory.

Everything is read from the database and the loaded index at the request's revision
(:class:`~service.atlas.sequence_map.SequenceMaps` caches the map per process), so replicas and
restarts answer alike.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from sqlalchemy.orm import Session

from service.atlas.filters import Selection
from service.atlas.sequence_map import SequenceMap, SequenceMaps
from service.atlas.state import LoadedAtlas
from service.config import Settings
from service.index import Hit
from service.ml.impostors import loop_score_threshold
from service.ml.sequences import (
    ConsistencySettings,
    Hypothesis,
    PlaceStatus,
    SequenceSettings,
    Trajectories,
    decide,
    match_sequence,
    sequence_starts,
)
from service.storage import repository as repo

# The service proposes candidates from the newest frame's own hits only (see SequenceSettings).
SERVICE_SEQUENCE = SequenceSettings(seed_frames=1)


@dataclass
class SequenceAnswer:
    """The best reference place for the robot's sequence.

    ``frame_id`` is aligned with the newest frame; ``aligned`` gives the frame aligned with each
    query frame, oldest first (None where the reference trajectory had none)."""

    score: float
    length: int
    aligned: list[int | None]
    speed: float
    frame_id: int


@dataclass(frozen=True)
class RobotContext:
    """What sequence scoring and consistency read about the asking robot."""

    robot_id: str
    timestamp: float | None
    sequence_length: int  # 0: no sequence scoring


@dataclass(frozen=True)
class Verdict:
    status: PlaceStatus
    consistent: int


@dataclass(frozen=True)
class RobotEvidence:
    """Read in the request's search session: the sequence answer, and the robot's previous
    observations' hypotheses for the consistency check (oldest first)."""

    sequence: SequenceAnswer | None
    previous: list[Hypothesis | None]
    position: dict[int, int]  # frame id -> map position (the map's, read-only here)
    trajectories: Trajectories
    consistency: ConsistencySettings

    def verdict(self, frame_id: int | None, passed: bool) -> Verdict:
        """The newest answer (its matched frame and whether it passed) judged with the
        previous observations."""
        at = self.position.get(frame_id, -1) if frame_id is not None else -1
        newest = Hypothesis(at, passed) if at >= 0 else None
        decision = decide([*self.previous, newest], self.trajectories, self.consistency)
        return Verdict(decision.status, decision.consistent)


def single_frame_verdict(passed: bool) -> Verdict:
    """A query without a robot: no history to be consistent with."""
    return Verdict(PlaceStatus.LOOP, 1) if passed else Verdict(PlaceStatus.NEW_PLACE, 0)


def query_sequence(
    session: Session, atlas_id: int, robot: RobotContext, longest: int, max_gap: float | None
) -> list[int]:
    """The robot's stored frames that precede the newest one in its current sequence (ids,
    oldest first, at most ``longest - 1``)."""
    if longest <= 1:
        return []
    recent = repo.recent_robot_frames(
        session, atlas_id=atlas_id, robot_id=robot.robot_id, limit=longest - 1
    )
    times = [t for _, t in recent] + [robot.timestamp]
    starts = sequence_starts(times, max_gap_seconds=max_gap)
    first = int(np.flatnonzero(starts)[-1])
    return [frame_id for frame_id, _ in recent[first:]]


def _eligible(view: SequenceMap, selection: Selection) -> np.ndarray:
    """Positions of the map a candidate may be (the query's filter)."""
    allowed = np.ones(view.count, dtype=bool)
    if selection.include is not None:
        allowed[:] = False
        included = view.positions(selection.include)
        allowed[included[included >= 0]] = True
    excluded = view.positions(selection.exclude)
    allowed[excluded[excluded >= 0]] = False
    return allowed


class SequenceScorer:
    """Sequence answers and consistency verdicts of one process (the map cache is its own)."""

    def __init__(self, settings: Settings) -> None:
        self.settings = settings
        self.maps = SequenceMaps(settings.sequence_max_gap_seconds)
        self.consistency = ConsistencySettings(required=settings.consistency_frames)

    def answer(
        self,
        session: Session,
        state: LoadedAtlas,
        robot: RobotContext,
        newest: np.ndarray,
        hits: list[Hit],
        selection: Selection,
    ) -> RobotEvidence:
        """The robot's sequence answer (None when off) and its previous observations."""
        longest = max(robot.sequence_length, self.consistency.required)
        previous = query_sequence(
            session, state.atlas_id, robot, longest, self.settings.sequence_max_gap_seconds
        )
        with self.maps.hold(session, state) as view:
            positions = view.positions(previous)
            previous_positions = positions[positions >= 0]
            eligible = _eligible(view, selection)
            sequence = None
            if robot.sequence_length > 0 and view.count:
                sequence = self._score(
                    state, view, newest, hits, previous_positions, eligible, selection, robot
                )
            past = self._previous(state, view, previous_positions, selection)
            return RobotEvidence(sequence, past, view.position, view.trajectories, self.consistency)

    def _score(
        self,
        state: LoadedAtlas,
        view: SequenceMap,
        newest: np.ndarray,
        hits: list[Hit],
        previous: np.ndarray,
        eligible: np.ndarray,
        selection: Selection,
        robot: RobotContext,
    ) -> SequenceAnswer | None:
        """The best place for the sequence; candidates come from the newest frame's hits and,
        with ``sequence_seed_frames`` > 1 (0: all), from searches of earlier frames too."""
        settings = replace(
            SERVICE_SEQUENCE,
            length=robot.sequence_length,
            seed_frames=self.settings.sequence_seed_frames,
        )
        previous = previous[-(settings.length - 1) :] if settings.length > 1 else previous[:0]
        queries = np.vstack([view.lookup(previous), newest[None].astype(np.float32)])
        seed_lists = [np.zeros(0, np.int64)] * len(previous) + [
            self._seeds(view, hits, settings.seeds)
        ]
        searched = len(previous) if not settings.seed_frames else settings.seed_frames - 1
        for j in range(max(len(previous) - searched, 0), len(previous)):
            found = state.index.search(
                queries[j], settings.seeds, include=selection.include, exclude=selection.exclude
            )
            seed_lists[j] = self._seeds(view, found, settings.seeds)
        matches = match_sequence(
            queries,
            seed_lists,
            view.lookup,
            view.trajectories,
            view.moments,
            settings,
            eligible=lambda frames: eligible[frames],
            top=1,
        )
        if not matches:
            return None
        best = matches[0]
        return SequenceAnswer(
            score=round(float(best.score), 6),
            length=best.length,
            aligned=[int(view.ids[p]) if p >= 0 else None for p in best.aligned],
            speed=float(best.speed),
            frame_id=int(view.ids[best.reference]),
        )

    @staticmethod
    def _seeds(view: SequenceMap, hits: list[Hit], count: int) -> np.ndarray:
        positions = view.positions([h.frame_id for h in hits[:count]])
        return positions[positions >= 0]

    def _previous(
        self,
        state: LoadedAtlas,
        view: SequenceMap,
        previous: np.ndarray,
        selection: Selection,
    ) -> list[Hypothesis | None]:
        """The robot's previous ``required - 1`` observations as DBoW2 sees them: each one's
        best single-frame match, passed by the query's own rule (unverified)."""
        required = self.consistency.required
        recent: list[Hypothesis | None] = []
        for position in previous[max(len(previous) - (required - 1), 0) :] if required > 1 else []:
            found = state.index.search(
                view.lookup(np.array([position]))[0],
                1,
                include=selection.include,
                exclude=selection.exclude,
            )
            recent.append(self._hypothesis(state, view, found[0] if found else None))
        return recent

    def _hypothesis(
        self, state: LoadedAtlas, view: SequenceMap, hit: Hit | None
    ) -> Hypothesis | None:
        if hit is None:
            return None
        at = view.position.get(hit.frame_id, -1)
        if at < 0:
            return None
        return Hypothesis(at, self._passes(state, hit.similarity))

    def _passes(self, state: LoadedAtlas, similarity: float) -> bool:
        """The query's own rule without verification: the calibrated score against its bar
        on a calibrated version, else the cosine against the loop-closure threshold."""
        scores = state.model.score(np.array([similarity], np.float64))
        if scores is None:
            return similarity >= self.settings.loop_closure_threshold
        bar = loop_score_threshold(self.settings.loop_score_min, state.index.size)
        return float(scores[0]) >= bar
