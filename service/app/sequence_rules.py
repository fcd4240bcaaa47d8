"""When a robot's sequence is a loop on its own evidence, and which loop it may continue.

The rules :class:`~service.app.sequences.SequenceScorer` applies to its best place: the newest
frame must favour that place itself
(:data:`~service.ml.sequences.distinctiveness.NEWEST_Z_MIN`), and a place that continues the
robot's newest loop of its last few frames needs only the tracking margin
(:func:`newest_loop`, :func:`service.ml.sequences.margin_needed`). What fails is said in an
operator's words (:func:`sequence_shortfalls`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

from service.app.sequence_map import SequenceMap
from service.ml.sequences.distinctiveness import NEWEST_Z_MIN, TRACKING_DROPOUT
from service.storage import repository as repo


class TrackedLoop(NamedTuple):
    """The robot's newest loop within :data:`TRACKING_DROPOUT` frames: the map position it
    closed with and how many frames the robot has driven since (1: its previous frame)."""

    position: int
    frames_since: int


def newest_loop(
    view: SequenceMap, previous: Sequence[int], kept: dict[int, repo.Kept]
) -> TrackedLoop | None:
    """The loop a sequence may continue (loop tracking): the newest one closed by the robot's
    last :data:`TRACKING_DROPOUT` frames of this sequence (``previous``, oldest first), None
    when none closed one or the map no longer holds its frame."""
    for since, frame_id in enumerate(reversed(previous[-TRACKING_DROPOUT:]), start=1):
        loop_frame = kept[frame_id].loop_frame_id if frame_id in kept else None
        if loop_frame is not None:
            held = int(view.positions([loop_frame])[0])
            return TrackedLoop(held, since) if held >= 0 else None
    return None


def sequence_shortfalls(
    margin: float, needed: float, length: int, required: int, newest_z: float
) -> list[str]:
    """Why a sequence is not a loop on its own evidence, in an operator's words (empty: it
    passed): too small a margin over its best rival, too few frames aligned, or a newest frame
    that does not favour the place itself."""
    out = []
    if margin < needed:
        out.append(f"margin {margin:.2f} is below {needed:g}")
    if length < required:
        out.append(f"{length} frames aligned, {required} needed")
    if newest_z < NEWEST_Z_MIN:
        out.append(
            f"this frame's own evidence (aligned_z {newest_z:.2f}) is below {NEWEST_Z_MIN:g}"
        )
    return out
