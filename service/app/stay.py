"""A robot's current stay: its newest frames that still show the place it is asking about.

A robot that stands still (a train at a station, a robot waiting at a door) keeps sending frames
of one place. The recent-frame exclusion (``exclude_recent_frames`` / ``_seconds``) covers a
fixed window; once the robot has stood longer than that, its own frames from the start of the
stop fall outside it and verify perfectly: a loop with itself that odometry already knows, which
a SLAM back end must not receive. A loop with its own past needs evidence that the robot left
the place in between.

The stay is read from the robot's frames newest first, each scored against the query frame by
the calibrated score against impostors (each frame judged on its own, not as the best of a
search: no ``log10(frames)`` is added), with hysteresis, since a stopped robot's frames vary
(people pass, light changes):

- a frame scoring at least ``loop_score_min`` shows the query's place: the stay reaches it;
- a frame scoring below ``ELSEWHERE_SCORE`` (as alike as one pair of different places in ten)
  shows another place; ``BREAK`` of them in a row are evidence that the robot was elsewhere,
  and end the walk;
- a frame in between neither extends nor ends the stay, but ``FADE`` frames in a row that do not
  show the place end it too.

The stay is every frame up to the oldest one that showed the place; it never matches, and
everything older may. On an uncalibrated model version there is no score that says "as alike as
the same place" (the cosine of unrelated frames may exceed any fixed threshold), so no stay is
recognised and only the recent-frame exclusion applies.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from sqlalchemy.orm import Session

from service.app.filters import QueryFilter
from service.app.sequence_map import SequenceMap, SequenceMaps
from service.app.state import LoadedAtlas
from service.config import Settings
from service.storage import repository as repo

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


def robot_stay(
    session: Session,
    state: LoadedAtlas,
    maps: SequenceMaps,
    settings: Settings,
    query: np.ndarray,
    query_filter: QueryFilter,
) -> np.ndarray:
    """The asking robot's current stay for a query frame's vector: empty without a robot whose
    own frames may match, with ``exclude_stay`` off, or on an uncalibrated version."""
    robot = query_filter.robot_id
    if robot is None or query_filter.robots == "others" or not settings.exclude_stay:
        return np.zeros(0, np.int64)
    if not state.model.scores:
        return np.zeros(0, np.int64)  # no bar says "as alike as the same place"

    def scores(similarities: np.ndarray) -> np.ndarray:
        out = np.full(len(similarities), np.nan)
        known = np.isfinite(similarities)
        out[known] = np.asarray(state.model.score(similarities[known].astype(np.float64)))
        return out

    with maps.hold(session, state) as view:  # the index's vectors, cached per process
        return current_stay(
            own_frames=own_frames_of(session, state.atlas_id, robot),
            query=query,
            vectors=lambda ids: _held_vectors(view, ids),
            scores=scores,
            alike=settings.loop_score_min,
            elsewhere=min(ELSEWHERE_SCORE, settings.loop_score_min),
        )


def _held_vectors(view: SequenceMap, ids: np.ndarray) -> np.ndarray:
    """The map's vectors of ``ids``; rows of NaN for frames the index does not hold yet (a
    replica catching up): they show another place."""
    positions = view.positions(ids)
    rows = np.full((len(ids), view.vectors.shape[1]), np.nan, np.float32)
    held = positions >= 0
    rows[held] = view.lookup(positions[held])
    return rows


def behind_sequence(
    own_frames: Callable[[int, int], np.ndarray], excluded: np.ndarray, length: int
) -> np.ndarray:
    """The robot's own frames a sequence of ``length`` frames may not align with: its newest
    frames that the query already leaves out (recent frames, the stay) and the ``length - 1``
    before them. Each frame of a sequence has its own recent past: the oldest is ``length - 1``
    frames behind the newest, so the frames just behind it lie that much further back (a slowly
    moving robot's sequence otherwise aligns with its own trajectory just outside the window).

    ``own_frames``: as for :func:`current_stay`."""
    if length <= 1:
        return np.zeros(0, np.int64)
    newest = own_frames(0, len(excluded) + length - 1)
    left_out = np.isin(newest, excluded)
    prefix = len(newest) if left_out.all() else int(np.argmin(left_out))
    return newest[: prefix + length - 1]


def own_frames_of(
    session: Session, atlas_id: int, robot_id: str
) -> Callable[[int, int], np.ndarray]:
    """``(offset, limit)`` -> the robot's frame ids newest first, from the database."""

    def own_frames(offset: int, limit: int) -> np.ndarray:
        return repo.robot_frames_newest_first(
            session, atlas_id=atlas_id, robot_id=robot_id, offset=offset, limit=limit
        )

    return own_frames
