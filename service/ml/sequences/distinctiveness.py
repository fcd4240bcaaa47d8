"""How distinct a sequence match is: its score's margin over the best rival place.

Look-alike stretches of route (forest, snow, a corridor) align along a trajectory as
consistently as the true place does, so a high sequence score alone does not make a place
certain: ranked by score, Nordland's winter sequences (L = 10) stay all right for only 2.5% of
the queries. What marks a true revisit is the absence of a competitor. The *margin* is the best
match's score minus the score of the best-scored candidate that is another place: on another
trajectory, or further along the same one than ``window`` frames (the temporal-consistency
check's notion of "another place", :class:`~service.ml.sequences.ConsistencySettings`
``max_step``). Candidates within the window are the same hypothesis shifted by a frame or two
and rise and fall with it. Scores are summed z-scores / sqrt(length), so the margin is in
standard deviations on any atlas; ranked by it, Nordland's queries stay all right for 53%
(benchmarks/RESULTS.md, sequences phase 4). This is SeqSLAM's uniqueness test, taken over the
scored candidates instead of the whole map.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from service.ml.sequences.scoring import SequenceMatch
from service.ml.sequences.trajectories import Trajectories


@dataclass(frozen=True)
class Distinctiveness:
    """Attributes:
    margin: the best match's score minus its best rival's (the rival counts as 0, chance
        level, when no other place was scored).
    rival: map frame of the best rival (None when there was none).
    """

    margin: float
    rival: int | None


def distinctiveness(
    matches: Sequence[SequenceMatch], trajectories: Trajectories, window: int
) -> Distinctiveness | None:
    """The margin of ``matches[0]`` (matches best first, as :func:`score_candidates` returns
    them) over the best match that is more than ``window`` frames away or on another
    trajectory; None without matches."""
    if not matches:
        return None
    best = matches[0]
    sequence, rank = trajectories.sequence[best.reference], trajectories.rank[best.reference]
    for match in matches[1:]:
        other = match.reference
        if (
            trajectories.sequence[other] != sequence
            or abs(trajectories.rank[other] - rank) > window
        ):
            return Distinctiveness(best.score - match.score, other)
    return Distinctiveness(best.score, None)


# A loop a passed sequence carries while its newest frame's own evidence is below this
# (aligned_z, standard deviations) is not answered at once: it waits for a later frame of the
# robot whose loop is answered at once and the same place (the consistency's rule), with every
# frame between pending on that place too, and is confirmed in that frame's answer. A robot's
# first frame off the mapped route still drags a tail of frames that align along it, and its own
# evidence is then weak but not absent; no test of its own frames can tell it from a bland
# stretch of the route, but the frames after it can. On the off-route proxy (Nordland, ten
# detours) the first half's two false loops had newest aligned_z 1.6 and 2.6, and 3 is the least
# that refuses both; it cost 1.1% of that half's right loops (benchmarks/RESULTS.md, issue 25,
# stop 46). Two weak frames off the map do not confirm each other (stop 47). The default of the
# setting sequence_confirm_z.
CONFIRM_Z = 3.0
# How far along its trajectory a sequence's place must lie past the place the robot's previous
# observation closed a loop with, to continue that loop: exactly one frame. The sequence model
# aligns one map frame per query frame at every speed it tries (SequenceSettings.speeds
# 0.8-1.25 round to 1), so the same hypothesis one frame on is the next frame; any other step
# is the hypothesis jumping. Wider windows closed false loops on Nordland: -1..3 let tracking
# drift two frames off (benchmarks/decision_headroom.py), 0..2 let it lag behind a robot that
# moved on, and 1..2 let it run ahead (eval-online: winter frame 237 onto summer 239 after a
# loop at 237, on an AVX-512 machine; benchmarks/RESULTS.md, issue 25, stops 41-42). A robot
# standing still, or one that outruns the map, loses the track and needs the full margin again.
TRACKING_STEP = 1
# A sequence passes only if its newest frame alone favours the aligned place by this many
# standard deviations: a robot that has just left the mapped route still drags a matching tail
# of frames behind it, which must not make its first frame somewhere new a loop (on the
# development sets this keeps 94-99% of the right sequence answers, 71-86% of the wrong ones).
NEWEST_Z_MIN = 1.0
# How many frames back the loop a sequence may continue can lie: a track that misses a few
# frames (bland ones, ones whose own evidence fails NEWEST_Z_MIN) is picked up again where the
# robot has driven since, ``TRACKING_STEP`` map frames per frame. On Nordland (L = 10) 3 frames
# added 78 loops and no false one; 10 added 40 more, but on the off-route proxy one of them was
# a false loop four frames into an unmapped detour (margin 3.19; stop 43). The off-the-map test
# (service.ml.sequences.off_map) refuses that one: with it, 10 frames add 49 right loops on
# Nordland, 14 on the proxy and 4 on cohog200 to 3 frames', and no false one
# (benchmarks/RESULTS.md, issue 25, stop 45).
TRACKING_DROPOUT = 10
# How much further than its speeds carry it a robot's loop may run ahead of the loops its last
# TRACKING_DROPOUT frames closed: one map frame (the rounding of an alignment). A sequence pinned
# by a few distinctive frames can slide along a bland stretch at its fastest speed, so that
# consecutive loops run two map frames a frame: on Nordland with automatic adaptation (L = 10)
# two such loops landed two frames past the robot (false at +-1); no right loop there ran
# ahead this fast, and two on cohog200 did, right only within its +-2 (benchmarks/RESULTS.md,
# issue 25, stop 44).
RUN_AHEAD_SLACK = 1


def continues_loop(
    trajectories: Trajectories, reference: int, previous_loop: int | None, frames_since: int = 1
) -> bool:
    """Whether map frame ``reference`` continues the loop the robot closed ``frames_since``
    frames ago at map frame ``previous_loop`` (None: none within reach): the same trajectory,
    :data:`TRACKING_STEP` frames further along it per frame driven since."""
    if previous_loop is None or not 1 <= frames_since <= TRACKING_DROPOUT:
        return False
    ahead = trajectories.step(np.array(previous_loop), np.array(TRACKING_STEP * frames_since))
    return int(ahead) == reference


def runs_ahead(
    trajectories: Trajectories,
    reference: int,
    loop: int,
    frames_since: int,
    fastest: float,
    both_ways: bool = False,
) -> int | None:
    """How many map frames ``reference`` lies past the loop the robot closed ``frames_since``
    frames ago at map frame ``loop``, when that is more than ``fastest`` map frames a frame
    carry it (plus :data:`RUN_AHEAD_SLACK`); None when it is not, or lies on another
    trajectory. Lagging behind is allowed (a robot may slow down or stop); ``both_ways``: a
    robot may drive the map backwards (reverse speeds), so running ahead either way counts."""
    if trajectories.sequence[reference] != trajectories.sequence[loop]:
        return None
    ahead = int(trajectories.rank[reference]) - int(trajectories.rank[loop])
    ahead = abs(ahead) if both_ways else ahead
    return ahead if ahead > fastest * frames_since + RUN_AHEAD_SLACK else None


def margin_needed(
    trajectories: Trajectories,
    reference: int,
    own_frame: int | None,
    *,
    other_run: float,
    own_run: float,
    previous_loop: int | None = None,
    tracking: float | None = None,
    frames_since: int = 1,
) -> float:
    """The margin a sequence whose best place is map frame ``reference`` needs to be a loop
    on its own: ``own_run`` when that place lies on the asking robot's own current sequence
    (``own_frame``: one of its earlier frames in the map; None: none is), else ``other_run``.
    Within one run the season, light and camera are the same on both sides, so look-alike
    stretches come closer than across runs: on the two-traversal Nordland replay wrong
    own-run answers reached a margin of 5.99, wrong answers across runs 3.85
    (benchmarks/RESULTS.md, issue 25, stop 40).

    Loop tracking: when the place continues the robot's newest loop (closed at
    ``previous_loop`` ``frames_since`` frames ago, :func:`continues_loop`), ``tracking``
    suffices if lower (None: off). The first loop of a revisit needs the full margin; its
    continuation is the same hypothesis a frame on per frame driven, as a SLAM front end tracks
    a relocalisation once made."""
    own = own_frame is not None and (
        trajectories.sequence[reference] == trajectories.sequence[own_frame]
    )
    needed = own_run if own else other_run
    if tracking is not None and continues_loop(
        trajectories, reference, previous_loop, frames_since
    ):
        return min(needed, tracking)
    return needed
