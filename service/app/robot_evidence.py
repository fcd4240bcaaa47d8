"""What the service knows about a robot that asks: who and when it asks, its earlier frames in
the current sequence, the evidence read for it in the search session, and the verdict judged
from that evidence (temporal consistency as DBoW2, a passed sequence a loop on its own, at once
or, when its newest frame's own evidence is weak, once a later frame of the same place answers a
loop at once: weak frames never confirm each other alone).

Kept apart from the scoring (:mod:`service.app.sequences`) so the decision and the use cases read
these types without importing the scorer.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from service.app.results import DeferredLoop, SequenceAnswer
from service.ml.sequences import (
    ConsistencySettings,
    Hypothesis,
    PlaceStatus,
    Trajectories,
    agree,
    decide,
)


@dataclass(frozen=True)
class RobotContext:
    """What sequence scoring and consistency read about the asking robot."""

    robot_id: str
    timestamp: float | None
    sequence_length: int  # 0: no sequence scoring


@dataclass(frozen=True)
class Earlier:
    """One of the robot's earlier frames in its sequence: its map position and the map
    positions of the matches its observation kept (None: stored without a search)."""

    position: int
    proposals: np.ndarray | None


@dataclass(frozen=True)
class Verdict:
    """``loop_frame_id``: the frame to close the loop with when ``status`` is a loop (the
    single-frame match, or the sequence's aligned frame when only the sequence passed).
    ``pending_loop_frame_id``: the sequence's aligned frame of a loop left to a later frame
    (status candidate); ``confirmed``: the pending loops of the robot's frames just before this
    one (oldest first), which this frame's loop, answered at once, confirms as the same place."""

    status: PlaceStatus
    consistent: int
    loop_frame_id: int | None = None
    pending_loop_frame_id: int | None = None
    confirmed: tuple[DeferredLoop, ...] = ()


@dataclass(frozen=True)
class RobotEvidence:
    """Read in the request's search session: the sequence answer, and the robot's previous
    observations' hypotheses for the consistency check (oldest first)."""

    sequence: SequenceAnswer | None
    previous: list[Hypothesis | None]
    position: dict[int, int]  # frame id -> map position (the map's, read-only here)
    trajectories: Trajectories
    consistency: ConsistencySettings
    # the search's hits in trajectory-contrast order (indices; None: contrast unavailable)
    hit_order: list[int] | None = None
    # cosine of the query with the sequence's aligned frame (None: no sequence)
    sequence_similarity: float | None = None
    # the pending loops of the robot's frames just before this one, oldest first (the run of
    # its latest frames whose loops wait: :func:`service.app.sequences.pending_run`)
    pending_run: tuple[DeferredLoop, ...] = ()

    def same_place(self, frame_id: int, other_id: int) -> bool | None:
        """Whether two map frames show one place by the consistency's rule (one reference
        trajectory, at most ``max_step`` frames apart); None when the map does not hold one."""
        a, b = self.position.get(frame_id, -1), self.position.get(other_id, -1)
        if a < 0 or b < 0:
            return None
        return agree(a, b, self.trajectories, self.consistency.max_step)

    def verdict(self, frame_id: int | None, passed: bool) -> Verdict:
        """The newest single-frame answer (its matched frame and whether it passed) judged with
        the previous observations; a passed sequence is a loop whatever they say, at once or,
        when it awaits a later frame, as a candidate whose loop is pending. A loop answered at
        once confirms the pending loops just before it that name its place."""
        at = self.position.get(frame_id, -1) if frame_id is not None else -1
        newest = Hypothesis(at, passed) if at >= 0 else None
        decision = decide([*self.previous, newest], self.trajectories, self.consistency)
        sequence = self.sequence
        if decision.status == PlaceStatus.LOOP:
            verdict = Verdict(PlaceStatus.LOOP, decision.consistent, frame_id)
        elif sequence is not None and sequence.passed and sequence.awaits_next:
            verdict = Verdict(
                PlaceStatus.CANDIDATE, decision.consistent, pending_loop_frame_id=sequence.frame_id
            )
        elif sequence is not None and sequence.passed:
            verdict = Verdict(PlaceStatus.LOOP, decision.consistent, sequence.frame_id)
        else:
            return Verdict(decision.status, decision.consistent)
        return replace(verdict, confirmed=self._confirmed(verdict))

    def _confirmed(self, verdict: Verdict) -> tuple[DeferredLoop, ...]:
        """The pending loops just before this frame that ``verdict``'s loop confirms: none while
        this frame's loop is pending too (the run waits on), else, walking back from the newest,
        each that names the same place as the loop after it (oldest first)."""
        link = verdict.loop_frame_id
        if link is None:
            return ()
        confirmed: list[DeferredLoop] = []
        for pending in reversed(self.pending_run):
            if not self.same_place(pending.loop_frame_id, link):
                break
            confirmed.append(pending)
            link = pending.loop_frame_id
        return tuple(reversed(confirmed))


def single_frame_verdict(frame_id: int | None, passed: bool) -> Verdict:
    """A query without a robot: no history to be consistent with."""
    if passed and frame_id is not None:
        return Verdict(PlaceStatus.LOOP, 1, frame_id)
    return Verdict(PlaceStatus.NEW_PLACE, 0)
