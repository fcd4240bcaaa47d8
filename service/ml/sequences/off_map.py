"""Has the robot left the map? A change test over the newest frames of a sequence match.

A robot that leaves the mapped route drags a tail of frames that still align along it, so its
sequence keeps a large margin for several frames while its newest frames favour the predicted
place only weakly: on Nordland's off-route proxy (winter frames from an unmapped stretch of the
line) an off-map frame's ``aligned_z`` has a median of 0.8-0.9, an on-route one 3.7-4.3. One
weak frame happens on the route too (a bland stretch: a tenth of the newest frames there score
below 0.9-1.2), so one frame cannot say "lost"; several weak frames in a row can. This is CUSUM
on the newest frames' evidence: each frame adds ``OFF_MAP_Z - aligned_z``, and the robot is taken to
have left the map when, for some ``k`` of its last 2-``OFF_MAP_FRAMES`` frames, the sum exceeds
``OFF_MAP_SLACK`` (the mean of the last k frames is below ``OFF_MAP_Z - OFF_MAP_SLACK / k``:
0.75 for two frames, 1.0 for three, 1.125 for four).

Chosen offline on the development sets' served reports (``benchmarks/off_map_guard.py
--grid``): of the off-route proxy's false loops it would refuse 2 of 4 at the defaults and 9 of
14 with automatic adaptation, for 8 and 2 of Nordland's right loops. As served at the defaults it
halved the proxy's false loops (4 -> 2) for 19 of Nordland's 2,611 right loops
(benchmarks/RESULTS.md, issue 25, stop 45). A robot's first frame off the map is beyond any test
of the frames' own evidence: that is what ``NEWEST_Z_MIN`` keeps small.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

# A frame on the map favours its aligned place by at least this many standard deviations on
# average; each frame below it counts towards "off the map".
OFF_MAP_Z = 1.5
# How far short of OFF_MAP_Z the newest frames may fall together before the robot counts as off
# the map.
OFF_MAP_SLACK = 1.5
# The newest frames the test looks back over (at least 2: one frame alone is NEWEST_Z_MIN's).
OFF_MAP_FRAMES = 4


class OffMap(NamedTuple):
    """The newest frames whose evidence says the robot has left the map."""

    frames: int  # how many of the newest frames
    mean_z: float  # their mean aligned_z
    needed: float  # the mean a robot on the map shows over that many frames


def left_the_map(
    aligned_z: Sequence[float],
    aligned: Sequence[int] | None = None,
    *,
    reference_z: float = OFF_MAP_Z,
    slack: float = OFF_MAP_SLACK,
    frames: int = OFF_MAP_FRAMES,
) -> OffMap | None:
    """The shortest run of newest frames (2 to ``frames``) of a sequence match whose evidence
    falls short of a robot on the map, None when none does. ``aligned_z`` and ``aligned`` are
    the match's (:class:`~service.ml.sequences.SequenceMatch`, oldest first); frames that
    aligned with no map frame (``aligned`` -1) carry no evidence and are skipped. The constants
    default to the service's; ``benchmarks/off_map_guard.py`` screens others."""
    evidence = [float(z) for i, z in enumerate(aligned_z) if aligned is None or aligned[i] >= 0]
    for k in range(2, min(frames, len(evidence)) + 1):
        newest = evidence[-k:]
        if k * reference_z - sum(newest) > slack:
            return OffMap(k, sum(newest) / k, reference_z - slack / k)
    return None
