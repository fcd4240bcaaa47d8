"""Growing an atlas's :class:`Trajectories` by one frame at a time, in O(frames) array moves
instead of a rebuild: a robot's new frame that is not older than its latest one goes to the end
of the robot's block (a new sequence after a gap), which is the steady state of robots
streaming. Anything else (an older timestamp arriving late) says so, and the caller rebuilds.

The result steps exactly as :meth:`Trajectories.build` on the same frames (same frames after
and before each frame within a sequence, same cuts); only block order and sequence numbers
may differ, which stepping never looks at.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from service.ml.sequences import Trajectories, carried_timestamps


@dataclass
class RobotTail:
    """Where a robot's block ends in ``order`` and the times at its end."""

    end: int  # one past the robot's last place in ``order``
    latest: float  # largest carried time (-inf when none known)
    last_arrival: float  # carried time of its newest arrival (NaN when none known)
    sequence: int  # the sequence of its last frame in time order


@dataclass
class GrowingTrajectories:
    max_gap_seconds: float | None
    trajectories: Trajectories = field(default_factory=lambda: Trajectories.build([]))
    tails: dict[str, RobotTail] = field(default_factory=dict)
    next_sequence: int = 0

    @classmethod
    def build(
        cls, robots: list[str], timestamps: list[float | None], max_gap_seconds: float | None
    ) -> GrowingTrajectories:
        built = Trajectories.build(robots, timestamps, max_gap_seconds=max_gap_seconds)
        grown = cls(max_gap_seconds, built, {}, int(built.sequence.max()) + 1 if robots else 0)
        positions: dict[str, list[int]] = {}
        for i, robot in enumerate(robots):
            positions.setdefault(robot, []).append(i)
        for robot, frames in positions.items():
            carried = carried_timestamps([timestamps[i] for i in frames])
            known = carried[~np.isnan(carried)]
            ranks = built.rank[frames]
            last_in_time = frames[int(np.argmax(ranks))]
            grown.tails[robot] = RobotTail(
                end=int(ranks.max()) + 1,
                latest=float(known.max()) if len(known) else -math.inf,
                last_arrival=float(carried[-1]),
                sequence=int(built.sequence[last_in_time]),
            )
        return grown

    def append(self, robot: str, timestamp: float | None) -> bool:
        """Frame ``len(trajectories)`` joins; False (nothing changed) when it does not go at
        the end of its robot's frames in time order."""
        old = self.trajectories
        position = len(old)
        tail = self.tails.get(robot)
        carried = (
            float(timestamp)
            if timestamp is not None
            else (tail.last_arrival if tail is not None else math.nan)
        )
        key = -math.inf if math.isnan(carried) else carried
        if tail is not None and key < tail.latest:
            return False
        if tail is None:
            at, sequence = position, self.next_sequence
            self.next_sequence += 1
            self.tails[robot] = RobotTail(position + 1, key, carried, sequence)
        else:
            at = tail.end
            gap = (
                timestamp is not None
                and self.max_gap_seconds is not None
                and tail.latest > -math.inf
                and float(timestamp) - tail.latest > self.max_gap_seconds
            )
            if gap:
                tail.sequence = self.next_sequence
                self.next_sequence += 1
            sequence = tail.sequence
            for other in self.tails.values():
                if other.end > at:
                    other.end += 1
            tail.end, tail.latest, tail.last_arrival = at + 1, key, carried
        order = np.insert(old.order, at, position)
        rank = np.empty(position + 1, dtype=np.int64)
        rank[order] = np.arange(position + 1)
        self.trajectories = Trajectories(
            order=order, rank=rank, sequence=np.append(old.sequence, sequence)
        )
        return True
