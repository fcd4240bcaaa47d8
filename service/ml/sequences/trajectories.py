"""Frames in the order a robot took them, cut into sequences.

A robot's frames are ordered by timestamp; a frame sent without one keeps its arrival place
(it takes the timestamp of the frame that arrived before it, so it stays right after it). A new
sequence starts at a robot's first frame, after a time gap longer than ``max_gap_seconds``, and
where time jumps backwards (a replayed or restarted stream). Sequence matching never walks across
such a cut: the frames on both sides need not be neighbours in space.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


def carried_timestamps(timestamps: Sequence[float | None]) -> np.ndarray:
    """Timestamps in arrival order, a missing one taking the previous frame's (NaN before any)."""
    values = np.array([np.nan if t is None else float(t) for t in timestamps], dtype=np.float64)
    if len(values) == 0:
        return values
    known = ~np.isnan(values)
    last_known = np.maximum.accumulate(np.where(known, np.arange(len(values)), -1))
    return np.where(last_known >= 0, values[np.maximum(last_known, 0)], np.nan)


def sequence_starts(
    timestamps: Sequence[float | None], *, max_gap_seconds: float | None
) -> np.ndarray:
    """``N`` bool over one robot's frames in arrival order: which frames start a new sequence.

    The first frame does; so does a frame more than ``max_gap_seconds`` after the previous one
    (None: gaps never cut), and a frame whose timestamp lies before the previous one's (a jump).
    Frames without a timestamp never cut (they keep arrival order).
    """
    times = carried_timestamps(timestamps)
    starts = np.zeros(len(times), dtype=bool)
    if len(times) == 0:
        return starts
    starts[0] = True
    step = np.diff(times)
    known = ~np.isnan(step)
    backwards = known & (step < 0)
    gap = known & (step > max_gap_seconds) if max_gap_seconds is not None else np.zeros_like(known)
    starts[1:] = backwards | gap
    return starts


@dataclass(frozen=True)
class Trajectories:
    """Every frame's sequence and place along it, for walking a reference trajectory.

    Frame indices are positions in the caller's arrays (the map's vectors). ``order`` lists the
    frames sequence by sequence, each in time order; ``rank[i]`` is frame i's place in ``order``
    and ``sequence[i]`` its sequence number.
    """

    order: np.ndarray
    rank: np.ndarray
    sequence: np.ndarray

    @classmethod
    def build(
        cls,
        robots: Sequence[str],
        timestamps: Sequence[float | None] | None = None,
        *,
        max_gap_seconds: float | None = None,
    ) -> Trajectories:
        """From each frame's robot and timestamp, frames given in arrival order."""
        n = len(robots)
        times = [None] * n if timestamps is None else list(timestamps)
        if len(times) != n:
            raise ValueError(f"{n} robots but {len(times)} timestamps")
        sequence = np.empty(n, dtype=np.int64)
        order_parts: list[np.ndarray] = []
        next_sequence = 0
        by_robot: dict[str, list[int]] = {}
        for i, robot in enumerate(robots):
            by_robot.setdefault(robot, []).append(i)
        for robot in sorted(by_robot):
            frames = np.array(by_robot[robot], dtype=np.int64)
            carried = carried_timestamps([times[i] for i in frames])
            # time order, arrival order among equal (or unknown) times
            key = np.where(np.isnan(carried), -np.inf, carried)
            frames = frames[np.lexsort((frames, key))]
            starts = sequence_starts([times[i] for i in frames], max_gap_seconds=max_gap_seconds)
            sequence[frames] = next_sequence + np.cumsum(starts) - 1
            next_sequence += int(starts.sum())
            order_parts.append(frames)
        order = np.concatenate(order_parts) if order_parts else np.zeros(0, np.int64)
        rank = np.empty(n, dtype=np.int64)
        rank[order] = np.arange(n)
        return cls(order=order, rank=rank, sequence=sequence)

    @classmethod
    def single(cls, n: int, starts: np.ndarray | None = None) -> Trajectories:
        """Frames ``0..n-1`` in order, one sequence, or cut where ``starts`` is True."""
        cuts = np.zeros(n, dtype=bool) if starts is None else np.asarray(starts, dtype=bool)
        if n:
            cuts = cuts.copy()
            cuts[0] = True
        return cls(
            order=np.arange(n, dtype=np.int64),
            rank=np.arange(n, dtype=np.int64),
            sequence=np.cumsum(cuts).astype(np.int64) - 1,
        )

    def __len__(self) -> int:
        return len(self.order)

    def step(self, frames: np.ndarray, offsets: np.ndarray) -> np.ndarray:
        """The frame ``offsets`` places after ``frames`` in the same sequence (broadcast), -1
        where that leaves the sequence (or ``frames`` is -1)."""
        frames = np.asarray(frames, dtype=np.int64)
        offsets = np.asarray(offsets, dtype=np.int64)
        valid = frames >= 0
        safe = np.where(valid, frames, 0)
        target = self.rank[safe] + offsets
        inside = valid & (target >= 0) & (target < len(self.order))
        landed = self.order[np.clip(target, 0, max(len(self.order) - 1, 0))]
        same = inside & (self.sequence[landed] == self.sequence[safe])
        return np.where(same, landed, -1)

    def recent(self, frame: int, length: int) -> np.ndarray:
        """The last ``length`` frames of ``frame``'s sequence up to and including it, oldest
        first (fewer where the sequence is shorter)."""
        back = self.step(np.array(frame, dtype=np.int64), -np.arange(length)[::-1])
        return back[back >= 0]
