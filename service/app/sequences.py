"""Sequence scoring and temporal consistency for a query or observation that names its robot.

The query sequence is the robot's most recent stored frames (arrival order; a time gap longer
than ``sequence_max_gap_seconds`` or a backwards jump starts a new sequence) followed by the frame
asked about. Every frame of it proposes candidate places (``sequence_seed_frames``, 0: all): the
newest through the request's own search, an earlier one through the matches its own
observation kept (:class:`~service.storage.models.FrameProposals`; a frame stored without them is
searched again). Candidates are scored by summed standardised similarities along the reference
trajectory over a range of speeds (:mod:`service.ml.sequences`), and the best one's margin over
its best rival place says how distinct it is: a sequence whose margin reaches
``sequence_margin_min`` over at least ``consistency_frames`` aligned frames is a loop on its own.
Temporal consistency (as DBoW2) judges the single-frame answers: the robot's previous
observations each get their best single-frame match (their kept matches, or one small search)
and the newest passing answer is a loop only when the last ``consistency_frames`` of them passed
and point at one stretch of one trajectory.

Everything is read from the database and the loaded index at the request's revision
(:class:`~service.app.sequence_map.SequenceMaps` caches the map per process), so replicas and
restarts answer alike.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from sqlalchemy.orm import Session

from service.app.filters import Selection
from service.app.results import DeferredLoop, SequenceAnswer
from service.app.robot_evidence import Earlier, RobotContext, RobotEvidence
from service.app.sequence_map import SequenceMap, SequenceMaps
from service.app.sequence_rules import (
    TrackedLoop,
    awaits_confirmation,
    ran_ahead,
    recent_loops,
    sequence_shortfalls,
)
from service.app.state import LoadedAtlas
from service.app.stay import RobotFrames, frame_stay, stay_rule
from service.config import Settings
from service.index import Hit
from service.ml.impostors import loop_score_threshold
from service.ml.sequences import (
    ConsistencySettings,
    Hypothesis,
    SequenceSettings,
    distinctiveness,
    margin_needed,
    match_sequence,
    sequence_starts,
)
from service.ml.sequences.contrast import contrasted_query
from service.ml.sequences.off_map import left_the_map
from service.storage import repository as repo

# Every frame of the sequence proposes candidates (see SequenceSettings); the settings' default.
SERVICE_SEQUENCE = SequenceSettings(seed_frames=0)


def _similarity(view: SequenceMap, query: np.ndarray, frame_id: int) -> float | None:
    """Cosine of ``query`` with the map's vector of ``frame_id`` (None: not held)."""
    position = view.positions([frame_id])[0]
    if position < 0:
        return None
    return float(view.lookup(np.array([position]))[0] @ np.asarray(query, np.float32))


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


def pending_run(previous: Sequence[int], kept: dict[int, repo.Kept]) -> tuple[DeferredLoop, ...]:
    """The loops the robot's latest frames of this sequence left pending, oldest first: the
    unbroken run of pending frames that ends with its previous frame (empty: none waits, or the
    robot starts a new sequence). Bounded by the frames read back (the longest of the sequence,
    the consistency and the trajectory contrast, less the newest frame: 10 at the defaults), so
    a loop waits at most that many frames for one answered at once."""
    run: list[DeferredLoop] = []
    for frame_id in reversed(previous):
        last = kept.get(frame_id)
        if last is None or not last.loop_pending or last.loop_frame_id is None:
            break
        run.append(DeferredLoop(frame_id, last.loop_frame_id))
    return tuple(reversed(run))


def contrast_order(
    view: SequenceMap, contrasted: np.ndarray | None, hits: list[Hit]
) -> list[int] | None:
    """The hits' order by trajectory-contrasted cosine with the query (best first; a hit the
    map does not hold yet goes last, in search order); None without a contrasted query. The
    search shortlists on plain vectors, the contrast orders the shortlist: on the development
    sets ordering the 50 best this way kept nearly all of a full contrasted search's gain."""
    if contrasted is None or not hits:
        return None
    positions = view.positions([h.frame_id for h in hits])
    held = positions >= 0
    similarity = np.full(len(hits), -np.inf)
    similarity[held] = view.contrasted_lookup(positions[held]) @ contrasted
    return [int(i) for i in np.argsort(-similarity, kind="stable")]


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
        self.maps = SequenceMaps(
            settings.sequence_max_gap_seconds, settings.trajectory_contrast_frames
        )
        self.consistency = ConsistencySettings(required=settings.consistency_frames)

    def answer(
        self,
        session: Session,
        state: LoadedAtlas,
        robot: RobotContext,
        newest: np.ndarray,
        hits: list[Hit],
        selection: Selection,
        own: RobotFrames | None = None,
    ) -> RobotEvidence:
        """The robot's sequence answer (None when off) and its previous observations; ``own``:
        the robot's frames as the request has read them (None: read here)."""
        contrast = self.settings.trajectory_contrast_frames
        longest = max(robot.sequence_length, self.consistency.required, contrast + 1)
        previous = query_sequence(
            session, state.atlas_id, robot, longest, self.settings.sequence_max_gap_seconds
        )
        kept = repo.frame_proposals(session, frame_ids=previous)
        with self.maps.hold(session, state) as view:
            positions = view.positions(previous)
            earlier = [
                self._earlier(view, int(p), kept.get(frame_id))
                for frame_id, p in zip(previous, positions, strict=True)
                if p >= 0
            ]
            eligible = _eligible(view, selection)
            own = own or RobotFrames(session, state.atlas_id, robot.robot_id)
            stays = self._stays(own, state, view, robot, previous)
            eligible[stays[stays >= 0]] = False
            contrasted = self._contrasted(view, newest, earlier)
            sequence = None
            if robot.sequence_length > 0 and view.count:
                sequence = self._score(
                    state,
                    view,
                    newest,
                    contrasted,
                    hits,
                    earlier,
                    eligible,
                    selection,
                    robot.sequence_length,
                    recent_loops(view, previous, kept),
                )
            past = self._previous(state, view, earlier, eligible, selection)
            return RobotEvidence(
                sequence,
                past,
                view.position,
                view.trajectories,
                self.consistency,
                contrast_order(view, contrasted[0], hits),
                _similarity(view, newest, sequence.frame_id) if sequence is not None else None,
                pending_run(previous, kept),
            )

    def _stays(
        self,
        own: RobotFrames,
        state: LoadedAtlas,
        view: SequenceMap,
        robot: RobotContext,
        previous: list[int],
    ) -> np.ndarray:
        """Map positions of the stays of the sequence's earlier frames (:mod:`service.app.stay`):
        each frame of a sequence is held to the rule of the frame asked about, so none aligns
        with the robot's own frames of the place it was standing at then."""
        rule = stay_rule(state, self.settings)
        frames = previous[-(robot.sequence_length - 1) :] if robot.sequence_length > 1 else []
        held = [f for f in frames if f in view.position]
        if rule is None or not held:
            return np.zeros(0, np.int64)
        vectors = view.lookup(view.positions(held))
        stays = [
            frame_stay(own, view, rule, vector, before=frame_id)
            for frame_id, vector in zip(held, vectors, strict=True)
        ]
        return view.positions(np.concatenate(stays))

    def _score(
        self,
        state: LoadedAtlas,
        view: SequenceMap,
        newest: np.ndarray,
        contrast: tuple[np.ndarray | None, int],
        hits: list[Hit],
        earlier: list[Earlier],
        eligible: np.ndarray,
        selection: Selection,
        length: int,
        loops: list[TrackedLoop],
    ) -> SequenceAnswer | None:
        """The best place for the sequence and its margin over the best rival (the margin it
        needs is lower where it continues the newest of the robot's recent ``loops``; it may
        not run ahead of any of them). Candidates come from the
        newest frame's hits and from the ``sequence_seed_frames`` - 1 earlier frames (0: all):
        their kept proposals, or a search where none were kept."""
        settings = replace(
            SERVICE_SEQUENCE,
            length=length,
            seed_frames=self.settings.sequence_seed_frames,
        )
        contrasted, contrast_frames = contrast
        earlier = earlier[-(settings.length - 1) :] if settings.length > 1 else []
        positions = np.array([e.position for e in earlier], dtype=np.int64)
        lookup, moments = view.lookup, view.moments
        if contrasted is not None:  # both sides against their trajectories' recent frames
            lookup, moments = view.contrasted_lookup, view.contrast_moments
        queries = np.vstack(
            [lookup(positions), (newest if contrasted is None else contrasted)[None]]
        ).astype(np.float32)
        seed_lists = [np.zeros(0, np.int64)] * len(earlier) + [
            self._positions(view, [h.frame_id for h in hits[: settings.seeds]])
        ]
        proposing = len(earlier) if not settings.seed_frames else settings.seed_frames - 1
        for j in range(max(len(earlier) - proposing, 0), len(earlier)):
            kept = earlier[j].proposals
            if kept is None:  # stored without a search of its own: search it now
                found = state.index.search(
                    queries[j], settings.seeds, include=selection.include, exclude=selection.exclude
                )
                kept = self._positions(view, [h.frame_id for h in found])
            seed_lists[j] = kept[: settings.seeds]
        matches = match_sequence(
            queries,
            seed_lists,
            lookup,
            view.trajectories,
            moments,
            settings,
            eligible=lambda frames: eligible[frames],
            top=None,
        )
        distinct = distinctiveness(matches, view.trajectories, self.consistency.max_step)
        if distinct is None:
            return None
        best = matches[0]
        tracked = loops[0] if loops else None
        needed = margin_needed(
            view.trajectories,
            best.reference,
            earlier[-1].position if earlier else None,
            other_run=self.settings.sequence_margin_min,
            own_run=self.settings.sequence_margin_min_own_run,
            previous_loop=tracked.position if tracked else None,
            tracking=self.settings.sequence_margin_min_tracking,
            frames_since=tracked.frames_since if tracked else 1,
        )
        shortfalls = sequence_shortfalls(
            float(distinct.margin),
            needed,
            best.length,
            self.consistency.required,
            best.newest_z,
            ran_ahead(view.trajectories, best.reference, loops, settings),
            left_the_map(best.aligned_z, best.aligned),
        )
        waits = (
            None
            if shortfalls
            else awaits_confirmation(best.newest_z, self.settings.sequence_confirm_z)
        )
        return SequenceAnswer(
            score=round(float(best.score), 6),
            length=best.length,
            aligned=[int(view.ids[p]) if p >= 0 else None for p in best.aligned],
            speed=float(best.speed),
            frame_id=int(view.ids[best.reference]),
            margin=round(float(distinct.margin), 6),
            rival_frame_id=int(view.ids[distinct.rival]) if distinct.rival is not None else None,
            contrast_frames=contrast_frames,
            margin_min=needed,
            aligned_z=[round(z, 3) for z in best.aligned_z],
            passed=not shortfalls,
            reason="; ".join(shortfalls) or waits,
            awaits_next=waits is not None,
        )

    def _contrasted(
        self, view: SequenceMap, newest: np.ndarray, earlier: list[Earlier]
    ) -> tuple[np.ndarray | None, int]:
        """The newest frame's trajectory-contrasted vector (against the robot's previous
        frames of this sequence, up to the window) and how many frames it was contrasted with;
        (None, 0) when contrast is off or the robot has no earlier frame here: the sequence is
        then scored on plain vectors."""
        window = view.contrast_window
        if not window or not earlier:
            return None, 0
        before = np.array([e.position for e in earlier[-window:]], dtype=np.int64)
        vector = contrasted_query(newest, view.lookup(before))
        return vector, len(before) if vector is not None else 0

    @classmethod
    def _earlier(cls, view: SequenceMap, position: int, kept: repo.Kept | None) -> Earlier:
        """An earlier frame at map ``position`` with the matches its observation kept (None:
        stored without a search)."""
        if kept is None:
            return Earlier(position, None)
        return Earlier(position, cls._positions(view, kept.proposals))

    @staticmethod
    def _positions(view: SequenceMap, frame_ids: Sequence[int] | np.ndarray) -> np.ndarray:
        """Map positions of those of ``frame_ids`` the map holds, in order."""
        positions = view.positions(list(frame_ids))
        return positions[positions >= 0]

    def _previous(
        self,
        state: LoadedAtlas,
        view: SequenceMap,
        earlier: list[Earlier],
        eligible: np.ndarray,
        selection: Selection,
    ) -> list[Hypothesis | None]:
        """The robot's previous ``required - 1`` observations as DBoW2 sees them: each one's
        best single-frame match that the query may name (from its kept proposals, else one
        search), passed by the query's own rule (unverified)."""
        required = self.consistency.required
        recent: list[Hypothesis | None] = []
        for frame in earlier[max(len(earlier) - (required - 1), 0) :] if required > 1 else []:
            vector = view.lookup(np.array([frame.position]))[0]
            if frame.proposals is not None:  # the best of its kept matches, by today's vectors
                kept = frame.proposals[eligible[frame.proposals]]
                similarities = view.lookup(kept) @ vector
                best = int(np.argmax(similarities)) if len(kept) else -1
                recent.append(
                    Hypothesis(int(kept[best]), self._passes(state, float(similarities[best])))
                    if best >= 0
                    else None
                )
                continue
            found = state.index.search(
                vector, 1, include=selection.include, exclude=selection.exclude
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
