"""Growing the trajectories frame by frame steps exactly like building them from all rows."""

from __future__ import annotations

import numpy as np
import pytest

from service.app.trajectory_growth import GrowingTrajectories
from service.ml.sequences import Trajectories


def stream(seed: int, frames: int = 300) -> tuple[list[str], list[float | None]]:
    """Robots streaming in turn: mostly one second apart, some gaps, some frames without a
    timestamp, and now and then one that arrives late (older than its robot's latest)."""
    rng = np.random.default_rng(seed)
    clocks = {f"r{i}": 0.0 for i in range(4)}
    robots, times = [], []
    for _ in range(frames):
        robot = f"r{rng.integers(0, 4)}"
        clocks[robot] += 60.0 if rng.random() < 0.05 else 1.0
        t = clocks[robot] - (5.0 if rng.random() < 0.03 else 0.0)
        robots.append(robot)
        times.append(None if rng.random() < 0.1 else t)
    return robots, times


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_grown_frame_by_frame_steps_like_built(seed: int) -> None:
    robots, times = stream(seed)
    grown = GrowingTrajectories(max_gap_seconds=10.0)
    rebuilt = 0
    for i in range(len(robots)):
        if not grown.append(robots[i], times[i]):
            grown = GrowingTrajectories.build(robots[: i + 1], times[: i + 1], 10.0)
            rebuilt += 1
    built = Trajectories.build(robots, times, max_gap_seconds=10.0)
    frames = np.arange(len(robots))[:, None]
    offsets = np.arange(-6, 7)[None, :]
    np.testing.assert_array_equal(
        grown.trajectories.step(frames, offsets), built.step(frames, offsets)
    )
    assert 0 < rebuilt < len(robots) // 10  # late frames rebuild; the rest grows in place
