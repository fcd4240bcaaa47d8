"""A frame's stay along its robot's trajectory: the neighbouring frames that still show its
place, read with hysteresis on calibrated scores (see :mod:`service.app.stay` for why the
service leaves a robot's current stay out of its own loop candidates, and
:mod:`service.ml.inlier_threshold` for why calibration does not count a stay's frames as
impostors).

The walk reads frames in one direction (newest first for a query), each scored against the
frame whose stay is read:

- a frame scoring at least ``alike`` shows the place: the stay reaches it;
- a frame scoring below ``elsewhere`` shows another place; ``BREAK`` of them in a row are
  evidence that the robot was elsewhere, and end the walk;
- a frame in between neither extends nor ends the stay, but ``FADE`` frames in a row that do not
  show the place end it too.

The stay is every frame up to the farthest one that showed the place.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

# Below this score a frame shows another place (one impostor pair in ten is as alike).
ELSEWHERE_SCORE = 1.0
# Frames in a row showing another place that end a stay: one odd frame (a person passing in
# front of the camera) is not evidence that the robot left.
BREAK = 2
# Frames in a row that do not show the query's place (scores in between) that end it as well.
FADE = 8
# The walk reads the robot's frames in blocks, doubling from the first: a moving robot's stay
# ends within the first block, a stopped robot's is read up to MAX_FRAMES back.
FIRST_BLOCK = 32
MAX_FRAMES = 4096


def current_stay(
    *,
    own_frames: Callable[[int, int], np.ndarray],
    query: np.ndarray,
    vectors: Callable[[np.ndarray], np.ndarray],
    scores: Callable[[np.ndarray], np.ndarray],
    alike: float,
    elsewhere: float = ELSEWHERE_SCORE,
    max_frames: int = MAX_FRAMES,
) -> np.ndarray:
    """Ids of the robot's newest frames that form its current stay (newest first).

    Args:
        own_frames: ``(offset, limit)`` -> the robot's frame ids newest first (ids grow with
            arrival), ``limit`` of them from ``offset``.
        query: the query frame's (unit) vector.
        vectors: the index's stored vectors of frame ids (rows in the same order).
        scores: calibrated scores of cosine similarities to the query (NaN: unknown).
        alike: the score from which a frame shows the query's place.
        elsewhere: the score below which it shows another place.
        max_frames: read no further back than this many of the robot's frames.
    """
    seen: list[int] = []
    reach = 0  # frames of ``seen`` up to the oldest that showed the place
    elsewhere_run = 0
    offset, block = 0, FIRST_BLOCK
    while offset < max_frames:
        ids = own_frames(offset, min(block, max_frames - offset))
        if not len(ids):
            break
        similarity = scores(vectors(ids) @ np.asarray(query, np.float32))
        for frame_id, score in zip(ids.tolist(), similarity.tolist(), strict=True):
            seen.append(frame_id)
            if score >= alike:
                reach, elsewhere_run = len(seen), 0
                continue
            elsewhere_run = elsewhere_run + 1 if not score >= elsewhere else 0  # NaN: elsewhere
            if elsewhere_run >= BREAK or len(seen) - reach >= FADE:
                return np.array(seen[:reach], np.int64)
        offset += len(ids)
        block *= 2
    return np.array(seen[:reach], np.int64)


@dataclass(frozen=True)
class StayRule:
    """How frames are scored against the frame whose stay is read (calibrated scores of cosine
    similarities; NaN: unknown, another place) and the hysteresis's two bars."""

    scores: Callable[[np.ndarray], np.ndarray]
    alike: float
    elsewhere: float = ELSEWHERE_SCORE

    def stay(
        self,
        own_frames: Callable[[int, int], np.ndarray],
        query: np.ndarray,
        vectors: Callable[[np.ndarray], np.ndarray],
    ) -> np.ndarray:
        """:func:`current_stay` by this rule."""
        return current_stay(
            own_frames=own_frames,
            query=query,
            vectors=vectors,
            scores=self.scores,
            alike=self.alike,
            elsewhere=self.elsewhere,
        )
