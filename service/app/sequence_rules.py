"""When a robot's sequence is a loop on its own evidence, and which loop it may continue.

The rules :class:`~service.app.sequences.SequenceScorer` applies to its best place: the newest
frame must favour that place itself
(:data:`~service.ml.sequences.distinctiveness.NEWEST_Z_MIN`), the place may not run ahead of
the robot's loops of its last few frames faster than the sequence's speeds carry a robot
(:func:`ran_ahead`), the newest few frames together may not look like a robot that has left the
map (:func:`service.ml.sequences.off_map.left_the_map`), and a place that continues the robot's
newest loop needs only the tracking margin (:func:`recent_loops`,
:func:`service.ml.sequences.margin_needed`). What fails is said in an operator's words
(:func:`sequence_shortfalls`). A sequence that passes while its newest frame's own evidence is
weak waits for a later frame answered at once (:func:`awaits_confirmation`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from service.app.sequence_map import SequenceMap
from service.ml.sequences import SequenceSettings, Trajectories, runs_ahead
from service.ml.sequences.distinctiveness import (
    NEWEST_Z_MIN,
    RUN_AHEAD_SLACK,
    TRACKING_DROPOUT,
)
from service.ml.sequences.off_map import OffMap
from service.storage import repository as repo


class TrackedLoop(NamedTuple):
    """A loop of one of the robot's last :data:`TRACKING_DROPOUT` frames: the map position it
    closed with and how many frames the robot has driven since (1: its previous frame)."""

    position: int
    frames_since: int


def recent_loops(
    view: SequenceMap, previous: Sequence[int], kept: dict[int, repo.Kept]
) -> list[TrackedLoop]:
    """The loops closed by the robot's last :data:`TRACKING_DROPOUT` frames of this sequence
    (``previous``, oldest first), newest first, up to the first whose frame the map no longer
    holds. The first is the loop a sequence may continue (loop tracking)."""
    loops = []
    for since, frame_id in enumerate(reversed(previous[-TRACKING_DROPOUT:]), start=1):
        loop_frame = kept[frame_id].loop_frame_id if frame_id in kept else None
        if loop_frame is not None:
            held = int(view.positions([loop_frame])[0])
            if held < 0:
                break
            loops.append(TrackedLoop(held, since))
    return loops


class RanAhead(NamedTuple):
    """A place further past one of the robot's recent loops than its speeds carry it."""

    frames: int  # map frames past the loop
    loop: TrackedLoop
    allowed: float  # the most the fastest speed carries the robot since, with the slack


def ran_ahead(
    trajectories: Trajectories,
    reference: int,
    loops: Sequence[TrackedLoop],
    settings: SequenceSettings,
) -> RanAhead | None:
    """The first of the robot's recent ``loops`` that map frame ``reference`` runs ahead of
    faster than the sequence's fastest speed (:func:`service.ml.sequences.runs_ahead`), None
    when it keeps pace with all of them."""
    speeds = settings.signed_speeds
    fastest, both_ways = float(np.max(np.abs(speeds))), bool(np.any(speeds < 0))
    for loop in loops:
        ahead = runs_ahead(
            trajectories, reference, loop.position, loop.frames_since, fastest, both_ways
        )
        if ahead is not None:
            return RanAhead(ahead, loop, fastest * loop.frames_since + RUN_AHEAD_SLACK)
    return None


def sequence_shortfalls(
    margin: float,
    needed: float,
    length: int,
    required: int,
    newest_z: float,
    outran: RanAhead | None = None,
    off_map: OffMap | None = None,
) -> list[str]:
    """Why a sequence is not a loop on its own evidence, in an operator's words (empty: it
    passed): too small a margin over its best rival, too few frames aligned, a newest frame
    that does not favour the place itself, a place running ahead of the robot's loops, or
    newest frames that together look like a robot off the map."""
    out = []
    if margin < needed:
        out.append(f"margin {margin:.2f} is below {needed:g}")
    if length < required:
        out.append(f"{length} frames aligned, {required} needed")
    if newest_z < NEWEST_Z_MIN:
        out.append(
            f"this frame's own evidence (aligned_z {newest_z:.2f}) is below {NEWEST_Z_MIN:g}"
        )
    if outran is not None:
        since = outran.loop.frames_since
        out.append(
            f"its place lies {outran.frames} map frames past the loop closed {since} "
            f"frame{'s' if since > 1 else ''} ago, more than the {outran.allowed:g} "
            "the sequence's speeds allow"
        )
    if off_map is not None:
        out.append(
            f"its last {off_map.frames} frames favour the place by a mean aligned_z of "
            f"{off_map.mean_z:.2f}, below the {off_map.needed:g} of a robot on the map "
            "(it may have left the mapped route)"
        )
    return out


def awaits_confirmation(newest_z: float, threshold: float) -> str | None:
    """Why a passed sequence's loop waits for a later frame of the robot to confirm it (its
    newest frame's own evidence is below ``threshold``, the setting ``sequence_confirm_z``), in
    an operator's words; None when the loop is answered at once."""
    if newest_z >= threshold:
        return None
    return (
        f"this frame's own evidence (aligned_z {newest_z:.2f}) is below {threshold:g}: the loop "
        "waits for a later frame with strong evidence of its own to confirm the place"
    )
